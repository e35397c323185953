// The ddsbridge .rmod reader (modules/ddsbridge/bridge_config.hpp): what a
// well-formed LOCAL section gives, and the message for each mistake, naming
// the file, the line and the key — checked before anything touches the network.
#include "bridge_config.hpp"
#include "dds_link.hpp"

#include <gtest/gtest.h>

#include <stdexcept>
#include <string>

namespace {

using namespace ddsbridge;

chimera::RmodFile rmod(std::vector<std::string> in, std::vector<std::string> out) {
    chimera::RmodFile r;
    r.name = "bridge";
    r.module = "ddsbridge";
    r.in_vars = std::move(in);
    r.out_vars = std::move(out);
    r.local.file = "bridge.rmod";
    return r;
}

void set(chimera::RmodFile& r, const std::string& key, const std::string& text, int line) {
    std::vector<std::string> words;
    std::string w;
    for (char c : text + " ") {
        if (c == ' ') {
            if (!w.empty()) words.push_back(w);
            w.clear();
        } else {
            w += c;
        }
    }
    r.local.set(key, words, line);
}

std::string error_of(const chimera::RmodFile& r) {
    try {
        parse_config(r);
    } catch (const std::invalid_argument& e) {
        return e.what();
    }
    return "";
}

}  // namespace

TEST(DdsBridgeConfig, AWellFormedSectionGivesEveryPortItsTopic) {
    auto r = rmod({"Q_MEZ", "STATE"}, {"T_REF"});
    set(r, "DOMAIN", "17", 10);
    set(r, "CONFIG", "cyclone.xml", 11);
    set(r, "JOINT_NAMES", "a b", 12);
    set(r, "TOPIC_Q_MEZ", "puma/joint_positions pub JointState.position state", 13);
    set(r, "TOPIC_T_REF", "puma/torques sub JointState.effort command 0.02 illegal", 14);
    set(r, "TOPIC_STATE", "puma/state pub StateVar state", 15);
    const BridgeConfig c = parse_config(r);
    EXPECT_EQ(c.domain, 17);
    EXPECT_EQ(c.config_file, "cyclone.xml");
    r.path = "/etc/arm/bridge.rmod";
    EXPECT_EQ(parse_config(r).config_file, "/etc/arm/cyclone.xml") << "a relative CONFIG is the .rmod's neighbour";
    set(r, "CONFIG", "/opt/dds.xml", 11);
    EXPECT_EQ(parse_config(r).config_file, "/opt/dds.xml");
    EXPECT_EQ(c.age_clock, AgeClock::receive);
    EXPECT_EQ(c.joint_names, (std::vector<std::string>{"a", "b"}));
    ASSERT_EQ(c.topics.size(), 3u);
    EXPECT_EQ(c.topics[0].port, "Q_MEZ");
    EXPECT_EQ(c.topics[0].dds_topic(), "rt/puma/joint_positions");
    EXPECT_EQ(c.topics[0].direction, Direction::pub);
    EXPECT_EQ(c.topics[0].message, Message::joint_position);
    EXPECT_EQ(c.topics[0].qos, Qos::state);
    EXPECT_EQ(c.topics[1].port, "STATE");
    EXPECT_EQ(c.topics[1].message, Message::state_var);
    EXPECT_EQ(c.topics[2].port, "T_REF");
    EXPECT_EQ(c.topics[2].direction, Direction::sub);
    EXPECT_EQ(c.topics[2].message, Message::joint_effort);
    EXPECT_EQ(c.topics[2].qos, Qos::command);
    EXPECT_DOUBLE_EQ(c.topics[2].age_limit, 0.02);
    EXPECT_EQ(c.topics[2].stale, StaleAction::illegal);
    EXPECT_STREQ(type_name(Message::joint_effort), "sensor_msgs::msg::dds_::JointState_");
    EXPECT_STREQ(type_name(Message::state_var), "chimera_msgs::msg::dds_::StateVar_");
}

