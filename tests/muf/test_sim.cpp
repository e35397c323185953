// The simulator against Figure 6.1 and hand-traced schedules (thesis §6.2).
#include <gtest/gtest.h>

#include <stdexcept>
#include <vector>

#include "chimera/muf.hpp"

using namespace chimera::muf;

namespace {

TaskSpec task(const char* name, double period, double wcet) {
    TaskSpec t;
    t.name = name;
    t.period = period;
    t.wcet = wcet;
    return t;
}

std::vector<TaskSpec> fig6_1() {
    return {task("t1", 6, 2), task("t2", 10, 4), task("t3", 12, 3), task("t4", 15, 4)};
}

std::vector<std::size_t> misses(const SimResult& r) {
    std::vector<std::size_t> m;
    for (const auto& s : r.stats) m.push_back(s.missed);
    return m;
}

using V = std::vector<std::size_t>;

struct Slice {
    std::size_t task;
    std::int64_t begin, end;
    bool operator==(const Slice&) const = default;
};

std::vector<Slice> slices(const SimResult& r) {
    std::vector<Slice> s;
    for (const auto& x : r.timeline) s.push_back({x.task, x.begin, x.end});
    return s;
}

}  // namespace

// (a) RM: only the two longest-period tasks miss; the RM critical set {t1, t2} never does.
TEST(MufSim, Figure6_1RateMonotonic) {
    for (LateJob late : {LateJob::abort, LateJob::finish}) {
        const auto r = simulate(fig6_1(), Policy::rm, late, 30);
        EXPECT_EQ(misses(r), (V{0, 0, 2, 2}));
    }
    EXPECT_EQ(misses(simulate(fig6_1(), Policy::rm, LateJob::abort, 60)), (V{0, 0, 2, 4}));
    // RM is static priority: t1 runs at every release, t2 right after it.
    const auto r = simulate(fig6_1(), Policy::rm, LateJob::abort, 12);
    EXPECT_EQ(slices(r), (std::vector<Slice>{{0, 0, 2}, {1, 2, 6}, {0, 6, 8}, {2, 8, 10}, {1, 10, 12}}));
}

// (b) EDF: t1 and t2, tasks of the critical set, fail; t3 and t4 do not.
TEST(MufSim, Figure6_1EarliestDeadlineFirst) {
    for (LateJob late : {LateJob::abort, LateJob::finish}) {
        const auto r = simulate(fig6_1(), Policy::edf, late, 30);
        EXPECT_EQ(misses(r), (V{2, 2, 0, 0}));
    }
    EXPECT_EQ(misses(simulate(fig6_1(), Policy::edf, LateJob::abort, 60)), (V{4, 4, 0, 0}));
    const auto set = critical_set(fig6_1(), Policy::muf);
    const auto r = simulate(fig6_1(), Policy::edf, LateJob::abort, 30);
    bool critical_missed = false;
    for (std::size_t i = 0; i < 4; ++i) critical_missed |= set.member[i] && r.stats[i].missed > 0;
    EXPECT_TRUE(critical_missed);
    // The first miss: t2's job released at 10 (deadline 20) loses to earlier deadlines.
    const SimJob* first = nullptr;
    for (const auto& j : r.jobs)
        if (j.missed && (!first || j.deadline < first->deadline)) first = &j;
    ASSERT_NE(first, nullptr);
    EXPECT_EQ(first->task, 1u);  // t2's job released at 10, deadline 20
    EXPECT_EQ(first->deadline, 20);
    EXPECT_EQ(first->executed, 3);  // one tick short
}

// (c) MUF: only t4, the task outside the critical set, misses.
TEST(MufSim, Figure6_1MaximumUrgencyFirst) {
    for (LateJob late : {LateJob::abort, LateJob::finish}) {
        for (std::int64_t until : {30, 60, 120}) {
            const auto r = simulate(fig6_1(), Policy::muf, late, until);
            const auto m = misses(r);
            EXPECT_EQ(m[0] + m[1] + m[2], 0u) << until;
            EXPECT_GT(m[3], 0u) << until;
        }
    }
    EXPECT_EQ(misses(simulate(fig6_1(), Policy::muf, LateJob::abort, 30)), (V{0, 0, 0, 2}));
    // Hand trace of the first 12 ticks: EDF among crit 5, t4 (crit 3) only in idle time.
    const auto r = simulate(fig6_1(), Policy::muf, LateJob::abort, 12);
    EXPECT_EQ(slices(r), (std::vector<Slice>{
                             {0, 0, 2}, {1, 2, 6}, {2, 6, 9}, {0, 9, 11}, {1, 11, 12}}));
}

TEST(MufSim, SingleTaskHandTrace) {
    const std::vector<SimTask> ts = {{"a", 5, 2, 0, 0, 5, 0}};
    SimOptions o;
    o.until = 10;
    const auto r = simulate(ts, o);
    ASSERT_EQ(r.jobs.size(), 2u);
    EXPECT_EQ(r.jobs[0].release, 0);
    EXPECT_EQ(r.jobs[0].start, 0);
    EXPECT_EQ(r.jobs[0].finish, 2);
    EXPECT_EQ(r.jobs[0].deadline, 5);
    EXPECT_EQ(r.jobs[1].release, 5);
    EXPECT_EQ(r.jobs[1].start, 5);
    EXPECT_EQ(r.jobs[1].finish, 7);
    EXPECT_EQ(r.stats[0].released, 2u);
    EXPECT_EQ(r.stats[0].completed, 2u);
    EXPECT_EQ(r.stats[0].missed, 0u);
}

