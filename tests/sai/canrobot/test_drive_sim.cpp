// The CAN robot protocol (modules/canrobot/canrobot/cia402.hpp) and the
// simulated drives (drive_sim.hpp), exactly, with a controllable clock: no
// socket, no thread, no sleep. What the drives promise the canrobot module:
// NMT and heartbeats, the CiA 402 state machine, feedback latched at SYNC,
// targets taking effect at SYNC, brakes when not enabled, RPDO deadline
// monitoring, fault and fault reset, CSP holding position.
#include "canrobot/bus_config.hpp"
#include "canrobot/cia402.hpp"
#include "canrobot/command_limits.hpp"
#include "canrobot/drive_sim.hpp"
#include "canrobot/sdo.hpp"
#include "robotics/dynamics.hpp"
#include "alloc_counter.hpp"

#include <chimera/cfg.hpp>
#include <chimera/sbs_files.hpp>

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <functional>
#include <numbers>
#include <string>
#include <tuple>
#include <vector>

namespace {

using namespace chimera::canrobot;
using namespace chimera::canrobot::cia402;
namespace rb = chimera::robotics;

constexpr std::int64_t kMs = 1'000'000;
constexpr double kCounts = 1 << 20;

// --- the protocol's pure parts ---------------------------------------------------

TEST(Cia402, StatuswordRoundTripsEveryState) {
    for (DriveState s : {DriveState::not_ready_to_switch_on, DriveState::switch_on_disabled,
                         DriveState::ready_to_switch_on, DriveState::switched_on, DriveState::operation_enabled,
                         DriveState::quick_stop_active, DriveState::fault_reaction_active, DriveState::fault})
        EXPECT_EQ(decode_statusword(encode_statusword(s)), s) << to_string(s);
    // The values of the CiA 402 state table (with bit 9, remote).
    EXPECT_EQ(encode_statusword(DriveState::switch_on_disabled), 0x0240);
    EXPECT_EQ(encode_statusword(DriveState::ready_to_switch_on), 0x0221);
    EXPECT_EQ(encode_statusword(DriveState::switched_on), 0x0233);
    EXPECT_EQ(encode_statusword(DriveState::operation_enabled), 0x0237);
    EXPECT_EQ(encode_statusword(DriveState::fault), 0x0208);
    // Manufacturer bits do not change the state read.
    EXPECT_EQ(decode_statusword(0x8237 | 0x0400), DriveState::operation_enabled);
}

TEST(Cia402, ControlwordTransitions) {
    using S = DriveState;
    EXPECT_EQ(next_state(S::switch_on_disabled, kCwShutdown, 0), S::ready_to_switch_on);     // 2
    EXPECT_EQ(next_state(S::switch_on_disabled, kCwEnableOperation, 0), S::switch_on_disabled);
    EXPECT_EQ(next_state(S::ready_to_switch_on, kCwSwitchOn, 0), S::switched_on);            // 3
    EXPECT_EQ(next_state(S::switched_on, kCwEnableOperation, 0), S::operation_enabled);      // 4
    EXPECT_EQ(next_state(S::operation_enabled, kCwSwitchOn, 0), S::switched_on);             // 5
    EXPECT_EQ(next_state(S::switched_on, kCwShutdown, 0), S::ready_to_switch_on);            // 6
    EXPECT_EQ(next_state(S::ready_to_switch_on, kCwDisableVoltage, 0), S::switch_on_disabled); // 7
    EXPECT_EQ(next_state(S::operation_enabled, kCwShutdown, 0), S::ready_to_switch_on);      // 8
    EXPECT_EQ(next_state(S::operation_enabled, kCwDisableVoltage, 0), S::switch_on_disabled); // 9
    EXPECT_EQ(next_state(S::switched_on, kCwQuickStop, 0), S::switch_on_disabled);           // 10
    EXPECT_EQ(next_state(S::operation_enabled, kCwQuickStop, 0), S::quick_stop_active);      // 11
    EXPECT_EQ(next_state(S::quick_stop_active, kCwDisableVoltage, 0), S::switch_on_disabled); // 12
    EXPECT_EQ(next_state(S::quick_stop_active, kCwEnableOperation, 0), S::operation_enabled); // 16
    EXPECT_EQ(next_state(S::operation_enabled, kCwEnableOperation, 0), S::operation_enabled);
    // Fault reset acts on the rising edge of bit 7 only.
    EXPECT_EQ(next_state(S::fault, kCwFaultReset, 0), S::switch_on_disabled);                // 15
    EXPECT_EQ(next_state(S::fault, kCwFaultReset, kCwFaultReset), S::fault);
    EXPECT_EQ(next_state(S::fault, kCwEnableOperation, 0), S::fault);
}

TEST(Cia402, TheMastersStepsReachOperationEnabledFromEveryState) {
    for (DriveState start : {DriveState::switch_on_disabled, DriveState::ready_to_switch_on,
                             DriveState::switched_on, DriveState::quick_stop_active, DriveState::fault}) {
        DriveState s = start;
        std::uint16_t cw = 0;
        int steps = 0;
        while (s != DriveState::operation_enabled && steps < 10) {
            const std::uint16_t next = controlword_toward_enabled(s, cw);
            s = next_state(s, next, cw);
            cw = next;
            ++steps;
        }
        EXPECT_EQ(s, DriveState::operation_enabled) << "from " << to_string(start);
        EXPECT_LE(steps, 5) << "from " << to_string(start);
    }
}

TEST(Cia402, UnitConversionsRoundAndSaturate) {
    EXPECT_EQ(torque_to_permille(1.234, 10.0), 123);
    EXPECT_EQ(torque_to_permille(-1.236, 10.0), -124);
    EXPECT_EQ(torque_to_permille(1e6, 10.0), 32767);
    EXPECT_EQ(torque_to_permille(-1e6, 10.0), -32768);
    EXPECT_EQ(torque_to_permille(std::nan(""), 10.0), 0);
    EXPECT_DOUBLE_EQ(permille_to_torque(123, 10.0), 1.23);
    EXPECT_EQ(to_counts(std::numbers::pi, kCounts), 1 << 19);
    EXPECT_EQ(to_counts(-2 * std::numbers::pi, kCounts), -(1 << 20));
    EXPECT_EQ(to_counts(1e9, kCounts), INT32_MAX);
    EXPECT_NEAR(from_counts(to_counts(0.785398, kCounts), kCounts), 0.785398, 2 * std::numbers::pi / kCounts);
    EXPECT_EQ(error_name(kErrRpdoTimeout), "RPDO timeout");
}

// --- configuration ---------------------------------------------------------------------

chimera::RmodFile rmod_from(const std::string& local_lines) {
    const std::string text =
        "MODULE canrobot\nDESC test\nOUTVAR Q_MEZ\nTASKTYPE periodic\nFREQ 100\nLOCAL\n" + local_lines + "EOF\n";
    auto reader = chimera::cfg::Reader::from_string(text, "bus.rmod");
    return chimera::parse_rmod(reader, "bus.rmod");
}

std::string config_error(const std::string& local_lines) {
    try {
        DriveConfig::from_rmod(rmod_from(local_lines));
    } catch (const std::invalid_argument& e) {
        return e.what();
    }
    return "(accepted)";
}

TEST(BusConfig, ReadsTheRmodAndNamesWhatIsWrong) {
    const auto c = DriveConfig::from_rmod(
        rmod_from("ROBOT planar2\nINTERFACE can1\nNODES 7 9\nRATED_TORQUE 5\nTLIMIT 100 50\nQ0 0.1 0.2\n"));
    EXPECT_EQ(c.bus.interface, "can1");
    EXPECT_EQ(c.bus.nodes, (std::vector<int>{7, 9}));
    EXPECT_DOUBLE_EQ(c.bus.rated_torque[1], 5.0);
    EXPECT_DOUBLE_EQ(c.bus.torque_limit[1], 50.0);
    EXPECT_DOUBLE_EQ(c.bus.counts_per_rev[0], kCounts);
    EXPECT_DOUBLE_EQ(c.q0[1], 0.2);

    EXPECT_NE(config_error("ROBOT planar2\nNODES 1 2\nRATED_TORQUE 5\n").find("INTERFACE"), std::string::npos);
    const std::string count = config_error("ROBOT planar2\nINTERFACE can0\nNODES 1 2 3\nRATED_TORQUE 5\n");
    EXPECT_NE(count.find("bus.rmod"), std::string::npos) << count;
    EXPECT_NE(count.find("line 9"), std::string::npos) << count;
    EXPECT_NE(count.find("3 node ids, the robot has 2 joints"), std::string::npos) << count;
    EXPECT_NE(config_error("ROBOT planar2\nINTERFACE can0\nNODES 4 4\nRATED_TORQUE 5\n").find("appears twice"),
              std::string::npos);
    EXPECT_NE(config_error("ROBOT planar2\nINTERFACE can0\nNODES 0 4\nRATED_TORQUE 5\n").find("not 1..127"),
              std::string::npos);
    EXPECT_NE(config_error("ROBOT planar2\nINTERFACE can0\nNODES 1 2\n").find("RATED_TORQUE"), std::string::npos);
    const std::string limit = config_error("ROBOT planar2\nINTERFACE can0\nNODES 1 2\nRATED_TORQUE 1\nTLIMIT 40\n");
    EXPECT_NE(limit.find("more than the bus can carry"), std::string::npos) << limit;
    EXPECT_NE(config_error("ROBOT scara\nINTERFACE can0\nNODES 1 2\nRATED_TORQUE 1\n").find("ROBOT 'scara'"),
              std::string::npos);
}

TEST(BusConfig, TheShippedRmodDescribesThePuma) {
    const auto c = DriveConfig::from_rmod(chimera::read_rmod(CANROBOT_RMOD_DIR "/puma_can.rmod"));
    EXPECT_EQ(c.model.ndof(), 6u);
    EXPECT_EQ(c.bus.nodes, (std::vector<int>{1, 2, 3, 4, 5, 6}));
    // Every peak torque is representable on the bus.
    for (Eigen::Index j = 0; j < 6; ++j) EXPECT_LE(c.bus.torque_limit[j], 32.767 * c.bus.rated_torque[j]);
}

// --- VLIMIT and TRATE: what canrobot commands, limited (issue #29.6) ------------------

chimera::canrobot::BusConfig planar_bus(const std::string& limits) {
    return DriveConfig::from_rmod(rmod_from("ROBOT planar2\nINTERFACE can0\nNODES 1 2\nRATED_TORQUE 10\n"
                                            "TLIMIT 100\n" + limits)).bus;
}

std::string limiter_error(const std::string& limits, bool position_mode) {
    try {
        chimera::canrobot::CommandLimiter l(planar_bus(limits), position_mode);
    } catch (const std::invalid_argument& e) {
        return e.what();
    }
    return "(accepted)";
}

TEST(CanRobotLimits, AbsentKeysMeanNoLimitAndGetLimitsSaysNone) {
    const auto bus = planar_bus("");
    EXPECT_TRUE(std::isinf(bus.vlimit[0]) && std::isinf(bus.trate[1]));
    chimera::canrobot::CommandLimiter l(bus, false);
    EXPECT_FALSE(l.active());
    EXPECT_EQ(l.report(), "none");
    Eigen::VectorXd tau(2), zero = Eigen::VectorXd::Zero(2);
    tau << 90.0, -90.0;
    l.limit_torque(tau, zero, zero, 0.01);
    EXPECT_EQ(tau, (Eigen::VectorXd(2) << 90.0, -90.0).finished());  // untouched: TLIMIT is the module's clamp
}

TEST(CanRobotLimits, OneValueOrOnePerJointAndOutOfRangeNamed) {
    const auto bus = planar_bus("VLIMIT 2 3\nTRATE 500\n");
    EXPECT_DOUBLE_EQ(bus.vlimit[0], 2.0);
    EXPECT_DOUBLE_EQ(bus.vlimit[1], 3.0);
    EXPECT_DOUBLE_EQ(bus.trate[0], 500.0);
    EXPECT_DOUBLE_EQ(bus.trate[1], 500.0);
    EXPECT_EQ(limiter_error("VLIMIT 2 0\n", false), "VLIMIT of joint 2 must be > 0");
    EXPECT_EQ(limiter_error("VLIMIT 2 0\n", true), "VLIMIT of joint 2 must be > 0");
    EXPECT_EQ(limiter_error("TRATE -1\n", false), "TRATE of joint 1 must be > 0");
    EXPECT_NE(limiter_error("VLIMIT 1 2 3\n", false).find("3 values, expected 1 or 2"), std::string::npos);
    // Position mode: the drive's loop makes the torque; a torque rate is refused, not ignored.
    EXPECT_NE(limiter_error("TRATE 500\n", true).find("TRATE: in position mode"), std::string::npos);
}

TEST(CanRobotLimits, TorqueModeRateLimitsTheTorqueFromTheOneAppliedAndCounts) {
    chimera::canrobot::CommandLimiter l(planar_bus("TRATE 1000\n"), false);  // 10 N m per 10 ms cycle
    ASSERT_TRUE(l.active());
    const Eigen::VectorXd zero = Eigen::VectorXd::Zero(2);
    l.reset((Eigen::VectorXd(2) << 5.0, 0.0).finished());  // the torque the drives apply after on()
    Eigen::VectorXd tau(2);
    tau << 50.0, -3.0;
    l.limit_torque(tau, zero, zero, 0.01);
    EXPECT_DOUBLE_EQ(tau[0], 15.0);  // 5 + 10
    EXPECT_DOUBLE_EQ(tau[1], -3.0);  // within the step: as asked
    tau << 50.0, -3.0;
    l.limit_torque(tau, zero, zero, 0.01);
    EXPECT_DOUBLE_EQ(tau[0], 25.0);
    EXPECT_EQ(l.rate_clamps(), 2u);
    EXPECT_EQ(l.speed_clamps(), 0u);
    EXPECT_EQ(l.report(), "speed_clamps 0 rate_clamps 2");
}

TEST(CanRobotLimits, TorqueModeSpeedEnvelopeIsCentredOnGravity) {
    // VLIMIT 2, TLIMIT 100: k = 50 N m per rad/s. At qd = 1 with gravity 5 the torque
    // may be 5 - 50 (2 + 1) = -145 .. 5 + 50 (2 - 1) = 55, then |torque| <= 100.
    chimera::canrobot::CommandLimiter l(planar_bus("VLIMIT 2\n"), false);
    const Eigen::VectorXd qd = (Eigen::VectorXd(2) << 1.0, 2.0).finished();
    const Eigen::VectorXd gravity = (Eigen::VectorXd(2) << 5.0, 5.0).finished();
    Eigen::VectorXd tau(2);
    tau << 80.0, 80.0;
    l.limit_torque(tau, qd, gravity, 0.01);
    EXPECT_DOUBLE_EQ(tau[0], 55.0);
    EXPECT_DOUBLE_EQ(tau[1], 5.0);  // at VLIMIT: held against gravity, not accelerated
    tau << -120.0, -50.0;           // braking is allowed
    l.limit_torque(tau, qd, gravity, 0.01);
    EXPECT_DOUBLE_EQ(tau[0], -100.0);  // the envelope allows -145; TLIMIT does not
    EXPECT_DOUBLE_EQ(tau[1], -50.0);
    EXPECT_EQ(l.speed_clamps(), 2u);
    EXPECT_EQ(l.rate_clamps(), 0u);
}

TEST(CanRobotLimits, PositionModeTargetMovesAtMostVlimitPerCycle) {
    // VLIMIT 0.5 rad/s, 10 ms: the target moves at most 5 mrad a cycle; the
    // velocity offset is clamped to +-0.5. A joint-cycle counts once.
    chimera::canrobot::CommandLimiter l(planar_bus("VLIMIT 0.5\n"), true);
    l.reset((Eigen::VectorXd(2) << 0.1, -0.2).finished());  // where the drives hold after on()
    Eigen::VectorXd q(2), qd(2);
    q << 0.2, -0.198;
    qd << 1.0, 0.1;
    l.limit_target(q, qd, 0.01);
    EXPECT_DOUBLE_EQ(q[0], 0.105);   // 0.1 + 0.005
    EXPECT_DOUBLE_EQ(q[1], -0.198);  // a 2 mrad step: as asked
    EXPECT_DOUBLE_EQ(qd[0], 0.5);
    EXPECT_DOUBLE_EQ(qd[1], 0.1);
    q << 0.2, -0.198;
    qd << 0.0, -0.7;
    l.limit_target(q, qd, 0.01);
    EXPECT_DOUBLE_EQ(q[0], 0.11);
    EXPECT_DOUBLE_EQ(q[1], -0.198);
    EXPECT_DOUBLE_EQ(qd[1], -0.5);  // the offset alone limited: counted
    EXPECT_EQ(l.speed_clamps(), 3u);
    EXPECT_EQ(l.report(), "speed_clamps 3 rate_clamps 0");
    // A hold re-anchors: from there, the next step is again at most 5 mrad.
    l.reset((Eigen::VectorXd(2) << 0.0, 0.0).finished());
    q << -1.0, 0.004;
    qd.setZero();
    l.limit_target(q, qd, 0.01);
    EXPECT_DOUBLE_EQ(q[0], -0.005);
    EXPECT_DOUBLE_EQ(q[1], 0.004);
}

// --- the drives ------------------------------------------------------------------------

DriveConfig planar_config() {
    auto c = DriveConfig::from_rmod(rmod_from(
        "ROBOT planar2\nINTERFACE vcan0\nNODES 3 4\nRATED_TORQUE 10\nQ0 0.4 -0.3\n"
        "DRIVE_HEARTBEAT 0.1\nDRIVE_RPDO_TIMEOUT 0.05\nDRIVE_EVENT_TIMER 0.1\n"));
    return c;
}

Frame frame(std::uint32_t id, std::initializer_list<std::uint8_t> bytes) {
    Frame f;
    f.id = id;
    for (std::uint8_t b : bytes) f.data[f.len++] = b;
    return f;
}
Frame rpdo1(int node, std::uint16_t cw, std::int16_t mode, std::int16_t torque) {
    Frame f{.id = cob_id(kRpdo1, node), .len = 6, .data = {}};
    put_u16(f, 0, cw);
    put_u16(f, 2, static_cast<std::uint16_t>(mode));
    put_u16(f, 4, static_cast<std::uint16_t>(torque));
    return f;
}
Frame rpdo2(int node, std::int32_t position, std::int32_t velocity) {
    Frame f{.id = cob_id(kRpdo2, node), .len = 8, .data = {}};
    put_u32(f, 0, static_cast<std::uint32_t>(position));
    put_u32(f, 4, static_cast<std::uint32_t>(velocity));
    return f;
}
Frame nmt(NmtCommand c, int node) { return frame(kNmt, {static_cast<std::uint8_t>(c), static_cast<std::uint8_t>(node)}); }
Frame sync_frame() { return frame(kSync, {1}); }

// --- SDO (CiA 301 expedited download, abort) ---------------------------------------------

std::vector<int> bytes_of(const Frame& f) { return std::vector<int>(f.data, f.data + f.len); }

TEST(Sdo, ExpeditedDownloadRequestsAreExact) {
    const Frame four = sdo::download_request(3, 0x6080, 0, 0x12345678);
    EXPECT_EQ(four.id, 0x603u);
    EXPECT_EQ(bytes_of(four), (std::vector<int>{0x23, 0x80, 0x60, 0x00, 0x78, 0x56, 0x34, 0x12}));
    // n = 4 - size in bits 3..2, e and s set; the unused data bytes are 0.
    EXPECT_EQ(bytes_of(sdo::download_request(127, 0x6072, 0, 0xABCD1234, 3)),
              (std::vector<int>{0x27, 0x72, 0x60, 0x00, 0x34, 0x12, 0xCD, 0x00}));
    EXPECT_EQ(sdo::download_request(127, 0x6072, 0, 0, 3).id, 0x67Fu);
    EXPECT_EQ(bytes_of(sdo::download_request(1, 0x6072, 2, 0xABCD1234, 2)),
              (std::vector<int>{0x2B, 0x72, 0x60, 0x02, 0x34, 0x12, 0x00, 0x00}));
    EXPECT_EQ(bytes_of(sdo::download_request(1, 0x1017, 0, 0xFF, 1)),
              (std::vector<int>{0x2F, 0x17, 0x10, 0x00, 0xFF, 0x00, 0x00, 0x00}));
    EXPECT_EQ(sdo::download_request(1, 0x6080, 0, 7, 9).data[0], 0x23);  // size outside 1..4: 4
}

TEST(Sdo, ResponsesAndAbortsAreExact) {
    const Frame ok = sdo::download_response(3, 0x6087, 0);
    EXPECT_EQ(ok.id, 0x583u);
    EXPECT_EQ(bytes_of(ok), (std::vector<int>{0x60, 0x87, 0x60, 0x00, 0, 0, 0, 0}));
    const Frame refused = sdo::abort_frame(3, 0x6080, 0, sdo::kAbortRange, true);
    EXPECT_EQ(refused.id, 0x583u);
    EXPECT_EQ(bytes_of(refused), (std::vector<int>{0x80, 0x80, 0x60, 0x00, 0x30, 0x00, 0x09, 0x06}));
    EXPECT_EQ(sdo::abort_frame(3, 0x6080, 0, sdo::kAbortTimeout, false).id, 0x603u);  // the master's abort
    EXPECT_EQ(sdo::kAbortNoObject, 0x06020000u);
    EXPECT_EQ(sdo::kAbortRange, 0x06090030u);
    EXPECT_EQ(sdo::kAbortTimeout, 0x05040000u);
    EXPECT_EQ(sdo::kAbortGeneral, 0x08000000u);
    EXPECT_EQ(sdo::abort_name(0x06020000), "object does not exist in the object dictionary");
    EXPECT_EQ(sdo::abort_name(0x06090030), "value range of parameter exceeded");
    EXPECT_EQ(sdo::abort_name(0x05040000), "SDO protocol timed out");
    EXPECT_EQ(sdo::abort_name(0x08000000), "general error");
    EXPECT_EQ(sdo::abort_name(0x12345678), "");
    EXPECT_EQ(sdo::object_name(0x6080), "max motor speed");
    EXPECT_EQ(sdo::object_name(0x6087), "torque slope");
}

TEST(Sdo, DecodeReadsWhatEncodeWrote) {
    auto r = sdo::decode_request(sdo::download_request(5, 0x6087, 0, 0x00C0FFEE));
    ASSERT_TRUE(r);
    EXPECT_EQ(r->kind, sdo::Request::Kind::download);
    EXPECT_EQ(r->index, 0x6087);
    EXPECT_EQ(r->subindex, 0);
    EXPECT_EQ(r->value, 0x00C0FFEEu);
    EXPECT_EQ(r->size, 4);
    r = sdo::decode_request(sdo::download_request(5, 0x6072, 1, 0xFFFFBEEF, 2));
    ASSERT_TRUE(r);
    EXPECT_EQ(r->size, 2);
    EXPECT_EQ(r->subindex, 1);
    EXPECT_EQ(r->value, 0xBEEFu);  // only the bytes the size covers
    // Size not indicated (e = 1, s = 0: 0x22): four bytes, size 0.
    r = sdo::decode_request(frame(0x605, {0x22, 0x80, 0x60, 0, 1, 2, 3, 4}));
    ASSERT_TRUE(r);
    EXPECT_EQ(r->kind, sdo::Request::Kind::download);
    EXPECT_EQ(r->size, 0);
    EXPECT_EQ(r->value, 0x04030201u);
    // An upload (0x40) and a segmented download (0x21) are not in the subset.
    EXPECT_EQ(sdo::decode_request(frame(0x605, {0x40, 0x80, 0x60, 0, 0, 0, 0, 0}))->kind, sdo::Request::Kind::unsupported);
    EXPECT_EQ(sdo::decode_request(frame(0x605, {0x21, 0x80, 0x60, 0, 8, 0, 0, 0}))->kind, sdo::Request::Kind::unsupported);
    r = sdo::decode_request(sdo::abort_frame(5, 0x6080, 0, sdo::kAbortTimeout, false));
    EXPECT_EQ(r->kind, sdo::Request::Kind::abort);
    EXPECT_EQ(r->value, sdo::kAbortTimeout);
    EXPECT_FALSE(sdo::decode_request(frame(0x605, {0x23, 0x80, 0x60, 0})));  // not 8 bytes
    EXPECT_FALSE(sdo::decode_request(sdo::download_response(5, 0x6080, 0)));  // a response
    EXPECT_FALSE(sdo::decode_request(frame(0x600, {0x23, 0x80, 0x60, 0, 0, 0, 0, 0})));  // node 0

    auto a = sdo::decode_response(sdo::abort_frame(5, 0x6080, 0, sdo::kAbortNoObject, true));
    ASSERT_TRUE(a);
    EXPECT_EQ(a->kind, sdo::Response::Kind::aborted);
    EXPECT_EQ(a->abort_code, 0x06020000u);
    EXPECT_EQ(a->index, 0x6080);
    a = sdo::decode_response(sdo::download_response(5, 0x6087, 0));
    EXPECT_EQ(a->kind, sdo::Response::Kind::downloaded);
    EXPECT_EQ(a->index, 0x6087);
    EXPECT_EQ(sdo::decode_response(frame(0x585, {0x43, 0x80, 0x60, 0, 0, 0, 0, 0}))->kind, sdo::Response::Kind::other);
    EXPECT_FALSE(sdo::decode_response(sdo::download_request(5, 0x6080, 0, 1)));
}

TEST(Sdo, DriveLimitsAreVlimitAndTrateInTheDrivesUnits) {
    const auto bus = BusConfig::from_local(
        rmod_from("ROBOT planar2\nINTERFACE vcan0\nNODES 3 4\nRATED_TORQUE 10 2\nVLIMIT 1 2.5\nTRATE 1000\n").local, 2);
    const auto d = drive_limit_downloads(bus);
    ASSERT_EQ(d.size(), 4u);
    // 1 rad/s at 2^20 counts/rev = 166886.05 counts/s, rounded down (never above VLIMIT).
    EXPECT_EQ(d[0].node, 3);
    EXPECT_EQ(d[0].joint, 0u);
    EXPECT_EQ(d[0].index, 0x6080);
    EXPECT_EQ(d[0].value, 166886u);
    EXPECT_EQ(d[1].index, 0x6087);
    EXPECT_EQ(d[1].value, 100000u);  // 1000 N m/s of 10 N m rated: 100 000 permille/s
    EXPECT_EQ(d[2].node, 4);
    EXPECT_EQ(d[2].value, 417215u);  // 2.5 rad/s
    EXPECT_EQ(d[3].value, 500000u);  // 1000 N m/s of 2 N m
    EXPECT_LE(from_counts(static_cast<std::int32_t>(d[2].value), kCounts), 2.5);
    EXPECT_EQ(max_motor_speed_counts(1e12, kCounts), 0x7FFFFFFFu);
    EXPECT_EQ(torque_slope_permille(1e-9, 10), 1u);
    EXPECT_TRUE(drive_limit_downloads(BusConfig::from_local(
                    rmod_from("ROBOT planar2\nINTERFACE vcan0\nNODES 3 4\nRATED_TORQUE 10\n").local, 2))
                    .empty());
}

// A bus with the drives on it, a clock the test moves, and every frame the
// drives sent.
class Drives : public ::testing::Test {
protected:
    Drives() : sim(planar_config()) {}

