// The deterministic parts of issue #29.6 ("a lost link never moves the arm
// fast"), exactly, with a clock the test moves:
//  - StaleHoldPid: while stale (or the configuration illegal, must_hold) the
//    output and the integral stay exactly what they were; on recovery the integral restarts and the output slews from
//    the held value to the PID's without exceeding the rate, then follows it;
//  - SlewLimiter reaches its target in the expected number of steps, never
//    past it, never faster than the rate;
//  - JointLimiter: the torque rate, the torque-speed envelope, the counts;
//  - Trajectory::segment_at / set_point / set_duration: what trajgen re-anchors
//    with (a segment from the measured position to the via point that was
//    under way, with its full duration);
//  - none of the per-cycle calls touches the heap.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "alloc_counter.hpp"
#include "robotics/limits.hpp"
#include "robotics/pid.hpp"
#include "robotics/stale.hpp"
#include "robotics/trajectory.hpp"

namespace rb = chimera::robotics;
using Eigen::VectorXd;

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kDt = 1.0 / 512;  // a power of two: rate * dt is exact

VectorXd v2(double a, double b) {
    VectorXd v(2);
    v << a, b;
    return v;
}

rb::Pid two_joint_pid() {
    return rb::Pid(2, rb::PidGains{v2(400, 800), v2(2000, 4000), v2(60, 120), v2(0.5, 0.5), v2(97.6, 186.4)});
}

}  // namespace

TEST(StaleWatch, TellsTheFirstFreshCycleAfterStaleOnes) {
    rb::StaleWatch w;
    EXPECT_EQ(w.update(false), rb::Freshness::fresh);
    EXPECT_EQ(w.update(true), rb::Freshness::stale);
    EXPECT_EQ(w.update(true), rb::Freshness::stale);
    EXPECT_EQ(w.update(false), rb::Freshness::recovered);
    EXPECT_EQ(w.update(false), rb::Freshness::fresh);
    const double fresh[3] = {7, 0.001, 1}, repeat[3] = {7, 0.01, 0}, stale[3] = {7, 0.06, -1};
    EXPECT_FALSE(rb::stamp_says_stale(nullptr));
    EXPECT_FALSE(rb::stamp_says_stale(fresh));
    EXPECT_FALSE(rb::stamp_says_stale(repeat));
    EXPECT_TRUE(rb::stamp_says_stale(stale));
}

TEST(SlewLimiter, ReachesItsTargetAtTheRateAndNeverPastIt) {
    rb::SlewLimiter s(v2(256, kInf));  // 0.5 per step of 1/512 s on the first, no limit on the second
    s.reset(v2(0, 0));
    VectorXd out(2);
    int steps = 0;
    double before = 0;
    while (s.step(v2(10, -3), kDt, out) > 0) {
        ++steps;
        EXPECT_EQ(out[0] - before, 0.5);
        EXPECT_EQ(out[1], -3);  // unlimited: at its target at once
        before = out[0];
    }
    EXPECT_EQ(steps, 19);  // 19 limited steps of 0.5, then the last 0.5 is within the rate
    EXPECT_EQ(out[0], 10);
    EXPECT_EQ(s.step(v2(10, -3), kDt, out), 0u);
    EXPECT_EQ(out[0], 10);
    EXPECT_THROW(rb::SlewLimiter(v2(1, 0)), std::invalid_argument);
}

TEST(StaleHoldPid, HoldsItsOutputAndIntegralWhileStale) {
    rb::StaleHoldPid c(two_joint_pid(), v2(1000, 1000));
    VectorXd u(2);
    const VectorXd zero = VectorXd::Zero(2);
    // Fresh cycles with an error: the integral grows.
    for (int i = 0; i < 50; ++i) c.update(false, v2(0.01, 0.02), zero, zero, zero, zero, kDt, u);
    const VectorXd held = u, integral = c.pid().integral();
    ASSERT_NE(integral[1], 0);
    // 500 stale cycles whose measurements are far off: nothing moves.
    for (int i = 0; i < 500; ++i) {
        EXPECT_EQ(c.update(true, v2(1, -1), v2(1, 1), v2(-1, 1), v2(3, 3), zero, kDt, u), rb::Freshness::stale);
        ASSERT_EQ(u, held) << "stale cycle " << i;
        ASSERT_EQ(c.pid().integral(), integral) << "stale cycle " << i;
    }
}