TEST(MufSim, PreemptionHandTrace) {
    // RM: A (T 4, C 1) preempts B (T 10, C 5) at 4.
    const std::vector<TaskSpec> ts = {task("A", 4, 1), task("B", 10, 5)};
    const auto r = simulate(ts, Policy::rm, LateJob::abort, 10);
    EXPECT_EQ(slices(r), (std::vector<Slice>{{0, 0, 1}, {1, 1, 4}, {0, 4, 5}, {1, 5, 7}, {0, 8, 9}}));
    const SimJob& b = r.jobs[1];
    EXPECT_EQ(b.task, 1u);
    EXPECT_EQ(b.start, 1);
    EXPECT_EQ(b.finish, 7);
    EXPECT_EQ(b.preemptions, 1);
    EXPECT_EQ(r.stats[1].preemptions, 1u);
    EXPECT_EQ(r.stats[0].preemptions, 0u);
}

TEST(MufSim, LateJobSemantics) {
    // One task that needs 5 every 4.
    const std::vector<SimTask> ts = {{"over", 4, 5, 0, 0, 5, 0}};
    SimOptions o;
    o.until = 12;
    o.late = LateJob::abort;
    auto r = simulate(ts, o);
    ASSERT_EQ(r.jobs.size(), 3u);
    for (const auto& j : r.jobs) {
        EXPECT_TRUE(j.missed);
        EXPECT_TRUE(j.aborted);
        EXPECT_EQ(j.finish, -1);
        EXPECT_EQ(j.executed, 4);
    }
    EXPECT_EQ(r.stats[0].aborted, 3u);

    o.late = LateJob::finish;
    r = simulate(ts, o);
    ASSERT_EQ(r.jobs.size(), 3u);
    EXPECT_EQ(r.jobs[0].finish, 5);   // late by 1
    EXPECT_EQ(r.jobs[1].start, 5);
    EXPECT_EQ(r.jobs[1].finish, 10);  // deadline 8
    EXPECT_EQ(r.jobs[2].start, 10);
    EXPECT_EQ(r.jobs[2].finish, -1);  // still running at 12, its deadline
    EXPECT_EQ(r.stats[0].missed, 3u);
    EXPECT_EQ(r.stats[0].completed, 2u);
    EXPECT_EQ(r.stats[0].aborted, 0u);
}

TEST(MufSim, MufTieBreaking) {
    // Same criticality and deadline: user priority decides, then first come first served.
    std::vector<SimTask> ts = {{"a", 10, 2, 0, 0, 5, 1}, {"b", 10, 2, 0, 0, 5, 2}};
    SimOptions o;
    o.until = 10;
    auto r = simulate(ts, o);
    EXPECT_EQ(r.timeline.front().task, 1u);
    ts[1].uprio = 1;
    r = simulate(ts, o);
    EXPECT_EQ(r.timeline.front().task, 0u);  // equal: file order
    ts[0].phase = 1;                          // a later: b first, a once b is done
    ts[0].deadline = 9;                       // same absolute deadline 10
    r = simulate(ts, o);
    EXPECT_EQ(slices(r), (std::vector<Slice>{{1, 0, 2}, {0, 2, 4}}));
    // Criticality beats an earlier deadline.
    ts = {{"hi", 10, 3, 0, 0, 6, 0}, {"lo", 10, 3, 3, 0, 5, 0}};
    o.late = LateJob::finish;
    r = simulate(ts, o);
    EXPECT_EQ(slices(r), (std::vector<Slice>{{0, 0, 3}, {1, 3, 6}}));
    EXPECT_EQ(r.stats[1].missed, 1u);  // lo's deadline 3 passed while hi ran
}

TEST(MufSim, DataFlowOrderAmongEqualTasks) {
    // Figure 6.3: tau_a feeds tau_b, T = 50, C = 5 each: a runs first.
    std::vector<TaskSpec> ts = {task("b", 50, 5), task("a", 50, 5)};
    const std::vector<Flow> flows = {{1, 0}};
    for (Policy p : {Policy::rm, Policy::edf, Policy::muf}) {
        const auto r = simulate(ts, p, LateJob::abort, 50, flows);
        ASSERT_EQ(r.timeline.size(), 2u);
        EXPECT_EQ(r.timeline[0].task, 1u) << to_string(p);
    }
}

TEST(MufSim, BadInputIsRejected) {
    std::vector<SimTask> ts = {{"z", 0, 1, 0, 0, 5, 0}};
    EXPECT_THROW(simulate(ts, SimOptions{}), std::invalid_argument);
    std::vector<TaskSpec> frac = {task("f", 2.5, 1)};
    EXPECT_THROW(simulate(frac, Policy::muf, LateJob::abort, 10), std::invalid_argument);
}

TEST(MufSim, GanttChart) {
    const std::vector<SimTask> ts = {{"A", 4, 1, 0, 0, 62, 0}, {"B", 10, 5, 0, 0, 61, 0}};
    SimOptions o;
    o.until = 10;
    o.use_deadline = false;
    const auto r = simulate(ts, o);
    EXPECT_EQ(gantt(ts, r),
              "     |0         \n"
              "A    |#...#...#.\n"
              "B    |-###-##...\n");
    // Misses are marked on the last tick the job had.
    const std::vector<SimTask> over = {{"X", 4, 5, 0, 0, 5, 0}};
    o.until = 8;
    EXPECT_EQ(gantt(over, simulate(over, o)),
              "     |0       \n"
              "X    |###!###!\n");
}
