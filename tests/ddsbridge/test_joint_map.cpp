// A received JointState matched by name (issue #29.7), and the consumer-side
// limits (issue #29.6): modules/ddsbridge/joint_map.hpp, exactly.
//   - reversed names put each value on the joint of its name;
//   - a subset updates the joints it names only (JOINT_SUBSET update), or is
//     refused whole (refuse);
//   - an unknown or twice-named joint refuses the message whole;
//   - no names: refused (UNNAMED refuse) or taken by position (positional);
//   - a message of one value too few or too many for its names is refused;
//   - the port is complete once every joint has had a value;
//   - matching allocates nothing;
//   - check() changes no joint, commit() applies what it took;
//   - a sample older than the newest taken is told (SampleOrder): a StateVar
//     by counter from the same writer, by stamp from another (a restarted
//     writer from counter 0); a JointState by stamp; equal is not older;
//   - a rate limit moves each joint by at most limit * period per cycle, a
//     magnitude limit clamps; both count what they clamp.
#include "joint_map.hpp"

#include <gtest/gtest.h>

#include <array>
#include <stdexcept>
#include <vector>

#include "alloc_counter.hpp"

namespace {

using namespace ddsbridge;
using Joints = std::array<double, 6>;

const std::vector<std::string> kNames{"j1", "j2", "j3", "j4", "j5", "j6"};

JointMap map(bool refuse_subset = false, bool accept_unnamed = false) {
    return JointMap(kNames, JointOptions{refuse_subset, accept_unnamed});
}

Applied apply(JointMap& m, std::vector<const char*> names, std::vector<double> values, Joints& joints) {
    return m.apply(names, values, joints.data());
}

}  // namespace

TEST(JointMap, ReversedNamesPutEachValueOnTheJointOfItsName) {
    JointMap m = map();
    Joints q{};
    const Applied a = apply(m, {"j6", "j5", "j4", "j3", "j2", "j1"}, {6, 5, 4, 3, 2, 1}, q);
    EXPECT_EQ(a.refusal, Refusal::none);
    EXPECT_TRUE(a.complete);
    EXPECT_EQ(q, (Joints{1, 2, 3, 4, 5, 6})) << "joint 1 gets the value named j1, not the first value";
}

TEST(JointMap, ASubsetUpdatesOnlyTheJointsItNames) {
    JointMap m = map();
    Joints q{};
    ASSERT_TRUE(apply(m, {"j1", "j2", "j3", "j4", "j5", "j6"}, {1, 2, 3, 4, 5, 6}, q).complete);
    const Applied a = apply(m, {"j5", "j2"}, {50, 20}, q);
    EXPECT_EQ(a.refusal, Refusal::none);
    EXPECT_TRUE(a.complete);
    EXPECT_EQ(q, (Joints{1, 20, 3, 4, 50, 6}));
}

TEST(JointMap, ThePortIsCompleteOnceEveryJointHasHadAValue) {
    JointMap m = map();
    Joints q{};
    EXPECT_FALSE(apply(m, {"j1", "j2", "j3"}, {1, 2, 3}, q).complete);
    EXPECT_FALSE(apply(m, {"j3", "j4"}, {30, 4}, q).complete) << "j3 twice over two messages counts once";
    EXPECT_TRUE(apply(m, {"j6", "j5"}, {6, 5}, q).complete);
    EXPECT_EQ(q, (Joints{1, 2, 30, 4, 5, 6}));
    m.reset();
    EXPECT_FALSE(apply(m, {"j1"}, {1}, q).complete) << "after reset no joint has a value";
}

TEST(JointMap, WithJointSubsetRefuseASubsetIsRefusedWhole) {
    JointMap m = map(/*refuse_subset=*/true);
    Joints q{1, 2, 3, 4, 5, 6};
    const Applied a = apply(m, {"j5", "j2"}, {50, 20}, q);
    EXPECT_EQ(a.refusal, Refusal::partial);
    EXPECT_FALSE(a.complete);
    EXPECT_EQ(q, (Joints{1, 2, 3, 4, 5, 6})) << "nothing of a refused message is applied";
    EXPECT_EQ(apply(m, {"j2", "j1", "j3", "j4", "j6", "j5"}, {20, 10, 30, 40, 60, 50}, q).refusal, Refusal::none)
        << "every joint, in any order, is taken";
    EXPECT_EQ(q, (Joints{10, 20, 30, 40, 50, 60}));
}

