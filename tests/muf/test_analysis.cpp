// Analysis formulas against hand-computed values (thesis §6.2–6.5, §4.5.1).
#include <gtest/gtest.h>

#include <cmath>
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

// Figure 6.1: T = 6, 10, 12, 15; C = 2, 4, 3, 4.
std::vector<TaskSpec> fig6_1() {
    return {task("t1", 6, 2), task("t2", 10, 4), task("t3", 12, 3), task("t4", 15, 4)};
}

std::vector<bool> members(std::initializer_list<bool> m) { return m; }

}  // namespace

TEST(MufAnalysis, UtilisationEq8) {
    const auto ts = fig6_1();
    // 1/3 + 2/5 + 1/4 + 4/15 = (20 + 24 + 15 + 16) / 60 = 75/60
    EXPECT_DOUBLE_EQ(utilisation(ts), 75.0 / 60.0);
    auto soft = ts;
    soft[3].effective = 2;  // reserved E instead of C
    EXPECT_DOUBLE_EQ(utilisation(soft), 67.0 / 60.0);  // 4/15 -> 2/15
}

TEST(MufAnalysis, RmBoundEq9) {
    EXPECT_DOUBLE_EQ(rm_bound(1), 1.0);
    EXPECT_NEAR(rm_bound(2), 2 * (std::sqrt(2.0) - 1), 1e-15);  // 0.8284
    EXPECT_NEAR(rm_bound(3), 3 * (std::cbrt(2.0) - 1), 1e-15);  // 0.7798
    EXPECT_NEAR(rm_bound(1000000), std::log(2.0), 1e-6);
    EXPECT_GT(rm_bound(2), rm_bound(3));
}

TEST(MufAnalysis, RmOrderShortestPeriodFirst) {
    std::vector<TaskSpec> ts = {task("a", 15, 1), task("b", 6, 1), task("c", 10, 1),
                                task("d", 6, 1)};
    EXPECT_EQ(rm_order(ts), (std::vector<std::size_t>{1, 3, 2, 0}));
}

TEST(MufAnalysis, CriticalSetsOfFigure6_1) {
    const auto ts = fig6_1();
    const auto rm = critical_set(ts, Policy::rm);
    // 0.733 <= W2 = 0.828, but 0.983 > W3 = 0.780: only t1, t2.
    EXPECT_EQ(rm.member, members({true, true, false, false}));
    EXPECT_DOUBLE_EQ(rm.utilisation, 44.0 / 60.0);
    EXPECT_DOUBLE_EQ(rm.bound, rm_bound(2));

    const auto muf = critical_set(ts, Policy::muf);
    // 0.983 <= 1 but 1.25 > 1: t1, t2, t3.
    EXPECT_EQ(muf.member, members({true, true, true, false}));
    EXPECT_DOUBLE_EQ(muf.utilisation, 59.0 / 60.0);

    // EDF in overload guarantees nobody.
    EXPECT_EQ(critical_set(ts, Policy::edf).member, members({false, false, false, false}));
    const std::vector<TaskSpec> light = {task("a", 4, 2), task("b", 8, 4)};  // U = 1 exactly
    EXPECT_EQ(critical_set(light, Policy::edf).member, members({true, true}));
    EXPECT_EQ(critical_set(light, Policy::muf).member, members({true, true}));
    EXPECT_EQ(critical_set(light, Policy::rm).member, members({true, false}));
}

TEST(MufAnalysis, MufCriticalSetIsPrefixAndHonoursExplicitCriticality) {
    auto ts = fig6_1();
    // t4 declared important: it is considered first, then RM order.
    ts[3].crit = 6;
    const auto set = critical_set(ts, Policy::muf);
    // t4 (16/60) + t1 (20/60) + t2 (24/60) = 1.0; t3 no longer fits.
    EXPECT_EQ(set.member, members({true, true, false, true}));
    EXPECT_NEAR(set.utilisation, 1.0, 1e-12);
    // A shorter deadline counts with C/D.
    std::vector<TaskSpec> d = {task("a", 10, 4), task("b", 10, 4)};
    d[1].deadline = 5;
    // b (deadline 5) comes first in rm_order and uses 0.8; a no longer fits.
    EXPECT_EQ(critical_set(d, Policy::muf).member, members({false, true}));
}