TEST(StaleHoldPid, RestartsWithoutABump) {
    const VectorXd slew = v2(512, 1024);  // 1 and 2 N m per cycle
    rb::StaleHoldPid c(two_joint_pid(), slew);
    VectorXd u(2);
    const VectorXd zero = VectorXd::Zero(2);
    for (int i = 0; i < 200; ++i) c.update(false, v2(0.01, 0.02), zero, zero, zero, zero, kDt, u);
    c.update(true, zero, zero, zero, zero, zero, kDt, u);
    const VectorXd held = u;
    // Fresh again, the reference re-anchored at the arm (no error): the PID
    // alone, integral restarted, asks for far less than the held output.
    rb::Pid reference = two_joint_pid();
    VectorXd expected(2);
    EXPECT_EQ(c.update(false, v2(0.5, 0.5), zero, v2(0.5, 0.5), zero, zero, kDt, u), rb::Freshness::recovered);
    reference.update(v2(0.5, 0.5), zero, v2(0.5, 0.5), zero, zero, kDt, expected);
    EXPECT_EQ(c.pid().integral(), VectorXd::Zero(2));  // restarted (no error since)
    VectorXd before = held;
    int cycles = 1;
    for (;;) {
        for (int j = 0; j < 2; ++j) EXPECT_LE(std::fabs(u[j] - before[j]), slew[j] * kDt) << "cycle " << cycles;
        if (c.slewing() == 0) break;
        before = u;
        c.update(false, v2(0.5, 0.5), zero, v2(0.5, 0.5), zero, zero, kDt, u);
        reference.update(v2(0.5, 0.5), zero, v2(0.5, 0.5), zero, zero, kDt, expected);
        ASSERT_LT(++cycles, 10000);
    }
    // The held output was the integral's alone: |held| / (rate * dt) cycles to reach 0.
    const int expected_cycles = static_cast<int>(std::ceil(std::max(std::fabs(held[0]) / (slew[0] * kDt),
                                                                    std::fabs(held[1]) / (slew[1] * kDt))));
    EXPECT_EQ(cycles, expected_cycles);
    EXPECT_EQ(u, expected);
    // From then on it is the PID, exactly.
    for (int i = 0; i < 20; ++i) {
        c.update(false, v2(0.5 + 1e-3 * i, 0.5), zero, v2(0.5, 0.5), zero, zero, kDt, u);
        reference.update(v2(0.5 + 1e-3 * i, 0.5), zero, v2(0.5, 0.5), zero, zero, kDt, expected);
        ASSERT_EQ(u, expected);
    }
}

// An illegal configuration (§3.10; the robot interface holds the arm) is held
// through like stale measurements: must_hold is what pid and trajgen feed
// StaleWatch / StaleHoldPid with under STALE hold.
TEST(MustHold, StaleStampOrIllegalConfiguration) {
    const double fresh[3] = {7, 0.001, 1}, stale[3] = {7, 0.06, -1};
    EXPECT_FALSE(rb::must_hold(nullptr, false));
    EXPECT_FALSE(rb::must_hold(fresh, false));
    EXPECT_TRUE(rb::must_hold(nullptr, true));  // no stamp (no bridge): the flag alone
    EXPECT_TRUE(rb::must_hold(fresh, true));
    EXPECT_TRUE(rb::must_hold(stale, false));
    EXPECT_TRUE(rb::must_hold(stale, true));
}

TEST(StaleHoldPid, HoldsThroughAnIllegalConfigurationAndRestartsAtTheRate) {
    const VectorXd slew = v2(512, 1024);  // 1 and 2 N m per cycle
    rb::StaleHoldPid c(two_joint_pid(), slew);
    VectorXd u(2);
    const VectorXd zero = VectorXd::Zero(2);
    const double fresh[3] = {1, 0.001, 1}, stale[3] = {1, 0.06, -1};
    for (int i = 0; i < 200; ++i) c.update(rb::must_hold(fresh, false), v2(0.01, 0.02), zero, zero, zero, zero, kDt, u);
    const VectorXd held = u, integral = c.pid().integral();
    ASSERT_NE(integral[0], 0);
    // Illegal for 1000 cycles (2 s), the reference running away from the held
    // arm; the flag clears while the stamp still says stale: held throughout.
    for (int i = 0; i < 1100; ++i) {
        const bool illegal = i < 1000, stamp_stale = i >= 990;
        const double q_ref = 0.01 + 1e-3 * i;
        EXPECT_EQ(c.update(rb::must_hold(stamp_stale ? stale : fresh, illegal), v2(q_ref, q_ref), v2(0.5, 0.5), zero,
                           zero, zero, kDt, u),
                  rb::Freshness::stale);
        ASSERT_EQ(u, held) << "held cycle " << i;
        ASSERT_EQ(c.pid().integral(), integral) << "held cycle " << i;
    }
    // Legal and fresh, the reference re-anchored at the arm: one recovery,
    // the integral restarted, T_REF moving from the held value at the rate.
    VectorXd before = held;
    for (int i = 0; c.slewing() > 0 || i == 0; ++i) {
        const rb::Freshness f = c.update(rb::must_hold(fresh, false), v2(0.5, 0.5), zero, v2(0.5, 0.5), zero, zero,
                                         kDt, u);
        EXPECT_EQ(f, i == 0 ? rb::Freshness::recovered : rb::Freshness::fresh);
        if (i == 0) {
            EXPECT_EQ(c.pid().integral(), zero);
        }
        for (int j = 0; j < 2; ++j) ASSERT_LE(std::fabs(u[j] - before[j]), slew[j] * kDt) << "cycle " << i;
        before = u;
        ASSERT_LT(i, 10000);
    }
    EXPECT_EQ(u, zero);  // caught up with the PID: no error, no integral
}