    void SetUp() override { sim.power_on(now, sent); }

    std::vector<Frame> send(const Frame& f) {
        std::vector<Frame> out;
        sim.receive(f, now, out);
        sent.insert(sent.end(), out.begin(), out.end());
        return out;
    }
    // Moves the clock to `t`, running every timer due on the way.
    std::vector<Frame> run_until(std::int64_t t) {
        std::vector<Frame> out;
        while (sim.next_timer() <= t) {
            now = std::max(now, sim.next_timer());
            sim.tick(now, out);
        }
        now = t;
        sim.tick(now, out);
        sent.insert(sent.end(), out.begin(), out.end());
        return out;
    }
    static std::vector<Frame> with_id(const std::vector<Frame>& frames, std::uint32_t id) {
        std::vector<Frame> r;
        for (const Frame& f : frames)
            if (f.id == id) r.push_back(f);
        return r;
    }
    void start_and_enable(std::int16_t mode, std::int16_t torque3 = 0, std::int16_t torque4 = 0) {
        send(nmt(NmtCommand::start, 0));
        std::uint16_t cw3 = 0, cw4 = 0;
        for (int i = 0; i < 3; ++i) {
            cw3 = controlword_toward_enabled(sim.state(0), cw3);
            cw4 = controlword_toward_enabled(sim.state(1), cw4);
            send(rpdo1(3, cw3, mode, torque3));
            send(rpdo1(4, cw4, mode, torque4));
        }
        ASSERT_EQ(sim.state(0), DriveState::operation_enabled);
        ASSERT_EQ(sim.state(1), DriveState::operation_enabled);
    }
    // A master cycling at `period`: targets, then SYNC, for `seconds`.
    void master_cycles(double seconds, std::int64_t period, const std::function<void()>& targets) {
        const std::int64_t end = now + static_cast<std::int64_t>(seconds * 1e9);
        while (now < end) {
            run_until(now + period);
            targets();
            send(sync_frame());
        }
    }

