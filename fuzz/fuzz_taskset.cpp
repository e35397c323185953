// fuzz/fuzz_taskset.cpp — the task-set reader (chimsched's files) on arbitrary text.
//
// Invariants: only cfg::ParseError escapes, with FILE:LINE; what the reader
// accepts chimsched can analyse: finite times (PERIOD > 0, WCET >= 0,
// EFFECTIVE <= WCET), CRIT 1..62, UPRIO 0..63, names unique, flows between
// two different known tasks; and the a-priori assignment of every policy
// runs on it, giving each task one criticality in 0..63.
#include <cmath>
#include <set>

#include "chimera/cfg.hpp"
#include "chimera/muf/analysis.hpp"
#include "chimera/muf/taskset.hpp"
#include "harness.hpp"

using namespace chimera;
using fuzz::require;

namespace {

void check_set(const muf::TaskSet& set) {
    require(!set.tasks.empty(), "a task set without tasks accepted");
    std::set<std::string> names;
    for (const muf::TaskSpec& t : set.tasks) {
        require(names.insert(t.name).second, "task " + t.name + " twice");
        require(std::isfinite(t.period) && t.period > 0 && std::isfinite(t.wcet) && t.wcet >= 0 &&
                    std::isfinite(t.deadline) && t.deadline >= 0 && std::isfinite(t.effective) &&
                    t.effective >= 0 && t.effective <= t.wcet,
                "task " + t.name + ": times accepted out of range");
        require(!t.crit || (*t.crit >= 1 && *t.crit <= 62), "task " + t.name + ": CRIT outside 1..62");
        require(!t.uprio || (*t.uprio >= 0 && *t.uprio <= 63), "task " + t.name + ": UPRIO outside 0..63");
    }
    for (const muf::Flow& f : set.flows)
        require(f.producer < set.tasks.size() && f.consumer < set.tasks.size() && f.producer != f.consumer,
                "a flow to an unknown task or to itself");
    for (muf::Policy policy : {muf::Policy::rm, muf::Policy::edf, muf::Policy::muf}) {
        const muf::Assignment a = muf::assign(set.tasks, policy, set.flows);
        require(a.crit.size() == set.tasks.size() && a.uprio.size() == set.tasks.size() &&
                    a.critical.member.size() == set.tasks.size(),
                "the assignment does not cover every task");
        for (int c : a.crit) require(c >= 0 && c <= 63, "a criticality outside 0..63");
    }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const std::string file = "fuzz.tasks";
    muf::TaskSet set;
    if (fuzz::accepted<cfg::ParseError>(file, [&] { set = muf::parse_task_set(fuzz::text_of(data, size), file); }))
        check_set(set);
    return 0;
}