// Turned on while the configuration is illegal (the flag is set while a
// reconfiguration switches jpid for jpidg): nothing was applied, so nothing
// is slewed from; the first legal cycle is the PID's, as after `on`.
TEST(StaleHoldPid, HeldFromResetStartsAsOnWould) {
    rb::StaleHoldPid c(two_joint_pid(), v2(512, 1024));
    VectorXd u(2), expected(2);
    const VectorXd zero = VectorXd::Zero(2), ff = v2(30, -40);
    for (int i = 0; i < 3; ++i) c.update(false, v2(0.01, 0.02), zero, zero, zero, ff, kDt, u);  // an earlier run
    c.reset();  // `on`
    for (int i = 0; i < 5; ++i) {
        EXPECT_EQ(c.update(true, v2(0.01, 0.02), zero, zero, zero, ff, kDt, u), rb::Freshness::stale);
        ASSERT_EQ(u, zero);
    }
    rb::Pid reference = two_joint_pid();
    EXPECT_EQ(c.update(false, v2(0.01, 0.02), zero, zero, zero, ff, kDt, u), rb::Freshness::recovered);
    reference.update(v2(0.01, 0.02), zero, zero, zero, ff, kDt, expected);
    EXPECT_EQ(u, expected);
    EXPECT_EQ(c.slewing(), 0u);
}

TEST(JointLimiter, TorqueRateReachesTheCommandAtTheRate) {
    rb::JointLimiter l(rb::JointLimits{v2(186.4, 50), v2(kInf, kInf), v2(1024, kInf)});  // 2 N m per cycle
    const VectorXd zero = VectorXd::Zero(2);
    VectorXd tau(2);
    int cycles = 0;
    do {
        tau = v2(100, -50);
        l.apply(tau, zero, zero, kDt);
        ++cycles;
        EXPECT_EQ(tau[0], std::min(100.0, 2.0 * cycles));
        EXPECT_EQ(tau[1], -50);  // no rate limit on joint 2
    } while (tau[0] < 100);
    EXPECT_EQ(cycles, 50);
    EXPECT_EQ(l.rate_clamps(), 49u);
    EXPECT_EQ(l.speed_clamps(), 0u);
    tau = v2(500, -500);  // TLIMIT first
    l.apply(tau, zero, zero, kDt);
    EXPECT_EQ(tau, v2(100 + 2, -50));
}

TEST(JointLimiter, TorqueSpeedEnvelope) {
    rb::JointLimiter l(rb::JointLimits{v2(100, 100), v2(1, 1), v2(kInf, kInf)});  // k = 100 N m s/rad
    const VectorXd bias = v2(10, 10);
    VectorXd tau(2);
    auto limited = [&](double command, double qd) {
        tau = v2(command, 0);
        l.apply(tau, v2(qd, 0), bias, kDt);
        return tau[0];
    };
    EXPECT_EQ(limited(100, 0), 100);     // at rest: the whole TLIMIT
    EXPECT_EQ(limited(100, 0.5), 60);    // 10 + 100 (1 - 0.5)
    EXPECT_EQ(limited(100, 1), 10);      // at VLIMIT: the holding torque, no more
    EXPECT_EQ(limited(100, 1.5), -40);   // beyond: braking
    EXPECT_EQ(limited(-100, 1), -100);   // braking is never limited
    EXPECT_EQ(limited(-100, -1), 10);    // the other way round
    EXPECT_EQ(l.speed_clamps(), 4u);
    EXPECT_THROW(rb::JointLimiter(rb::JointLimits{v2(1, 1), v2(1, 0), v2(1, 1)}), std::invalid_argument);
    EXPECT_THROW(rb::JointLimiter(rb::JointLimits{v2(1, 1), v2(1, 1), VectorXd::Ones(3)}), std::invalid_argument);
}