TEST(DdsBridgeConfig, EachMistakeIsNamedWithFileLineAndKey) {
    auto base = [] { return rmod({"Q"}, {"T"}); };
    auto with = [&](const std::string& q, const std::string& t) {
        auto r = base();
        set(r, "TOPIC_Q", q, 7);
        set(r, "TOPIC_T", t, 8);
        return error_of(r);
    };
    const std::string t_ok = "t sub StateVar state 0.1 warn";
    const std::string q_ok = "q pub StateVar state";
    EXPECT_EQ(with(q_ok, t_ok), "");
    EXPECT_EQ(with("q pub", t_ok),
              "bridge.rmod:7: TOPIC_Q takes TOPIC pub|sub MESSAGE state|command [AGE_LIMIT STALE_ACTION]");
    EXPECT_EQ(with("rt/q pub StateVar state", t_ok),
              "bridge.rmod:7: TOPIC_Q: topic 'rt/q': give the ROS 2 name; the bridge adds the DDS prefix rt/");
    EXPECT_EQ(with("a//b pub StateVar state", t_ok),
              "bridge.rmod:7: TOPIC_Q: topic 'a//b': empty name token (leading, trailing or double '/')");
    EXPECT_EQ(with("a-b pub StateVar state", t_ok),
              "bridge.rmod:7: TOPIC_Q: topic 'a-b': character '-' (ROS 2 names take letters, digits, '_' and '/')");
    EXPECT_EQ(with("9a pub StateVar state", t_ok), "bridge.rmod:7: TOPIC_Q: topic '9a': a name token starts with a digit");
    EXPECT_EQ(with("q both StateVar state", t_ok), "bridge.rmod:7: TOPIC_Q: direction 'both': expected pub or sub");
    EXPECT_EQ(with("q pub Twist state", t_ok),
              "bridge.rmod:7: TOPIC_Q: message 'Twist': expected JointState.position, JointState.velocity, "
              "JointState.effort or StateVar");
    EXPECT_EQ(with("q pub StateVar fast", t_ok),
              "bridge.rmod:7: TOPIC_Q: QoS profile 'fast': expected state or command");
    EXPECT_EQ(with("q pub StateVar state 0.1 warn", t_ok),
              "bridge.rmod:7: TOPIC_Q: a published topic takes no age limit");
    EXPECT_EQ(with("q sub StateVar state 0.1 warn", t_ok),
              "bridge.rmod:7: TOPIC_Q: sub needs Q among the OUTVARs (what the bridge subscribes)");
    EXPECT_EQ(with(q_ok, "t pub StateVar state"),
              "bridge.rmod:8: TOPIC_T: pub needs T among the INVARs (what the bridge publishes)");
    EXPECT_EQ(with(q_ok, "t sub StateVar state"),
              "bridge.rmod:8: TOPIC_T: a subscribed topic needs AGE_LIMIT (seconds) and STALE_ACTION");
    EXPECT_EQ(with(q_ok, "t sub StateVar state -1 warn"), "bridge.rmod:8: TOPIC_T: age limit '-1': expected seconds > 0");
    EXPECT_EQ(with(q_ok, "t sub StateVar state 1e999 warn"),
              "bridge.rmod:8: TOPIC_T: age limit '1e999': expected seconds > 0");
    EXPECT_EQ(with(q_ok, "t sub StateVar state 0.1 panic"),
              "bridge.rmod:8: TOPIC_T: stale action 'panic': expected warn, hold, zero, illegal or error");
    EXPECT_EQ(with(q_ok, "q sub StateVar state 0.1 warn"),
              "bridge.rmod:8: TOPIC_T: topic q is already TOPIC_Q's (one variable per topic)");

    auto stamped = rmod({"Q"}, {"T", "T_RX"});
    set(stamped, "TOPIC_Q", q_ok, 7);
    set(stamped, "TOPIC_T", t_ok, 8);
    set(stamped, "STAMP_T", "T_RX", 9);
    EXPECT_EQ(parse_config(stamped).topics[1].stamp_port, "T_RX");
    set(stamped, "STAMP_T", "T_RX extra", 9);
    EXPECT_EQ(error_of(stamped), "bridge.rmod:9: STAMP_T takes one OUTVAR (3 doubles: counter, age, new/repeat/stale)");
    set(stamped, "STAMP_T", "NOPE", 9);
    EXPECT_EQ(error_of(stamped), "bridge.rmod:9: STAMP_T takes one OUTVAR (3 doubles: counter, age, new/repeat/stale)");
    stamped.local.erase("STAMP_T");
    set(stamped, "STAMP_Q", "T_RX", 9);
    EXPECT_EQ(error_of(stamped), "bridge.rmod:9: STAMP_Q: Q has no subscribed TOPIC_Q line");

    auto missing = base();
    set(missing, "TOPIC_Q", q_ok, 7);
    EXPECT_EQ(error_of(missing), "bridge.rmod: OUTVAR T has no TOPIC_T line in LOCAL");
    auto clock = base();
    set(clock, "TOPIC_Q", q_ok, 7);
    set(clock, "TOPIC_T", t_ok, 8);
    set(clock, "AGE_CLOCK", "wall", 9);
    EXPECT_EQ(error_of(clock), "bridge.rmod:9: AGE_CLOCK 'wall': expected receive or source");
    clock.local.erase("AGE_CLOCK");
    EXPECT_EQ(parse_config(clock).notify, Notify::poll);
    set(clock, "NOTIFY", "wake", 10);
    EXPECT_EQ(parse_config(clock).notify, Notify::wake);
    set(clock, "NOTIFY", "spin", 10);
    EXPECT_EQ(parse_config(clock).notify, Notify::spin);
    set(clock, "NOTIFY", "signal", 10);
    EXPECT_EQ(error_of(clock), "bridge.rmod:10: NOTIFY 'signal': expected poll, spin or wake");
}