TEST(MufAnalysis, RmCriticalSetIsSubsetOfMuf) {
    const std::vector<std::vector<TaskSpec>> sets = {
        fig6_1(),
        {task("a", 3, 1), task("b", 5, 2), task("c", 7, 1), task("d", 11, 3)},
        {task("a", 2, 1), task("b", 3, 1), task("c", 100, 1)}};
    for (const auto& ts : sets) {
        const auto rm = critical_set(ts, Policy::rm);
        const auto muf = critical_set(ts, Policy::muf);
        for (std::size_t i = 0; i < ts.size(); ++i) {
            if (rm.member[i]) {
                EXPECT_TRUE(muf.member[i]) << ts[i].name;
            }
        }
    }
}

TEST(MufAnalysis, MufAssignmentOfFigure6_1) {
    const auto ts = fig6_1();
    const auto a = assign(ts, Policy::muf);
    EXPECT_EQ(a.crit, (std::vector<int>{5, 5, 5, 3}));
    EXPECT_EQ(a.uprio, (std::vector<int>{0, 0, 0, 0}));  // no flows: first come, first served
    const std::vector<Flow> flows = {{3, 0}};                // t4 feeds t1
    // t1 waits for its producer t4: t2, t3, t4, t1.
    EXPECT_EQ(assign(ts, Policy::muf, flows).uprio, (std::vector<int>{1, 4, 3, 2}));
    EXPECT_TRUE(a.uses_deadline);

    const auto rm = assign(ts, Policy::rm);
    EXPECT_EQ(rm.crit, (std::vector<int>{62, 61, 60, 59}));
    EXPECT_FALSE(rm.uses_deadline);

    const auto edf = assign(ts, Policy::edf);
    EXPECT_EQ(edf.crit, (std::vector<int>{5, 5, 5, 5}));
}

TEST(MufAnalysis, RmAssignmentEqualPeriodsShareCriticality) {
    std::vector<TaskSpec> ts = {task("a", 10, 1), task("b", 5, 1), task("c", 10, 1)};
    EXPECT_EQ(assign(ts, Policy::rm).crit, (std::vector<int>{61, 62, 61}));
}

TEST(MufAnalysis, DataFlowUserPriorities) {
    // Figure 6.3: tau_a (sensor) -> x -> tau_b. Equal periods: the producer ranks higher.
    std::vector<TaskSpec> ts = {task("b", 50, 5), task("a", 50, 5)};
    const std::vector<Flow> ab = {{1, 0}};
    EXPECT_EQ(data_flow_user_priorities(ts, ab), (std::vector<int>{1, 2}));
    EXPECT_EQ(data_flow_user_priorities(ts, {}), (std::vector<int>{2, 1}));  // file order

    // The flow beats RM order: c (T=10) consumes a's output (T=50).
    std::vector<TaskSpec> chain = {task("a", 50, 1), task("b", 20, 1), task("c", 10, 1)};
    const std::vector<Flow> ac = {{0, 2}};
    EXPECT_EQ(data_flow_user_priorities(chain, ac), (std::vector<int>{2, 3, 1}));
    // rm order is c, b, a; c waits for its producer a, so b, a, c.

    // A cycle a -> b -> a is broken at the shortest period.
    std::vector<TaskSpec> cyc = {task("a", 20, 1), task("b", 10, 1)};
    const std::vector<Flow> loop = {{0, 1}, {1, 0}};
    EXPECT_EQ(data_flow_user_priorities(cyc, loop), (std::vector<int>{1, 2}));

    // Figure 3.7's loop at one rate, robot listed first: jtraj -> jpid <-> robot.
    // The cycle is broken where the data has arrived: jpid (fed by jtraj)
    // before the robot, so jtraj, jpid, robot.
    std::vector<TaskSpec> fig = {task("robot", 2, 1), task("jpid", 2, 1), task("jtraj", 2, 1)};
    const std::vector<Flow> loop37 = {{2, 1}, {1, 0}, {0, 1}};
    EXPECT_EQ(data_flow_user_priorities(fig, loop37), (std::vector<int>{1, 2, 3}));

    // Explicit user priorities override.
    ts[0].uprio = 9;
    EXPECT_EQ(data_flow_user_priorities(ts, ab), (std::vector<int>{9, 2}));
}

