// Task-set files: see include/chimera/muf/taskset.hpp.
#include "chimera/muf/taskset.hpp"

#include <cmath>

#include "chimera/cfg.hpp"

namespace chimera::muf {

namespace {

TaskSet parse(cfg::Reader& in) {
    TaskSet set;
    set.file = in.file();
    const auto find = [&](const cfg::Line& line, const std::string& name) {
        for (std::size_t i = 0; i < set.tasks.size(); ++i)
            if (set.tasks[i].name == name) return i;
        in.fail(line, "FLOW names unknown task " + name + " (tasks must be defined before FLOW)");
    };
    while (in.peek() != nullptr) {
        const cfg::Line line = in.expect_one_of({"TASK", "FLOW"});
        if (line.keyword == "FLOW") {
            in.require_args(line, 2);
            const std::size_t p = find(line, line.args[0]);
            const std::size_t c = find(line, line.args[1]);
            if (p == c) in.fail(line, "FLOW from task " + line.args[0] + " to itself");
            set.flows.push_back({p, c});
            continue;
        }
        if (line.args.empty()) in.fail(line, "TASK needs a name");
        TaskSpec t;
        t.name = line.args[0];
        for (const auto& other : set.tasks)
            if (other.name == t.name) in.fail(line, "task " + t.name + " is defined twice");
        bool have_period = false, have_wcet = false;
        std::vector<std::string> seen;
        for (std::size_t k = 1; k < line.args.size(); k += 2) {
            const std::string& key = line.args[k];
            if (k + 1 >= line.args.size())
                in.fail(line, "task " + t.name + ": " + key + " needs a value");
            for (const auto& s : seen)
                if (s == key) in.fail(line, "task " + t.name + ": " + key + " given twice");
            seen.push_back(key);
            const std::string what = "task " + t.name + " " + key;
            if (key == "PERIOD") {
                t.period = in.to_double(line, k + 1, what);
                if (!(t.period > 0)) in.fail(line, what + " must be > 0");
                have_period = true;
            } else if (key == "WCET") {
                t.wcet = in.to_double(line, k + 1, what);
                if (!(t.wcet >= 0)) in.fail(line, what + " must be >= 0");
                have_wcet = true;
            } else if (key == "DEADLINE") {
                t.deadline = in.to_double(line, k + 1, what);
                if (!(t.deadline > 0)) in.fail(line, what + " must be > 0");
            } else if (key == "EFFECTIVE") {
                t.effective = in.to_double(line, k + 1, what);
                if (!(t.effective > 0)) in.fail(line, what + " must be > 0");
            } else if (key == "CRIT") {
                const auto v = in.to_int(line, k + 1, what);
                if (v < 1 || v > 62) in.fail(line, what + " must be 1..62 (0 and 63 are reserved)");
                t.crit = static_cast<int>(v);
            } else if (key == "UPRIO") {
                const auto v = in.to_int(line, k + 1, what);
                if (v < 0 || v > 63) in.fail(line, what + " must be 0..63");
                t.uprio = static_cast<int>(v);
            } else {
                in.fail(line, "task " + t.name + ": unknown option " + key +
                                  " (expected PERIOD, WCET, CRIT, UPRIO, DEADLINE or EFFECTIVE)");
            }
        }
        if (!have_period) in.fail(line, "task " + t.name + " has no PERIOD");
        if (!have_wcet) in.fail(line, "task " + t.name + " has no WCET");
        if (t.effective > t.wcet)
            in.fail(line, "task " + t.name + ": EFFECTIVE is larger than WCET");
        set.tasks.push_back(std::move(t));
    }
    in.expect_end();
    if (set.tasks.empty()) in.fail(in.end_line(), "no TASK in the file");
    return set;
}

}  // namespace

TaskSet read_task_set(const std::string& path) {
    auto in = cfg::Reader::from_file(path);
    return parse(in);
}

TaskSet parse_task_set(std::string_view text, const std::string& name) {
    auto in = cfg::Reader::from_string(text, name);
    return parse(in);
}

}  // namespace chimera::muf