// `hold` behaves as `warn` in the cycle (the last value kept, the stamp -1 while
// stale, one warning each way); it names the intent that consumers hold on the
// stamp, so a hold without a STAMP_ line is a mistake, not a silent warn.
TEST(DdsBridgeConfig, HoldIsWarnThatNeedsAStampForItsConsumers) {
    auto r = rmod({}, {"T", "T_RX"});
    set(r, "TOPIC_T", "t sub StateVar state 0.1 hold", 8);
    EXPECT_EQ(error_of(r), "bridge.rmod:8: TOPIC_T: stale action hold needs a STAMP_T line (the consumers hold on "
                           "the stamp's -1)");
    set(r, "STAMP_T", "T_RX", 9);
    const auto c = parse_config(r);
    EXPECT_EQ(c.topics[0].stale, StaleAction::hold);
    EXPECT_STREQ(to_string(c.topics[0].stale), "hold");
    EXPECT_EQ(c.topics[0].stamp_port, "T_RX");
}

// Joint names and the consumer side's options and limits (issue #29.6, #29.7).
TEST(DdsBridgeConfig, JointNamesDefaultToJoint1ToNAndTheSubscribersOptionsAreRead) {
    auto r = rmod({}, {"Q", "V", "T"});
    set(r, "TOPIC_Q", "q sub JointState.position state 0.1 warn", 7);
    set(r, "TOPIC_V", "v sub JointState.velocity state 0.1 warn", 8);
    set(r, "TOPIC_T", "t sub JointState.effort command 0.1 zero", 9);
    BridgeConfig c = parse_config(r);
    EXPECT_FALSE(c.refuse_subset) << "default: a subset updates the joints it names";
    EXPECT_FALSE(c.accept_unnamed) << "default: a message without names is refused";
    EXPECT_EQ(joint_names_for(c, c.topics[0], 3, "bridge.rmod"), (std::vector<std::string>{"joint1", "joint2", "joint3"}));
    EXPECT_TRUE(c.topics[0].limits.empty());
    set(r, "JOINT_SUBSET", "refuse", 10);
    set(r, "UNNAMED", "positional", 11);
    set(r, "JOINT_NAMES", "a b c", 12);
    set(r, "VLIMIT_Q", "1 2 3", 13);
    set(r, "VLIMIT_V", "4", 14);
    set(r, "TRATE_T", "50 50 10", 15);
    c = parse_config(r);
    EXPECT_TRUE(c.refuse_subset);
    EXPECT_TRUE(c.accept_unnamed);
    EXPECT_EQ(joint_names_for(c, c.topics[0], 3, "bridge.rmod"), (std::vector<std::string>{"a", "b", "c"}));
    EXPECT_EQ(limits_for(c.topics[0], 3, "bridge.rmod"), (std::vector<double>{1, 2, 3}));
    EXPECT_EQ(limits_for(c.topics[1], 3, "bridge.rmod"), (std::vector<double>{4, 4, 4})) << "one for every joint";
    EXPECT_EQ(limits_for(c.topics[2], 3, "bridge.rmod"), (std::vector<double>{50, 50, 10}));
}