TEST(MufAnalysis, UrgencyEncodingFigure6_2) {
    const UrgencyEncoding enc;  // c = 6, d = 20, u = 6
    EXPECT_EQ(enc.infinity_ticks(), 1048575);
    EXPECT_EQ(dynamic_priority(enc, 0), 1048575u);
    EXPECT_EQ(dynamic_priority(enc, 10), 1048565u);
    EXPECT_EQ(dynamic_priority(enc, -5), 1048575u);       // already late: most urgent
    EXPECT_EQ(dynamic_priority(enc, 1048575), 0u);        // 2^d - 1 ticks away: infinity
    EXPECT_EQ(dynamic_priority(enc, 5000000), 0u);
    EXPECT_EQ(dynamic_priority(enc, std::nullopt), 0u);   // no deadline

    EXPECT_EQ(urgency(enc, 5, 10, 3), (5ull << 26) | (1048565ull << 6) | 3ull);
    EXPECT_EQ(urgency(enc, 99, std::nullopt, 99), (63ull << 26) | 63ull);  // clamped

    // Criticality dominates the deadline, the deadline dominates the user priority.
    EXPECT_GT(urgency(enc, 5, 1000, 0), urgency(enc, 3, 0, 63));
    EXPECT_GT(urgency(enc, 5, 10, 0), urgency(enc, 5, 11, 63));
    EXPECT_GT(urgency(enc, 5, 10, 2), urgency(enc, 5, 10, 1));

    const UrgencyEncoding small{2, 3, 2};  // infinity at 7 ticks
    EXPECT_EQ(urgency(small, 1, 2, 1), (1u << 5) | (5u << 2) | 1u);
    EXPECT_EQ(urgency(small, 1, 7, 1), (1u << 5) | 1u);
}

TEST(MufAnalysis, CriticalityFromFrequencySection4_5_1) {
    // MINFREQ 0.1, MAXFREQ 1000: four decades over 61 steps.
    EXPECT_EQ(criticality_from_frequency(0.05, 0.1, 1000), 1);
    EXPECT_EQ(criticality_from_frequency(0.1, 0.1, 1000), 1);
    EXPECT_EQ(criticality_from_frequency(1, 0.1, 1000), 16);    // 1 + floor(61/4)
    EXPECT_EQ(criticality_from_frequency(10, 0.1, 1000), 31);   // 1 + floor(30.5)
    EXPECT_EQ(criticality_from_frequency(25, 0.1, 1000), 37);
    EXPECT_EQ(criticality_from_frequency(1000, 0.1, 1000), 62);
    EXPECT_EQ(criticality_from_frequency(5000, 0.1, 1000), 62);
    // A narrow range separates nearby frequencies.
    EXPECT_LT(criticality_from_frequency(25, 10, 100), criticality_from_frequency(27, 10, 100));
    // Default MINFREQ = MAXFREQ = 1 Hz.
    EXPECT_EQ(criticality_from_frequency(1, 1, 1), 1);
    EXPECT_EQ(criticality_from_frequency(2, 1, 1), 62);
    // Monotone.
    int last = 0;
    for (double f = 0.05; f < 2000; f *= 1.07) {
        const int c = criticality_from_frequency(f, 0.1, 1000);
        EXPECT_GE(c, last);
        EXPECT_GE(c, 1);
        EXPECT_LE(c, 62);
        last = c;
    }
}