TEST(JointMap, AnUnknownNameRefusesTheMessageWholeAndSaysWhichName) {
    JointMap m = map();
    Joints q{1, 2, 3, 4, 5, 6};
    const Applied a = apply(m, {"j1", "joint7", "j3"}, {10, 70, 30}, q);
    EXPECT_EQ(a.refusal, Refusal::unknown);
    EXPECT_EQ(a.offender, 1u);
    EXPECT_EQ(q, (Joints{1, 2, 3, 4, 5, 6})) << "j1, named before the unknown one, is not applied either";
    EXPECT_EQ(apply(m, {"J1"}, {1}, q).refusal, Refusal::unknown) << "names are compared exactly";
    EXPECT_EQ(apply(m, {"j1", nullptr}, {1, 2}, q).refusal, Refusal::unknown) << "a null name is no joint's";
}

TEST(JointMap, AJointNamedTwiceRefusesTheMessage) {
    JointMap m = map();
    Joints q{1, 2, 3, 4, 5, 6};
    const Applied a = apply(m, {"j2", "j3", "j2"}, {20, 30, 21}, q);
    EXPECT_EQ(a.refusal, Refusal::duplicate);
    EXPECT_EQ(a.offender, 2u);
    EXPECT_EQ(q, (Joints{1, 2, 3, 4, 5, 6}));
    // More names than joints: refused by name, never written past the scratch.
    EXPECT_EQ(apply(m, {"j1", "j2", "j3", "j4", "j5", "j6", "j1"}, {1, 2, 3, 4, 5, 6, 7}, q).refusal, Refusal::duplicate);
    EXPECT_EQ(apply(m, {"j1", "j2", "j3", "j4", "j5", "j6", "j7"}, {1, 2, 3, 4, 5, 6, 7}, q).refusal, Refusal::unknown);
    EXPECT_EQ(apply(m, {"j2", "j3"}, {20, 30}, q).refusal, Refusal::none) << "the next message starts afresh";
}

TEST(JointMap, ValuesThatDoNotMatchTheNamesAreRefused) {
    JointMap m = map();
    Joints q{1, 2, 3, 4, 5, 6};
    EXPECT_EQ(apply(m, {"j1", "j2"}, {10}, q).refusal, Refusal::length);
    EXPECT_EQ(apply(m, {"j1", "j2"}, {}, q).refusal, Refusal::length) << "the field this port takes is empty";
    EXPECT_EQ(apply(m, {"j1"}, {10, 20}, q).refusal, Refusal::length);
    EXPECT_EQ(q, (Joints{1, 2, 3, 4, 5, 6}));
}

TEST(JointMap, WithoutNamesAMessageIsRefusedUnlessTheRmodTakesItByPosition) {
    JointMap strict = map();
    Joints q{1, 2, 3, 4, 5, 6};
    EXPECT_EQ(apply(strict, {}, {6, 5, 4, 3, 2, 1}, q).refusal, Refusal::unnamed);
    EXPECT_EQ(q, (Joints{1, 2, 3, 4, 5, 6}));

    JointMap positional = map(false, /*accept_unnamed=*/true);
    const Applied a = apply(positional, {}, {6, 5, 4, 3, 2, 1}, q);
    EXPECT_EQ(a.refusal, Refusal::none);
    EXPECT_TRUE(a.complete);
    EXPECT_EQ(q, (Joints{6, 5, 4, 3, 2, 1}));
    EXPECT_EQ(apply(positional, {}, {1, 2, 3, 4, 5}, q).refusal, Refusal::length) << "by position: one per joint";
    EXPECT_EQ(apply(positional, {"j1"}, {10}, q).refusal, Refusal::none) << "named messages are still matched";
    EXPECT_EQ(q, (Joints{10, 5, 4, 3, 2, 1}));
}

TEST(JointMap, MatchingAllocatesNothing) {
    JointMap m = map();
    Joints q{};
    const std::vector<const char*> reversed{"j6", "j5", "j4", "j3", "j2", "j1"}, unknown{"j1", "x"};
    const std::vector<double> values{6, 5, 4, 3, 2, 1};
    const long allocations = chimera::test::allocations_in(
        [&] {
            for (int i = 0; i < 100; ++i) {
                (void)m.apply(reversed, values, q.data());
                (void)m.apply(unknown, std::span(values).first(2), q.data());
                m.reset();
            }
        },
        chimera::test::AllocScope::this_thread);
    EXPECT_EQ(allocations, 0);
}

TEST(JointMap, CheckChangesNoJointAndCommitAppliesWhatItTook) {
    JointMap m = map();
    Joints q{1, 2, 3, 4, 5, 6};
    const std::vector<const char*> names{"j6", "j1"};
    const std::vector<double> values{60, 10};
    EXPECT_EQ(m.check(names, values).refusal, Refusal::none);
    EXPECT_EQ(q, (Joints{1, 2, 3, 4, 5, 6})) << "check() applies nothing";
    const Applied a = m.commit(names, values, q.data());
    EXPECT_EQ(a.refusal, Refusal::none);
    EXPECT_FALSE(a.complete) << "four joints have had no value";
    EXPECT_EQ(q, (Joints{10, 2, 3, 4, 5, 60}));
    EXPECT_EQ(m.check(std::vector<const char*>{"j1", "j1"}, std::vector<double>{1, 1}).refusal, Refusal::duplicate);
}