TEST(DdsBridgeConfig, EachJointMistakeIsNamedWithFileLineAndKey) {
    auto base = [] {
        auto r = rmod({}, {"Q", "T", "S"});
        set(r, "TOPIC_Q", "q sub JointState.position state 0.1 warn", 7);
        set(r, "TOPIC_T", "t sub JointState.effort command 0.1 zero", 8);
        set(r, "TOPIC_S", "s sub StateVar state 0.1 warn", 9);
        return r;
    };
    auto with = [&](const std::string& key, const std::string& value) {
        auto r = base();
        set(r, key, value, 12);
        return error_of(r);
    };
    EXPECT_EQ(with("JOINT_SUBSET", "some"), "bridge.rmod:12: JOINT_SUBSET 'some': expected update or refuse");
    EXPECT_EQ(with("UNNAMED", "yes"), "bridge.rmod:12: UNNAMED 'yes': expected refuse or positional");
    EXPECT_EQ(with("JOINT_NAMES", "a b a"), "bridge.rmod:12: JOINT_NAMES: 'a' is given twice (a name is one joint)");
    EXPECT_EQ(with("VLIMIT_T", "1"),
              "bridge.rmod:12: VLIMIT_T: a velocity limit is for a JointState.position or JointState.velocity port");
    EXPECT_EQ(with("TRATE_Q", "1"), "bridge.rmod:12: TRATE_Q: a torque-rate limit is for a JointState.effort port");
    EXPECT_EQ(with("VLIMIT_S", "1"),
              "bridge.rmod:12: VLIMIT_S: a velocity limit is for a JointState.position or JointState.velocity port");
    EXPECT_EQ(with("VLIMIT_X", "1"), "bridge.rmod:12: VLIMIT_X: X has no subscribed TOPIC_X line");
    EXPECT_EQ(with("VLIMIT_Q", "1 0 1"), "bridge.rmod:12: VLIMIT_Q: limit '0': expected a number > 0 (units per second)");
    EXPECT_EQ(with("TRATE_T", "nan"), "bridge.rmod:12: TRATE_T: limit 'nan': expected a number > 0 (N m per second)");

    auto r = base();
    set(r, "JOINT_NAMES", "a b", 12);
    set(r, "TRATE_T", "1 2", 13);
    const BridgeConfig c = parse_config(r);
    auto error = [](auto f) {
        try {
            f();
        } catch (const std::invalid_argument& e) {
            return std::string(e.what());
        }
        return std::string();
    };
    EXPECT_EQ(error([&] { joint_names_for(c, c.topics[0], 3, "bridge.rmod"); }),
              "bridge.rmod: JOINT_NAMES has 2 names, TOPIC_Q 3 joints");
    EXPECT_EQ(error([&] { limits_for(c.topics[1], 3, "bridge.rmod"); }),
              "bridge.rmod:13: TRATE_T has 2 limits for 3 joints (give one per joint, or one for all)");
}