TEST(JointLimiter, AJointDrivenAtFullTorqueNeverPassesItsSpeedLimit) {
    // A joint of 1 kg m^2 under gravity torque 10 N m and a command stuck at
    // +TLIMIT, integrated at the cycle: the speed creeps up to VLIMIT from below.
    rb::JointLimiter l(rb::JointLimits{VectorXd::Constant(1, 100), VectorXd::Constant(1, 1),
                                       VectorXd::Constant(1, 1000)});
    const VectorXd gravity = VectorXd::Constant(1, 10);
    VectorXd qd = VectorXd::Zero(1), tau(1);
    double fastest = 0;
    for (int i = 0; i < 5 * 512; ++i) {
        tau[0] = 100;
        l.apply(tau, qd, gravity, kDt);
        qd[0] += (tau[0] - gravity[0]) * kDt;
        fastest = std::max(fastest, qd[0]);
    }
    EXPECT_LE(fastest, 1.0);
    EXPECT_GT(qd[0], 0.999);
    EXPECT_GT(l.speed_clamps(), 0u);
}

TEST(Trajectory, SegmentUnderWayAcrossCyclicPasses) {
    const rb::Trajectory t(1, {VectorXd::Zero(1), VectorXd::Ones(1), VectorXd::Constant(1, 2)}, {1.0, 2.0, 4.0},
                           rb::Profile::quintic, true);
    auto span = [&](double at) {
        const auto s = t.segment_at(at);
        return std::make_pair(s.start, s.end);
    };
    EXPECT_EQ(span(0), std::make_pair(0.0, 1.0));
    EXPECT_EQ(span(1.5), std::make_pair(1.0, 3.0));
    EXPECT_EQ(span(6.5), std::make_pair(3.0, 7.0));
    EXPECT_EQ(span(7.25), std::make_pair(7.0, 8.0));  // the second pass
    EXPECT_EQ(span(14.5), std::make_pair(14.0, 15.0));  // the third
    EXPECT_EQ(span(15), std::make_pair(15.0, 17.0));    // at a via point: the next segment, as evaluate
    const rb::Trajectory once(1, {VectorXd::Zero(1), VectorXd::Ones(1)}, {2.0}, rb::Profile::quintic, false);
    EXPECT_EQ(once.segment_at(1).end, 2.0);
    EXPECT_EQ(once.segment_at(5).start, 2.0);  // done: nothing under way
    EXPECT_EQ(once.segment_at(5).end, 2.0);
}

TEST(Trajectory, ReanchoredSegmentStartsAtTheArmAtRest) {
    // What trajgen does on recovery: a preallocated two-point segment, re-aimed.
    rb::Trajectory seg(2, {VectorXd::Zero(2), VectorXd::Zero(2)}, {1.0}, rb::Profile::quintic, false);
    const VectorXd arm = v2(0.3, -0.2), target = v2(0.5, 0.4);
    VectorXd p(2), v(2), a(2);
    const long allocations = chimera::test::allocations_in([&] {
        seg.set_point(0, arm);
        seg.set_point(1, target);
        seg.set_duration(0, 2.0);
    });
    EXPECT_EQ(allocations, 0);
    EXPECT_EQ(seg.total_time(), 2.0);
    seg.evaluate(0, p, v, a);
    EXPECT_EQ(p, arm);
    EXPECT_EQ(v, VectorXd::Zero(2));
    seg.evaluate(2.0, p, v, a);
    EXPECT_EQ(p, target);
    seg.set_duration(0, -1);  // refused: nothing changes
    EXPECT_EQ(seg.total_time(), 2.0);
}

TEST(NoAllocation, StaleHoldAndLimitsDoNotTouchTheHeap) {
    rb::StaleHoldPid c(two_joint_pid(), v2(1000, 1000));
    rb::JointLimiter l(rb::JointLimits{v2(100, 100), v2(1, 1), v2(1000, 1000)});
    const rb::Trajectory t(2, {VectorXd::Zero(2), VectorXd::Ones(2)}, {1.0, 1.0}, rb::Profile::quintic, true);
    const VectorXd zero = VectorXd::Zero(2), q = v2(0.1, 0.2);
    VectorXd u(2), tau(2);
    double sum = 0;
    const long allocations = chimera::test::allocations_in([&] {
        for (int i = 0; i < 30; ++i) {
            c.update(i % 10 < 3, q, zero, zero, zero, zero, kDt, u);
            tau = u;
            l.apply(tau, q, zero, kDt);
            sum += t.segment_at(0.1 * i).end + static_cast<double>(c.slewing());
        }
    });
    EXPECT_EQ(allocations, 0);
    EXPECT_GT(sum, 0);
}