TEST(SampleOrder, AStateVarIsComparedByCounterFromItsWriterAndByStampFromAnother) {
    SampleOrder o(true);
    EXPECT_FALSE(o.older({7, 5, 1000})) << "nothing taken yet";
    o.taken({7, 5, 1000});
    EXPECT_TRUE(o.older({7, 4, 2000})) << "an older counter of the same writer, whatever its stamp";
    EXPECT_TRUE(o.by_counter({7, 4, 2000}));
    EXPECT_FALSE(o.older({7, 5, 1000})) << "equal is not older";
    EXPECT_FALSE(o.older({7, 6, 500})) << "a newer counter with its sender's clock set back";
    EXPECT_FALSE(o.older({8, 0, 1001})) << "a restarted writer: counter 0, a newer stamp";
    EXPECT_TRUE(o.older({8, 9, 999})) << "another writer's older stamp, whatever its counter";
    EXPECT_FALSE(o.by_counter({8, 9, 999}));
    o.taken({8, 0, 1001});
    EXPECT_FALSE(o.older({8, 1, 1002}));
    EXPECT_TRUE(o.older({7, 6, 1000})) << "the first writer again, compared by stamp";
}

TEST(SampleOrder, AJointStateIsComparedByStampOnlyAndEqualStampsAreTaken) {
    SampleOrder o;  // no counter
    o.taken({7, 5, 1000});
    EXPECT_TRUE(o.older({7, 6, 999}));
    EXPECT_FALSE(o.by_counter({7, 6, 999}));
    EXPECT_FALSE(o.older({7, 4, 1000})) << "equal stamps: taken";
    EXPECT_FALSE(o.older({9, 0, 1001}));
}

TEST(JointMap, TheRmodsNamesMustBeDistinct) {
    EXPECT_THROW(JointMap({"a", "b", "a"}, JointOptions{}), std::invalid_argument);
}

TEST(JointLimiter, ARateLimitMovesEachJointByAtMostLimitTimesPeriodPerCycle) {
    JointLimiter l(JointLimiter::Kind::rate, {100, 10});  // per second
    l.set_period(0.01);                                   // steps of 1 and 0.1
    l.start_from_zero();
    const double target[2] = {2.5, -0.05};
    double out[2];
    EXPECT_EQ(l.apply(target, out), 1u);
    EXPECT_DOUBLE_EQ(out[0], 1.0);
    EXPECT_DOUBLE_EQ(out[1], -0.05) << "within its step: as it came";
    EXPECT_EQ(l.apply(target, out), 1u);
    EXPECT_DOUBLE_EQ(out[0], 2.0);
    EXPECT_EQ(l.apply(target, out), 0u) << "the last 0.5 is within a step";
    EXPECT_DOUBLE_EQ(out[0], 2.5);
    const double back[2] = {-10, 1};
    EXPECT_EQ(l.apply(back, out), 2u);
    EXPECT_DOUBLE_EQ(out[0], 1.5);
    EXPECT_DOUBLE_EQ(out[1], 0.05);
}

TEST(JointLimiter, WithoutAReferenceTheFirstValueIsTakenAsItComes) {
    JointLimiter l(JointLimiter::Kind::rate, {1});
    l.set_period(0.01);
    l.start_afresh();
    const double far[1] = {3.0};
    double out[1];
    EXPECT_EQ(l.apply(far, out), 0u) << "a position's first value: no jump from a made-up zero";
    EXPECT_DOUBLE_EQ(out[0], 3.0);
    const double next[1] = {4.0};
    EXPECT_EQ(l.apply(next, out), 1u);
    EXPECT_DOUBLE_EQ(out[0], 3.01);
}

TEST(JointLimiter, AMagnitudeLimitClampsEachJointToItsLimit) {
    JointLimiter l(JointLimiter::Kind::magnitude, {2, 3});
    l.set_period(0.01);
    const double target[2] = {-5, 2.9};
    double out[2];
    EXPECT_EQ(l.apply(target, out), 1u);
    EXPECT_DOUBLE_EQ(out[0], -2.0);
    EXPECT_DOUBLE_EQ(out[1], 2.9);
}

TEST(JointLimiter, ALimitMustBePositive) {
    EXPECT_THROW(JointLimiter(JointLimiter::Kind::rate, {1, 0}), std::invalid_argument);
}