// WriteSchedule (dds_link.hpp): when the task's next write is due, from its
// release grid and the earliest phase of its recent writes.
TEST(WriteSchedule, TheNextWriteIsDueOnePeriodOnAtTheEarliestPhaseSeen) {
    constexpr std::int64_t P = 1'000'000, t0 = 5'000'000'000;
    WriteSchedule s;
    EXPECT_EQ(s.next_due(t0), 0) << "nothing known before the first write";
    s.seen(t0 + 30'000, P);  // released at t0, wrote 30 µs late: the grid's origin
    EXPECT_EQ(s.next_due(t0 + 30'000), t0 + P + 30'000);
    s.seen(t0 + P + 5'000, P);  // 25 µs earlier in its period than the first
    EXPECT_EQ(s.earliest(), -25'000);
    EXPECT_EQ(s.next_due(t0 + P + 5'000), t0 + 2 * P + 5'000);
    s.seen(t0 + 2 * P + 50'000, P);  // late: the earliest phase stays, relaxed by kRelax
    EXPECT_EQ(s.earliest(), -25'000 + WriteSchedule::kRelax);
    EXPECT_EQ(s.next_due(t0 + 2 * P + 50'000), t0 + 3 * P + 5'000 + WriteSchedule::kRelax)
        << "a late write does not push the next one's due time back";
    // A write skipped (the task missed a release): still the same grid.
    s.seen(t0 + 4 * P + 6'000, P);
    EXPECT_EQ(s.next_due(t0 + 4 * P + 6'000), t0 + 5 * P + 5'000 + 2 * WriteSchedule::kRelax);
}

TEST(WriteSchedule, TheTypicalTimeIsTheMovingAverageOfThePhases) {
    constexpr std::int64_t P = 1'000'000, t0 = 5'000'000'000;
    WriteSchedule s;
    EXPECT_EQ(s.next_typical(t0), 0) << "nothing known before the first write";
    s.seen(t0 + 10'000, P);
    EXPECT_EQ(s.next_typical(t0 + 10'000), t0 + P + 10'000);
    s.seen(t0 + P + 90'000, P);  // phase +80 µs: the average moves an eighth of the way
    EXPECT_EQ(s.typical(), 80'000 / WriteSchedule::kAverage);
    EXPECT_EQ(s.next_due(t0 + P + 90'000), t0 + 2 * P + 10'000) << "the earliest phase is still the first write's";
    EXPECT_EQ(s.next_typical(t0 + P + 90'000), t0 + 2 * P + 10'000 + 10'000);
    for (int k = 2; k < 200; ++k) s.seen(t0 + k * P + 90'000, P);
    EXPECT_NEAR(static_cast<double>(s.typical()), 80'000, WriteSchedule::kAverage) << "settles on the writes' phase";
    EXPECT_GE(s.next_typical(t0 + 199 * P + 90'000), s.next_due(t0 + 199 * P + 90'000));
}

// WakeLateness (dds_link.hpp): how early NOTIFY poll asks to be woken.
TEST(WakeLateness, IsTheMovingAverageOfHowLateSleepsEndedAndOneStallCountsLittle) {
    WakeLateness w;
    EXPECT_EQ(w.average(), WakeLateness::kStart) << "before any sleep";
    w.seen(2'000);  // an eighth of the way from 10 µs to 2 µs
    EXPECT_EQ(w.average(), 10'000 - 8'000 / WakeLateness::kAverage);
    for (int k = 0; k < 200; ++k) w.seen(4'000);
    EXPECT_NEAR(static_cast<double>(w.average()), 4'000, WakeLateness::kAverage) << "settles on the usual lateness";
    const std::int64_t settled = w.average();
    w.seen(50'000'000);  // a 50 ms stall counts as kMax
    EXPECT_EQ(w.average(), settled + (WakeLateness::kMax - settled) / WakeLateness::kAverage);
    w.seen(-5'000);  // a clock read before the asked time (cannot be late by less than 0)
    EXPECT_GE(w.average(), 0);
}

TEST(WriteSchedule, TheEarliestPhaseIsForgottenSlowly) {
    constexpr std::int64_t P = 1'000'000, t0 = 5'000'000'000;
    WriteSchedule s;
    s.seen(t0 + 40'000, P);
    s.seen(t0 + P + 10'000, P);  // one early write: -30 µs
    for (int k = 2; k < 12; ++k) s.seen(t0 + k * P + 40'000, P);
    EXPECT_EQ(s.earliest(), -30'000 + 10 * WriteSchedule::kRelax);
    for (int k = 12; k < 400; ++k) s.seen(t0 + k * P + 40'000, P);
    EXPECT_EQ(s.earliest(), 0) << "never later than the writes themselves";
}

TEST(WriteSchedule, ANewPeriodOrALongSilenceStartsANewGrid) {
    constexpr std::int64_t P = 1'000'000, t0 = 5'000'000'000;
    WriteSchedule s;
    s.seen(t0 + 40'000, P);
    s.seen(t0 + P + 10'000, P);
    ASSERT_EQ(s.earliest(), -30'000);
    s.seen(t0 + 10 * P + 700'000, P);  // OFF and ON again: released on another grid
    EXPECT_EQ(s.earliest(), 0);
    EXPECT_EQ(s.next_due(t0 + 10 * P + 700'000), t0 + 11 * P + 700'000);
    s.seen(t0 + 11 * P + 700'000, 2 * P);  // a new period: a new grid
    EXPECT_EQ(s.next_due(t0 + 11 * P + 700'000), t0 + 13 * P + 700'000);
}

TEST(WriteSchedule, WritesEitherSideOfTheGridPointBelongToIt) {
    constexpr std::int64_t P = 1'000'000, t0 = 5'000'000'000;
    WriteSchedule s;
    s.seen(t0 + 400'000, P);  // the first write was 400 µs late
    s.seen(t0 + P + 20'000, P);  // the next one nearly on time: phase -380 µs, the same grid point
    EXPECT_EQ(s.earliest(), -380'000);
    EXPECT_EQ(s.next_due(t0 + P + 20'000), t0 + 2 * P + 20'000);
    EXPECT_EQ(s.next_due(t0 + P + 450'000), t0 + 2 * P + 20'000) << "a write late in its period";
}