    std::int64_t now = 5 * kMs;
    DriveSim sim;
    std::vector<Frame> sent;
};

TEST_F(Drives, PowerOnSendsBootUpAndWaitsPreoperational) {
    ASSERT_EQ(sent.size(), 2u);
    EXPECT_EQ(sent[0].id, 0x703u);
    EXPECT_EQ(sent[1].id, 0x704u);
    EXPECT_EQ(sent[0].len, 1);
    EXPECT_EQ(sent[0].data[0], 0x00);  // boot-up
    EXPECT_EQ(sim.nmt(0), NmtState::preoperational);
    EXPECT_EQ(sim.state(0), DriveState::switch_on_disabled);
    // Heartbeats every 100 ms, carrying the NMT state.
    auto beats = with_id(run_until(now + 250 * kMs), 0x703);
    ASSERT_EQ(beats.size(), 2u);
    EXPECT_EQ(beats[0].data[0], 0x7F);
}

TEST_F(Drives, PdosAreIgnoredUntilNmtStart) {
    EXPECT_TRUE(send(rpdo1(3, kCwShutdown, kModeCst, 0)).empty());
    EXPECT_TRUE(send(sync_frame()).empty());  // no TPDO2 either
    EXPECT_EQ(sim.state(0), DriveState::switch_on_disabled);
    EXPECT_EQ(sim.ignored_frames(), 1u);

    // Start node 4 only: it answers with its TPDO1 at once.
    auto out = send(nmt(NmtCommand::start, 4));
    ASSERT_EQ(out.size(), 1u);
    EXPECT_EQ(out[0].id, 0x184u);
    EXPECT_EQ(get_u16(out[0], 0), 0x0240);  // switch on disabled
    EXPECT_EQ(sim.nmt(0), NmtState::preoperational);
    EXPECT_EQ(sim.nmt(1), NmtState::operational);
    EXPECT_EQ(with_id(run_until(now + 100 * kMs), 0x704).at(0).data[0], 0x05);
}

TEST_F(Drives, EnablingWalksTheStateMachineAndReportsEachStep) {
    send(nmt(NmtCommand::start, 0));
    sent.clear();
    for (std::uint16_t cw : {kCwShutdown, kCwSwitchOn, kCwEnableOperation}) send(rpdo1(3, cw, kModeCst, 0));
    const auto tpdo1 = with_id(sent, 0x183);
    ASSERT_EQ(tpdo1.size(), 3u);  // on change: once per state, and the mode appeared with the first
    EXPECT_EQ(get_u16(tpdo1[0], 0), 0x0221);
    EXPECT_EQ(static_cast<std::int16_t>(get_u16(tpdo1[0], 2)), kModeCst);
    EXPECT_EQ(get_u16(tpdo1[1], 0), 0x0233);
    EXPECT_EQ(get_u16(tpdo1[2], 0), 0x0237);
    EXPECT_EQ(sim.state(0), DriveState::operation_enabled);
    EXPECT_EQ(sim.state(1), DriveState::switch_on_disabled);
    // Unchanged status: no TPDO1 until the event timer.
    EXPECT_TRUE(send(rpdo1(3, kCwEnableOperation, kModeCst, 0)).empty());
}

TEST_F(Drives, SyncLatchesPositionAndVelocity) {
    send(nmt(NmtCommand::start, 0));
    const auto out = send(sync_frame());
    ASSERT_EQ(with_id(out, 0x283).size(), 1u);
    ASSERT_EQ(with_id(out, 0x284).size(), 1u);
    const Frame f = with_id(out, 0x284)[0];
    EXPECT_EQ(f.len, 8);
    EXPECT_EQ(static_cast<std::int32_t>(get_u32(f, 0)), to_counts(-0.3, kCounts));
    EXPECT_EQ(static_cast<std::int32_t>(get_u32(f, 4)), 0);
    EXPECT_EQ(sim.syncs(), 1u);
}

TEST_F(Drives, BrakesHoldTheArmWhileNotEnabled) {
    send(nmt(NmtCommand::start, 0));
    run_until(now + 2000 * kMs);  // gravity pulls, for two seconds
    EXPECT_DOUBLE_EQ(sim.q()[0], 0.4);
    EXPECT_DOUBLE_EQ(sim.q()[1], -0.3);
    EXPECT_EQ(sim.torque(0), 0.0);
}

TEST_F(Drives, TargetTorqueTakesEffectAtSyncAndHoldsAgainstGravity) {
    rb::Dynamics dyn(rb::planar2());
    Eigen::VectorXd g(2);
    ASSERT_TRUE(dyn.gravity(sim.q(), g));
    const auto t3 = torque_to_permille(g[0], 10.0), t4 = torque_to_permille(g[1], 10.0);
    start_and_enable(kModeCst, t3, t4);
    run_until(now + kMs);
    EXPECT_EQ(sim.torque(0), 0.0);  // received, not in effect before the SYNC
    EXPECT_EQ(sim.torque(1), 0.0);
    send(sync_frame());
    run_until(now + kMs);
    EXPECT_NEAR(sim.torque(0), g[0], 0.005);
    EXPECT_NEAR(sim.torque(1), g[1], 0.005);

    // A 500 Hz master sending the gravity torques, open loop: the raised arm
    // is an unstable equilibrium, so the quantised torques (and the millisecond
    // of zero torque before the first SYNC) drift it, slowly.
    master_cycles(0.3, 2 * kMs, [&] {
        send(rpdo1(3, kCwEnableOperation, kModeCst, t3));
        send(rpdo1(4, kCwEnableOperation, kModeCst, t4));
    });
    EXPECT_NEAR(sim.q()[0], 0.4, 5e-3);
    EXPECT_NEAR(sim.q()[1], -0.3, 5e-3);
    EXPECT_EQ(sim.state(0), DriveState::operation_enabled);

    // Zero torque for as long: the arm falls.
    master_cycles(0.3, 2 * kMs, [&] {
        send(rpdo1(3, kCwEnableOperation, kModeCst, 0));
        send(rpdo1(4, kCwEnableOperation, kModeCst, 0));
    });
    EXPECT_GT(std::fabs(sim.q()[0] - 0.4), 0.1);
}

TEST_F(Drives, TorqueIsLimitedToTheDrivesMaximum) {
    start_and_enable(kModeCst, 32767, -32768);
    send(sync_frame());
    run_until(now + kMs);
    EXPECT_DOUBLE_EQ(sim.torque(0), 327.67);  // the bus's maximum for RATED_TORQUE 10 = the default TLIMIT
    EXPECT_DOUBLE_EQ(sim.torque(1), -327.67);
}

TEST_F(Drives, NoRpdoWithinTheTimeoutFaultsAndBrakes) {
    start_and_enable(kModeCst);
    sent.clear();
    run_until(now + 40 * kMs);
    EXPECT_EQ(sim.state(0), DriveState::operation_enabled);  // 40 ms < 50 ms
    run_until(now + 20 * kMs);
    EXPECT_EQ(sim.state(0), DriveState::fault);
    EXPECT_EQ(sim.error_code(0), kErrRpdoTimeout);
    const auto tpdo1 = with_id(sent, 0x183);
    ASSERT_FALSE(tpdo1.empty());
    EXPECT_EQ(decode_statusword(get_u16(tpdo1.back(), 0)), DriveState::fault);
    EXPECT_EQ(get_u16(tpdo1.back(), 4), kErrRpdoTimeout);
    // Braked where it was: gravity no longer moves it.
    const double q = sim.q()[0];
    run_until(now + 500 * kMs);
    EXPECT_DOUBLE_EQ(sim.q()[0], q);
}

TEST_F(Drives, FaultResetOnTheRisingEdgeClearsTheError) {
    start_and_enable(kModeCst);
    run_until(now + 100 * kMs);
    ASSERT_EQ(sim.state(0), DriveState::fault);
    send(rpdo1(3, kCwEnableOperation, kModeCst, 0));
    EXPECT_EQ(sim.state(0), DriveState::fault);  // enable does not leave fault
    send(rpdo1(3, kCwFaultReset, kModeCst, 0));
    EXPECT_EQ(sim.state(0), DriveState::switch_on_disabled);
    EXPECT_EQ(sim.error_code(0), kErrNone);
}

TEST_F(Drives, AnUnsupportedModeIsAFault) {
    start_and_enable(kModeCst);
    send(rpdo1(3, kCwEnableOperation, 3 /* profile velocity */, 0));
    EXPECT_EQ(sim.state(0), DriveState::fault);
    EXPECT_EQ(sim.error_code(0), kErrParameter);
    EXPECT_EQ(sim.mode(0), 3);
}

TEST_F(Drives, NmtStopIgnoresPdosSoTheRpdoTimeoutStopsTheDrive) {
    start_and_enable(kModeCst);
    send(nmt(NmtCommand::stop, 3));
    EXPECT_EQ(sim.nmt(0), NmtState::stopped);
    for (int i = 0; i < 40; ++i) {
        run_until(now + 2 * kMs);
        send(rpdo1(3, kCwEnableOperation, kModeCst, 0));
        send(rpdo1(4, kCwEnableOperation, kModeCst, 0));
    }
    EXPECT_EQ(sim.state(0), DriveState::fault);             // its RPDOs were ignored
    EXPECT_EQ(sim.state(1), DriveState::operation_enabled);  // node 4 is served
}

TEST_F(Drives, ResetNodeRebootsItsCommunicationAndDisablesIt) {
    start_and_enable(kModeCst);
    const auto out = send(nmt(NmtCommand::reset_node, 4));
    ASSERT_EQ(with_id(out, 0x704).size(), 1u);
    EXPECT_EQ(with_id(out, 0x704)[0].data[0], 0x00);
    EXPECT_EQ(sim.nmt(1), NmtState::preoperational);
    EXPECT_EQ(sim.state(1), DriveState::switch_on_disabled);
    EXPECT_EQ(sim.state(0), DriveState::operation_enabled);
}

TEST_F(Drives, CspHoldsWhereEnabledAndFollowsTargets) {
    start_and_enable(kModeCsp);
    // No RPDO2 yet: the drive holds where it was enabled, against gravity.
    master_cycles(1.0, 2 * kMs, [&] {
        send(rpdo1(3, kCwEnableOperation, kModeCsp, 0));
        send(rpdo1(4, kCwEnableOperation, kModeCsp, 0));
    });
    EXPECT_NEAR(sim.q()[0], 0.4, 2e-3);
    EXPECT_NEAR(sim.q()[1], -0.3, 2e-3);
    // A target 0.1 rad away is reached.
    master_cycles(2.0, 2 * kMs, [&] {
        send(rpdo1(3, kCwEnableOperation, kModeCsp, 0));
        send(rpdo2(3, to_counts(0.5, kCounts), 0));
        send(rpdo1(4, kCwEnableOperation, kModeCsp, 0));
    });
    EXPECT_NEAR(sim.q()[0], 0.5, 2e-3);
    EXPECT_NEAR(sim.q()[1], -0.3, 2e-3);
}

TEST_F(Drives, FramesForOtherNodesAreNotAnswered) {
    send(nmt(NmtCommand::start, 5));
    EXPECT_EQ(sim.nmt(0), NmtState::preoperational);
    send(nmt(NmtCommand::start, 0));
    EXPECT_TRUE(send(rpdo1(5, kCwShutdown, kModeCst, 0)).empty());
    EXPECT_TRUE(send(frame(0x185, {0, 0})).empty());
    EXPECT_EQ(sim.state(0), DriveState::switch_on_disabled);
}

// --- the drives' own limits, downloaded by SDO ---------------------------------------------

Frame sdo_download(int node, std::uint16_t index, std::uint32_t value, std::uint8_t size = 4, std::uint8_t sub = 0) {
    return sdo::download_request(node, index, sub, value, size);
}

TEST_F(Drives, AnswersSdoDownloadsOfItsLimitsAndAbortsTheRest) {
    EXPECT_EQ(sim.nmt(0), NmtState::preoperational);  // SDO works before NMT start
    EXPECT_TRUE(std::isinf(sim.max_speed(0)));
    EXPECT_TRUE(std::isinf(sim.torque_slope(0)));
    auto answer = [&](const Frame& request) {
        const auto out = send(request);
        EXPECT_EQ(out.size(), 1u);
        return out.empty() ? Frame{} : out[0];
    };
    Frame a = answer(sdo_download(3, 0x6080, 166886));
    EXPECT_EQ(a.id, 0x583u);
    EXPECT_EQ(bytes_of(a), bytes_of(sdo::download_response(3, 0x6080, 0)));
    EXPECT_NEAR(sim.max_speed(0), 1.0, 1e-5);
    EXPECT_LE(sim.max_speed(0), 1.0);
    EXPECT_TRUE(std::isinf(sim.max_speed(1)));  // node 4 untouched
    a = answer(sdo_download(4, 0x6087, 2500));
    EXPECT_EQ(bytes_of(a), bytes_of(sdo::download_response(4, 0x6087, 0)));
    EXPECT_DOUBLE_EQ(sim.torque_slope(1), 25.0);  // 2500 permille/s of 10 N m
    a = answer(sdo_download(3, 0x6072, 500, 2));
    EXPECT_EQ(bytes_of(a), bytes_of(sdo::download_response(3, 0x6072, 0)));
    EXPECT_DOUBLE_EQ(sim.torque_limit(0), 5.0);
    // Refusals, each an abort naming the object.
    auto refused = [&](const Frame& request, std::uint16_t index, std::uint8_t sub, std::uint32_t code) {
        EXPECT_EQ(bytes_of(answer(request)), bytes_of(sdo::abort_frame(request.id - 0x600, index, sub, code, true)))
            << std::hex << index << " code " << code;
    };
    refused(sdo_download(3, 0x6081, 100), 0x6081, 0, 0x06020000);          // profile velocity: not in this drive
    refused(sdo_download(3, 0x1017, 100, 2), 0x1017, 0, 0x06020000);       // heartbeat time: a .rmod key here
    refused(sdo_download(3, 0x6080, 0), 0x6080, 0, 0x06090030);            // a drive that cannot move
    refused(sdo_download(3, 0x6080, 0x80000000u), 0x6080, 0, 0x06090030);  // beyond the i32 of 0x606C
    refused(sdo_download(4, 0x6087, 0), 0x6087, 0, 0x06090030);
    refused(sdo_download(3, 0x6072, 40000, 2), 0x6072, 0, 0x06090030);
    refused(sdo_download(3, 0x6080, 100, 4, 1), 0x6080, 1, 0x06090011);    // no sub-index 1
    refused(sdo_download(3, 0x6080, 100, 2), 0x6080, 0, 0x06070010);       // a u32 sent as 2 bytes
    refused(frame(0x603, {0x40, 0x80, 0x60, 0, 0, 0, 0, 0}), 0x6080, 0, 0x05040001);  // upload: not in the subset
    EXPECT_NEAR(sim.max_speed(0), 1.0, 1e-5);  // the refused values changed nothing
    EXPECT_DOUBLE_EQ(sim.torque_slope(1), 25.0);
    EXPECT_TRUE(send(sdo::abort_frame(3, 0x6080, 0, sdo::kAbortTimeout, false)).empty());  // the master's abort: no answer
    EXPECT_TRUE(send(frame(0x603, {0x23, 0x80, 0x60, 0})).empty());  // not 8 bytes: ignored
}

TEST_F(Drives, SdoIsNotAnsweredWhenStoppedAndResetNodeForgetsTheLimits) {
    send(nmt(NmtCommand::start, 0));
    EXPECT_EQ(send(sdo_download(3, 0x6080, 1000)).size(), 1u);  // operational: answered
    send(nmt(NmtCommand::stop, 3));
    EXPECT_TRUE(send(sdo_download(3, 0x6080, 2000)).empty());
    EXPECT_DOUBLE_EQ(sim.max_speed(0), from_counts(1000, kCounts));
    send(nmt(NmtCommand::reset_node, 3));
    EXPECT_TRUE(std::isinf(sim.max_speed(0)));
}

// The drives of the planar arm with no RPDO deadline: a master that stops
// sending leaves the last torque applied for as long as the test runs.
DriveConfig planar_no_deadline() {
    return DriveConfig::from_rmod(rmod_from("ROBOT planar2\nINTERFACE vcan0\nNODES 3 4\nRATED_TORQUE 10\nQ0 0.4 -0.3\n"
                                            "DRIVE_RPDO_TIMEOUT 0\nDRIVE_STEP 0.00025\n"));
}

// Enables both drives in CST and applies `torque` (permille) at a SYNC, then
// never sends again; runs 1 s one integration step at a time, calling
// `each_step` after each.
void dead_master(DriveSim& sim, std::int16_t torque3, std::int16_t torque4, const std::function<void()>& each_step,
                 const std::vector<Frame>& downloads = {}) {
    std::vector<Frame> out;
    std::int64_t now = 0;
    sim.power_on(now, out);
    for (const Frame& f : downloads) sim.receive(f, now, out);
    sim.receive(nmt(NmtCommand::start, 0), now, out);
    std::uint16_t cw3 = 0, cw4 = 0;
    for (int i = 0; i < 3; ++i) {
        cw3 = controlword_toward_enabled(sim.state(0), cw3);
        cw4 = controlword_toward_enabled(sim.state(1), cw4);
        sim.receive(rpdo1(3, cw3, kModeCst, torque3), now, out);
        sim.receive(rpdo1(4, cw4, kModeCst, torque4), now, out);
    }
    sim.receive(sync_frame(), now, out);
    ASSERT_EQ(sim.state(0), DriveState::operation_enabled);
    const auto step = static_cast<std::int64_t>(sim.config().max_step * 1e9);
    for (int s = 0; s < 4000; ++s) {
        now += step;
        out.clear();
        sim.tick(now, out);  // exactly one integration step
        each_step();
    }
    EXPECT_EQ(sim.state(0), DriveState::operation_enabled);  // nothing stopped it but its own limits
}

TEST(DriveLimits, MaxMotorSpeedHoldsUnderATorqueADeadMasterLeftOn) {
    // 30 and -20 N m (3000, -2000 permille of 10 N m), then silence: without
    // 0x6080 both joints run away.
    {
        DriveSim sim(planar_no_deadline());
        double peak0 = 0, peak1 = 0;
        dead_master(sim, 3000, -2000, [&] {
            peak0 = std::max(peak0, std::fabs(sim.qd()[0]));
            peak1 = std::max(peak1, std::fabs(sim.qd()[1]));
        });
        EXPECT_GT(peak0, 5.0);
        EXPECT_GT(peak1, 5.0);
    }
    // With 0.5 and 1 rad/s downloaded, at the end of every integration step
    // each joint is within its limit — and reaches it (the torque drives it there).
    DriveSim sim(planar_no_deadline());
    const std::uint32_t v0 = max_motor_speed_counts(0.5, kCounts), v1 = max_motor_speed_counts(1.0, kCounts);
    const double lim0 = from_counts(static_cast<std::int32_t>(v0), kCounts);
    const double lim1 = from_counts(static_cast<std::int32_t>(v1), kCounts);
    double peak0 = 0, peak1 = 0;
    int steps = 0;
    dead_master(sim, 3000, -2000, [&] {
        ++steps;
        EXPECT_LE(std::fabs(sim.qd()[0]), lim0) << "step " << steps;
        EXPECT_LE(std::fabs(sim.qd()[1]), lim1) << "step " << steps;
        peak0 = std::max(peak0, std::fabs(sim.qd()[0]));
        peak1 = std::max(peak1, std::fabs(sim.qd()[1]));
    }, {sdo_download(3, 0x6080, v0), sdo_download(4, 0x6080, v1)});
    EXPECT_EQ(steps, 4000);
    EXPECT_GT(peak0, 0.999 * lim0);
    EXPECT_GT(peak1, 0.999 * lim1);
    EXPECT_GT(sim.speed_limited_steps(), 1000u);
    // The drive did it by changing the torque it applies (not the 30 N m
    // asked for: against gravity and the other link, braking may need more),
    // within its torque limit.
    EXPECT_NE(sim.torque(0), 30.0);
    EXPECT_LE(std::fabs(sim.torque(0)), sim.torque_limit(0));
    EXPECT_LE(std::fabs(sim.torque(1)), sim.torque_limit(1));
}

TEST(DriveLimits, TheSpeedLimitedStepAllocatesNothing) {
    // candrive steps the arm in its real-time thread: holding 0x6080 re-steps
    // and solves for the joints over their limit, from storage sized once.
    DriveSim sim(planar_no_deadline());
    const std::uint32_t v0 = max_motor_speed_counts(0.5, kCounts), v1 = max_motor_speed_counts(1.0, kCounts);
    int steps = 0;
    long allocations = -1;
    std::uint64_t limited_before = 0;
    dead_master(sim, 3000, -2000, [&] {
        ++steps;
        if (steps == 1000) {
            limited_before = sim.speed_limited_steps();
            chimera::test::alloc_count_start();
        } else if (steps == 3000) {
            allocations = chimera::test::alloc_count_stop();
        }
    }, {sdo_download(3, 0x6080, v0), sdo_download(4, 0x6080, v1)});
    EXPECT_GT(sim.speed_limited_steps() - limited_before, 1000u);  // the limit was at work meanwhile
    EXPECT_EQ(allocations, 0);
}

TEST(DriveLimits, TorqueSlopeBoundsEveryStepOfTheAppliedTorque) {
    // 0x6087 = 100 000 permille/s = 1000 N m/s of 10 N m: a step to 30 N m
    // takes 30 ms, at most 0.25 N m per 0.25 ms step; the other joint, with no
    // slope, jumps at once.
    DriveSim sim(planar_no_deadline());
    double last0 = 0, step0 = 0;
    int steps = 0, ramp_steps = 0;
    bool jumped = false;
    dead_master(sim, 3000, 1000, [&] {
        if (++steps == 1) jumped = std::fabs(sim.torque(1) - 10.0) < 1e-9;
        step0 = std::max(step0, std::fabs(sim.torque(0) - last0));
        if (std::fabs(sim.torque(0) - 30.0) > 1e-9) ramp_steps = steps;
        last0 = sim.torque(0);
    }, {sdo_download(3, 0x6087, 100000)});
    EXPECT_LE(step0, 1000.0 * 0.00025 + 1e-9);
    EXPECT_GE(step0, 1000.0 * 0.00025 - 1e-9);
    EXPECT_EQ(ramp_steps, 119);  // 30 N m / 0.25 N m: the 120th step applies the target
    EXPECT_TRUE(jumped);
}

// A master's downloads (sdo::DownloadSequence) against the drives: what
// canrobot does at init when VLIMIT or TRATE is declared.
struct DownloadRun {
    bool done = false, failed = false;
    std::string failure, unconfirmed;
    std::size_t requests = 0;
};
DownloadRun run_downloads(DriveSim& sim, std::vector<sdo::Download> downloads) {
    sdo::DownloadSequence seq(std::move(downloads), "vcan0");
    std::vector<Frame> to_drives, from_drives;
    DownloadRun r;
    seq.start(to_drives);
    // Until nothing more is sent (the caller's timeout, here: the bus is quiet).
    while (!to_drives.empty()) {
        r.requests += to_drives.size();
        from_drives.clear();
        for (const Frame& f : to_drives) sim.receive(f, 0, from_drives);
        to_drives.clear();
        for (const Frame& f : from_drives) seq.receive(f, to_drives);
    }
    r.done = seq.done();
    r.failed = seq.failed();
    r.failure = seq.failure();
    r.unconfirmed = seq.unconfirmed();
    return r;
}

TEST(DriveLimits, TheMastersDownloadsSetEveryDrivesLimitsOrNameTheRefusal) {
    DriveSim sim(DriveConfig::from_rmod(rmod_from(
        "ROBOT puma560\nINTERFACE vcan0\nNODES 1 2 3 4 5 6\nRATED_TORQUE 10 10 10 1 1 1\n"
        "VLIMIT 1 1 1 2 2 2\nTRATE 1000 2000 1000 200 200 200\n")));
    std::vector<Frame> out;
    sim.power_on(0, out);
    const auto downloads = drive_limit_downloads(sim.config().bus);
    ASSERT_EQ(downloads.size(), 12u);
    const DownloadRun ok = run_downloads(sim, downloads);
    EXPECT_TRUE(ok.done);
    EXPECT_EQ(ok.requests, 12u);
    EXPECT_EQ(ok.unconfirmed, "");
    for (std::size_t j = 0; j < 6; ++j) {
        const double v = j < 3 ? 1.0 : 2.0;
        EXPECT_LE(sim.max_speed(j), v);
        EXPECT_GT(sim.max_speed(j), v - 1e-5);
        EXPECT_NEAR(sim.torque_slope(j), sim.config().bus.trate[static_cast<Eigen::Index>(j)], 1e-9);
    }
    // A drive that refuses: the first abort fails the sequence, naming node,
    // joint, object, value and abort code; nothing more is sent.
    std::vector<sdo::Download> bad = downloads;
    bad[4].value = 0;  // node 3's 0x6080
    const DownloadRun refused = run_downloads(sim, bad);
    EXPECT_FALSE(refused.done);
    EXPECT_TRUE(refused.failed);
    EXPECT_EQ(refused.failure,
              "node 3 (joint 3) on vcan0 refused 0x6080 max motor speed = 0: SDO abort 0x06090030 value range of "
              "parameter exceeded");
    const DownloadRun unknown = run_downloads(sim, {{2, 1, 0x6081, 5, 4}});
    EXPECT_EQ(unknown.failure,
              "node 2 (joint 2) on vcan0 refused 0x6081 = 5: SDO abort 0x06020000 object does not exist in the object "
              "dictionary");
    // A node that is not on the bus never answers: the caller's timeout
    // names what is unconfirmed.
    const DownloadRun silent = run_downloads(sim, {{1, 0, 0x6080, 5, 4}, {9, 1, 0x6080, 5, 4}, {9, 1, 0x6087, 5, 4}});
    EXPECT_FALSE(silent.done);
    EXPECT_FALSE(silent.failed);
    EXPECT_EQ(silent.unconfirmed,
              "node 9 (joint 2) on vcan0: 0x6080 max motor speed not confirmed; node 9 (joint 2) on vcan0: 0x6087 "
              "torque slope not confirmed");
}

TEST(DriveSimPuma, ThePumaStartsAtQ0Braked) {
    DriveSim sim(DriveConfig::from_rmod(chimera::read_rmod(CANROBOT_RMOD_DIR "/puma_can.rmod")));
    std::vector<Frame> out;
    sim.power_on(0, out);
    EXPECT_EQ(out.size(), 6u);
    sim.tick(1'000'000'000, out);
    EXPECT_NEAR(sim.q()[1], 0.785398, 1e-9);
    EXPECT_NEAR(sim.q()[2], 3.141593, 1e-9);
}

// The loop the guest test runs over a real bus (CanRobotGuest.AReferenceThatJumps...),
// here exactly: the simulated PUMA's drives, and a master that does each cycle
// what canrobot does — read the TPDO2 latched at the previous SYNC, compute a
// torque, limit it with CommandLimiter, send RPDO1, then SYNC — with a PD
// controller (jpid's gains, ULIMIT) whose reference jumps 0.6 rad on every joint.
struct LoopPeaks {
    Eigen::VectorXd speed_at_sync, speed_any, step;  // rad/s; rad/s between SYNCs too; N m per cycle
    Eigen::VectorXd step_unclamped;  // N m per cycle, over the cycles the speed envelope did not act
    Eigen::VectorXd unit;            // N m, the bus's torque unit (RATED_TORQUE / 1000)
    std::uint64_t speed_clamps = 0, rate_clamps = 0;
};
// `drive_limits`: the drives get VLIMIT and TRATE as their own 0x6080 and
// 0x6087 before NMT start, downloaded as canrobot does at init.
LoopPeaks closed_loop_jump(const std::string& limits, double freq, int late_every = 0, int late_by = 1,
                           bool drive_limits = false) {
    auto cfg = DriveConfig::from_rmod(rmod_from(
        "ROBOT puma560\nINTERFACE vcan0\nNODES 1 2 3 4 5 6\nRATED_TORQUE 10 10 10 1 1 1\n"
        "TLIMIT 97.6 186.4 89.4 24.2 20.1 21.3\nQ0 0 0.785398 3.141593 0 0.785398 0\nDRIVE_RPDO_TIMEOUT 0\n" + limits));
    cfg.max_step = 0.0005;
    DriveSim sim(cfg);
    rb::Dynamics dyn(cfg.model);
    CommandLimiter lim(cfg.bus, false);
    const Eigen::Index n = 6;
    const double dt = 1.0 / freq;
    const auto period = static_cast<std::int64_t>(dt * 1e9);
    std::int64_t now = 0;
    std::vector<Frame> out;
    sim.power_on(now, out);
    auto send = [&](const Frame& f) { out.clear(); sim.receive(f, now, out); };
    if (drive_limits) {
        const DownloadRun r = run_downloads(sim, drive_limit_downloads(cfg.bus));
        EXPECT_TRUE(r.done) << r.failure << r.unconfirmed;
    }
    send(nmt(NmtCommand::start, 0));
    Eigen::VectorXd q = cfg.q0, qd = Eigen::VectorXd::Zero(n), g(n), tau(n), target = cfg.q0.array() + 0.6;
    dyn.gravity(q, g);
    std::vector<std::uint16_t> cw(6, 0);
    for (int i = 0; i < 4; ++i)
        for (int j = 0; j < 6; ++j) {
            cw[j] = controlword_toward_enabled(sim.state(j), cw[j]);
            send(rpdo1(j + 1, cw[j], kModeCst, torque_to_permille(g[j], cfg.bus.rated_torque[j])));
        }
    send(sync_frame());
    lim.reset(g);
    const Eigen::VectorXd kp = (Eigen::VectorXd(6) << 400, 800, 400, 40, 40, 20).finished();
    const Eigen::VectorXd kd = (Eigen::VectorXd(6) << 60, 120, 60, 6, 6, 3).finished();
    LoopPeaks p;
    p.speed_at_sync = p.speed_any = p.step = p.step_unclamped = Eigen::VectorXd::Zero(n);
    p.unit = cfg.bus.rated_torque / 1000;
    Eigen::VectorXd last_sent = g, last_limited = g;
    for (int k = 0; k < static_cast<int>(4 * freq); ++k) {
        // The cycle's start: late by `late_by` periods every `late_every` cycles.
        const int wait = late_every && k % late_every == late_every - 1 ? late_by : 1;
        for (int s = 0; s < 10 * wait; ++s) {
            now += period / 10;
            out.clear();
            sim.tick(now, out);
            p.speed_any = p.speed_any.cwiseMax(sim.qd().cwiseAbs());
        }
        dyn.gravity(q, g);
        tau = (kp.array() * (target - q).array() - kd.array() * qd.array()).matrix();
        for (Eigen::Index j = 0; j < n; ++j) tau[j] = std::clamp(tau[j], -cfg.bus.torque_limit[j], cfg.bus.torque_limit[j]);
        // Which joints the speed envelope cuts (robotics/limits.hpp's order:
        // TLIMIT, then TRATE from the torque sent before, then the envelope).
        std::vector<bool> cut(6, false);
        for (Eigen::Index j = 0; j < n; ++j) {
            const double tl = cfg.bus.torque_limit[j], v = cfg.bus.vlimit[j], step = cfg.bus.trate[j] * dt;
            const double rated = std::clamp(std::clamp(tau[j], -tl, tl), last_limited[j] - step, last_limited[j] + step);
            if (std::isfinite(v))
                cut[j] = rated > g[j] + tl / v * (v - qd[j]) || rated < g[j] - tl / v * (v + qd[j]);
        }
        lim.limit_torque(tau, qd, g, dt);
        for (Eigen::Index j = 0; j < n; ++j) {
            const std::int16_t pm = torque_to_permille(tau[j], cfg.bus.rated_torque[j]);
            const double sent_t = permille_to_torque(pm, cfg.bus.rated_torque[j]);
            p.step[j] = std::max(p.step[j], std::fabs(sent_t - last_sent[j]));
            if (!cut[j]) p.step_unclamped[j] = std::max(p.step_unclamped[j], std::fabs(sent_t - last_sent[j]));
            last_sent[j] = sent_t;
            last_limited[j] = tau[j];
            send(rpdo1(static_cast<int>(j) + 1, kCwEnableOperation, kModeCst, pm));
        }
        out.clear();
        sim.receive(sync_frame(), now, out);
        for (const Frame& f : out)
            if (f.id > kTpdo2 && f.id <= kTpdo2 + 6) {
                const auto j = static_cast<Eigen::Index>(f.id - kTpdo2 - 1);
                q[j] = from_counts(static_cast<std::int32_t>(get_u32(f, 0)), kCounts);
                qd[j] = from_counts(static_cast<std::int32_t>(get_u32(f, 4)), kCounts);
                p.speed_at_sync[j] = std::max(p.speed_at_sync[j], std::fabs(qd[j]));
            }
    }
    p.speed_clamps = lim.speed_clamps();
    p.rate_clamps = lim.rate_clamps();
    return p;
}

constexpr const char* kPumaLimited = "VLIMIT 1 1 1 2 2 2\nTRATE 1000 2000 1000 200 200 200\n";

TEST(CanRobotLimits, AJumpingReferenceMovesTheSimulatedPumaNoFasterThanVlimit) {
    const Eigen::VectorXd vlimit = (Eigen::VectorXd(6) << 1, 1, 1, 2, 2, 2).finished();
    // The provocation is real: without limits the jump drives every joint
    // past its VLIMIT (2.4 to 3.1 rad/s at the torque limits).
    const LoopPeaks free = closed_loop_jump("", 200);
    for (Eigen::Index j = 0; j < 6; ++j) EXPECT_GT(free.speed_any[j], vlimit[j]) << "joint " << j + 1;
    // With the limits, at 200 and 500 Hz, no joint reaches its VLIMIT — at the
    // SYNCs nor between them (ten times a cycle) — though the controller asks
    // for its torque limit: the envelope cut the torque (0.72 to 0.97 x VLIMIT).
    for (double freq : {200.0, 500.0}) {
        const LoopPeaks p = closed_loop_jump(kPumaLimited, freq);
        for (Eigen::Index j = 0; j < 6; ++j)
            EXPECT_LE(p.speed_any[j], vlimit[j]) << "joint " << j + 1 << " at " << freq << " Hz";
        EXPECT_GT(p.speed_clamps, 0u);
        EXPECT_GT(p.rate_clamps, 0u);
        // TRATE held on every cycle where the speed envelope did not cut the
        // torque; where it did, the speed limit wins (robotics/limits.hpp)
        // and the step may be larger — toward braking.
        const Eigen::VectorXd trate = (Eigen::VectorXd(6) << 1000, 2000, 1000, 200, 200, 200).finished();
        for (Eigen::Index j = 0; j < 6; ++j)
            EXPECT_LE(p.step_unclamped[j], trate[j] / freq + p.unit[j] + 1e-9) << "joint " << j + 1 << " at " << freq << " Hz";
    }
    // TRATE alone: every cycle's step is within TRATE x period (plus the bus's
    // unit of torque, for rounding), and the arm, unlimited in speed, still
    // gets there faster than VLIMIT would allow.
    const LoopPeaks rate = closed_loop_jump("TRATE 1000 2000 1000 200 200 200\n", 200);
    const Eigen::VectorXd step = (Eigen::VectorXd(6) << 5, 10, 5, 1, 1, 1).finished();
    for (Eigen::Index j = 0; j < 6; ++j) EXPECT_LE(rate.step[j], step[j] + rate.unit[j] + 1e-9) << "joint " << j + 1;
    EXPECT_EQ(rate.speed_clamps, 0u);
}

// A master that is late (its cycle 3 periods long every 10th cycle) leaves the
// last torque applied for those periods: the speed limit, applied by the
// master on speeds a cycle old, is then passed (joint 3: 1.13 rad/s against
// VLIMIT 1; at 50 Hz, on time, up to 3.2 x VLIMIT). With VLIMIT and TRATE
// downloaded into the drives (0x6080, 0x6087), as canrobot does at init, the
// drives hold every joint within VLIMIT whatever the master does — checked at
// every integration step at 200 Hz (ten ticks a 5 ms cycle, 0.5 ms steps).
TEST(CanRobotLimits, TheDrivesOwnLimitsHoldVlimitWhenTheMasterIsLate) {
    const Eigen::VectorXd vlimit = (Eigen::VectorXd(6) << 1, 1, 1, 2, 2, 2).finished();
    // The provocation: the master's limits alone let joint 3 pass VLIMIT.
    const LoopPeaks master_only = closed_loop_jump(kPumaLimited, 200, 10, 3);
    EXPECT_GT(master_only.speed_any[2], 1.05);
    for (const auto& [freq, every, by] : {std::tuple{200.0, 10, 3}, std::tuple{200.0, 3, 10}, std::tuple{50.0, 0, 1}}) {
        const LoopPeaks p = closed_loop_jump(kPumaLimited, freq, every, by, true);
        for (Eigen::Index j = 0; j < 6; ++j)
            EXPECT_LE(p.speed_any[j], vlimit[j])
                << "joint " << j + 1 << " at " << freq << " Hz, late by " << by << " every " << every;
        EXPECT_GT(p.speed_any.maxCoeff(), 0.5) << "the arm moved";
    }
}

}  // namespace