TEST(MufAnalysis, ServerSizesEq12_15_22_25) {
    // No periodic load: the whole CPU.
    EXPECT_DOUBLE_EQ(server_max_size(Server::rds, 0), 1.0);
    EXPECT_DOUBLE_EQ(server_max_size(Server::rss, 0), 1.0);
    EXPECT_DOUBLE_EQ(server_max_size(Server::mds, 0), 1.0);
    EXPECT_DOUBLE_EQ(server_max_size(Server::mss, 0), 1.0);
    // RM servers vanish at U_p = ln 2, MUF servers at 1.
    EXPECT_NEAR(server_max_size(Server::rds, std::log(2.0)), 0, 1e-15);
    EXPECT_NEAR(server_max_size(Server::rss, std::log(2.0)), 0, 1e-15);
    EXPECT_DOUBLE_EQ(server_max_size(Server::mds, 1), 0);
    EXPECT_DOUBLE_EQ(server_max_size(Server::mss, 1), 0);
    // U_p = 0.5 by hand.
    const double e = std::exp(-0.5);
    EXPECT_DOUBLE_EQ(server_max_size(Server::rds, 0.5), (2 * e - 1) / (2 - e));
    EXPECT_DOUBLE_EQ(server_max_size(Server::rss, 0.5), 2 * e - 1);
    EXPECT_DOUBLE_EQ(server_max_size(Server::mds, 0.5), 0.25);
    EXPECT_DOUBLE_EQ(server_max_size(Server::mss, 0.5), 1.0 / 3.0);
}

TEST(MufAnalysis, ServerBoundsEq11_14_21_24_23_26) {
    for (Server s : {Server::rds, Server::rss, Server::mds, Server::mss})
        for (double up : {0.1, 0.3, 0.5, 0.6}) {
            if ((s == Server::rds || s == Server::rss) && up >= std::log(2.0)) continue;
            const double us = server_max_size(s, up);
            EXPECT_NEAR(server_periodic_bound(s, us), up, 1e-12) << to_string(s);
            EXPECT_NEAR(server_schedulable_bound(s, us), up + us, 1e-12) << to_string(s);
        }
    EXPECT_DOUBLE_EQ(server_schedulable_bound(Server::mds, 0.25), 0.75);  // eq. 23
    EXPECT_DOUBLE_EQ(server_schedulable_bound(Server::mss, 1.0 / 3.0), 0.5 + 1.0 / 3.0);
}

TEST(MufAnalysis, ServerComparisonSection6_5_3) {
    for (double up = 0.01; up < 0.69; up += 0.01) {
        // MSS is the largest server; MDS always beats RDS.
        EXPECT_GT(server_max_size(Server::mss, up), server_max_size(Server::mds, up));
        EXPECT_GT(server_max_size(Server::mss, up), server_max_size(Server::rss, up));
        EXPECT_GT(server_max_size(Server::mds, up), server_max_size(Server::rds, up));
    }
    // MDS beats RSS for U_p > 0.42 (and not below).
    EXPECT_LT(server_max_size(Server::mds, 0.40), server_max_size(Server::rss, 0.40));
    EXPECT_GT(server_max_size(Server::mds, 0.44), server_max_size(Server::rss, 0.44));
}

TEST(MufAnalysis, RmServersForMTasksEq10_13) {
    // m = 2 is exactly the MUF servers' derivation (eq. 21 from eq. 10, eq. 24 from eq. 13).
    for (double us : {0.1, 0.25, 0.5}) {
        EXPECT_NEAR(rm_server_periodic_bound(Server::rds, us, 2),
                    server_periodic_bound(Server::mds, us), 1e-12);
        EXPECT_NEAR(rm_server_periodic_bound(Server::rss, us, 2),
                    server_periodic_bound(Server::mss, us), 1e-12);
        // The limit m -> infinity is eq. 11 / eq. 14.
        EXPECT_NEAR(rm_server_periodic_bound(Server::rds, us, 1000000),
                    server_periodic_bound(Server::rds, us), 1e-6);
        EXPECT_NEAR(rm_server_periodic_bound(Server::rss, us, 1000000),
                    server_periodic_bound(Server::rss, us), 1e-6);
        // Inverse.
        for (std::size_t m : {2u, 3u, 5u}) {
            const double up = rm_server_periodic_bound(Server::rds, us, m);
            EXPECT_NEAR(rm_server_max_size(Server::rds, up, m), us, 1e-12);
            const double up2 = rm_server_periodic_bound(Server::rss, us, m);
            EXPECT_NEAR(rm_server_max_size(Server::rss, up2, m), us, 1e-12);
        }
    }
    // m = 3, U_rds = 0.5: 2 * ((2.5 / 2)^(1/2) - 1).
    EXPECT_NEAR(rm_server_periodic_bound(Server::rds, 0.5, 3), 2 * (std::sqrt(1.25) - 1), 1e-15);
}

TEST(MufAnalysis, SoftTaskEffectiveExecutionTimeFigure6_6) {
    // T = 12, C = 10, 90 % of cycles done within 6.
    ExecutionProfile p;
    p.bin_width = 1;
    p.counts = {0, 0, 10, 30, 30, 20, 5, 3, 1, 1};
    EXPECT_EQ(p.total(), 100u);
    EXPECT_DOUBLE_EQ(p.worst_case(), 10);
    EXPECT_DOUBLE_EQ(p.psi(6), 0.9);
    EXPECT_DOUBLE_EQ(p.psi(5.5), 0.7);
    EXPECT_DOUBLE_EQ(p.psi(10), 1.0);
    EXPECT_DOUBLE_EQ(p.effective(0.9), 6);   // H = 0.9 -> E = 6
    EXPECT_DOUBLE_EQ(p.effective(1.0), 10);  // hard: E = C
    EXPECT_DOUBLE_EQ(p.effective(0.95), 7);
    TaskSpec t = task("soft", 12, 10);
    t.effective = p.effective(0.9);
    EXPECT_DOUBLE_EQ(utilisation(std::span(&t, 1)), 0.5);  // instead of 0.83
    EXPECT_EQ(guaranteed_one_in(10, 6), 2u);  // 10 <= 2 * 6
    EXPECT_EQ(guaranteed_one_in(12, 6), 2u);
    EXPECT_EQ(guaranteed_one_in(12.5, 6), 3u);
    EXPECT_EQ(guaranteed_one_in(6, 6), 1u);
    EXPECT_EQ(guaranteed_one_in(6, 0), 0u);

    ExecutionProfile wide{0.5, {0, 4, 4, 2}};  // times in (0.5,1], (1,1.5], (1.5,2]
    EXPECT_DOUBLE_EQ(wide.effective(0.4), 1.0);
    EXPECT_DOUBLE_EQ(wide.effective(0.8), 1.5);
    EXPECT_DOUBLE_EQ(wide.worst_case(), 2.0);
}

TEST(MufAnalysis, EffectiveExecutionTimeFromSamples) {
    const std::vector<double> s = {10, 1, 9, 2, 8, 3, 7, 4, 6, 5};
    EXPECT_DOUBLE_EQ(effective_execution_time(s, 0.9), 9);
    EXPECT_DOUBLE_EQ(effective_execution_time(s, 1.0), 10);
    EXPECT_DOUBLE_EQ(effective_execution_time(s, 0.5), 5);
    EXPECT_DOUBLE_EQ(effective_execution_time(s, 0.55), 6);
    EXPECT_DOUBLE_EQ(effective_execution_time({}, 0.9), 0);
}

TEST(MufAnalysis, PolicyNames) {
    EXPECT_EQ(parse_policy("MUF"), Policy::muf);
    EXPECT_EQ(parse_policy("rm"), Policy::rm);
    EXPECT_EQ(parse_policy("edf"), Policy::edf);
    EXPECT_EQ(parse_policy("fifo"), std::nullopt);
    EXPECT_EQ(to_string(Policy::edf), "edf");
}
