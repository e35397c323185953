// canrobot — robot interface over a CAN bus (thesis §7.3: an SAI driver as a
// port-based object). It drives one CANopen joint drive per joint with the
// CiA 402 subset of canrobot/cia402.hpp, through the IOD RCB driver (§7.2), and
// has exactly the ports of robotsim, so a subsystem runs against the real arm
// (or the simulated drives of `candrive`) or against the in-process simulation
// by swapping this one module (transparent simulation).
//
// Ports (internal names; SVARALIAS may rename them):
//   OUTCONST NDOF (int), DH (double[18*(NDOF+1)])   from LOCAL ROBOT, as robotsim
//   INVAR    torque mode:   T_REF                  joint torques (N m) -> CST target torque
//            position mode: Q_REF [Q^_REF]         rad, rad/s -> CSP target position, velocity offset
//   OUTVAR   Q_MEZ [Q^_MEZ]                        position / velocity actual, latched at the last SYNC
//
// Each cycle: read every drive's feedback (never blocking), check it (fresh
// TPDO2, heartbeat, state, fault), publish it, send the targets (RPDO1, RPDO2)
// and then the SYNC at which they take effect. One cycle of transport delay:
// the positions a cycle publishes were latched at the previous cycle's SYNC.
//
// Safety, as a control engineer expects it:
//   - init starts the drives (NMT) and fails, naming the node, if one does not answer;
//   - on walks every drive through the CiA 402 state machine to operation
//     enabled (resetting a fault) and fails, naming the node and its state or
//     fault code, when one does not get there in ENABLE_TIMEOUT; in position
//     mode it refuses to start with Q_REF more than ON_TOLERANCE away;
//   - a drive that faults, leaves operation enabled, stops sending feedback or
//     heartbeats is an error naming the node: the task goes to ERROR and every
//     drive gets a quick stop (brakes); a master that dies stops sending RPDOs
//     and the drives fault on their RPDO timeout;
//   - off switches the drives off (shutdown: brakes), kill returns them to
//     pre-operational — each confirmed by the drives, commands resent until
//     then (a frame can be lost), for at most ENABLE_TIMEOUT;
//   - with STABILITY hold, while the illegal-configuration flag is up (§3.10)
//     the drives hold the position they had when it rose, in their own CSP
//     loop; turned on inside a reconfiguration, the drives are enabled that
//     way, so the brakes open onto a hold, not onto a torque no controller
//     has computed yet. Turn the interface on in the same reconfig as its
//     controller;
//   - with VLIMIT and/or TRATE (optional, per joint), what it commands goes
//     through canrobot/command_limits.hpp: in torque mode the torque (the
//     robotics::JointLimiter of robotsim), in position mode the target's
//     change per cycle; `get LIMITS` answers how often each limit acted. And
//     init downloads them into every drive by SDO before NMT start (0x6080
//     max motor speed from VLIMIT, 0x6087 torque slope from TRATE): the
//     drives' own limits hold when this master is late or gone; a drive that
//     refuses or does not answer fails init, naming node, joint, object and
//     SDO abort code.
// The LOCAL keys are in README.md.
#include <chimera/iod.hpp>
#include <chimera/module.hpp>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "canrobot/bus_config.hpp"
#include "canrobot/cia402.hpp"
#include "canrobot/command_limits.hpp"
#include "canrobot/sdo.hpp"
#include "robotics/dynamics.hpp"
#include "robotics/ports.hpp"

namespace rb = chimera::robotics;
namespace iod = chimera::iod;
using namespace chimera::canrobot::cia402;

namespace {

// Ports of a node's device, in the order of the generated database.
constexpr int kRpdo1Ports = 0;     // controlword, mode, target torque (3 x 16 bits)
constexpr int kRpdo2Ports = 3;     // target position, velocity offset (2 x 32)
constexpr int kTpdo1Ports = 5;     // statusword, mode display, error code (3 x 16)
constexpr int kTpdo2Ports = 8;     // position, velocity (2 x 32)
constexpr int kHeartbeatPort = 10; // NMT state (8)
constexpr int kSdoRequestPorts = 11;   // SDO request, 8 bytes (8 x 8 bits)
constexpr int kSdoResponsePorts = 19;  // SDO response, 8 bytes

// on(): a step of the enabling a drive did not answer is sent again after this.
constexpr std::chrono::milliseconds kStepResend{100};

// Error numbers this module raises (task.error codes).
constexpr int kErrNoFeedback = 1;
constexpr int kErrHeartbeat = 2;
constexpr int kErrDriveFault = 3;
constexpr int kErrDriveState = 4;
constexpr int kErrBus = 5;

std::string hex(std::uint32_t v) {
    char b[16];
    std::snprintf(b, sizeof b, "0x%03X", v);
    return b;
}

// The IOD database of the bus: one device per node (so a second master for a
// node is refused by the IOD port reservation), plus the bus's single SYNC
// producer and NMT master.
std::string bus_database(const std::string& interface, const std::vector<int>& nodes) {
    std::string db;
    for (int n : nodes) {
        db += "DEVICE " + interface + ".node" + std::to_string(n) + " RCB socketcan\nPATH " + interface + "\n";
        db += "FRAME " + hex(cob_id(kRpdo1, n)) + " OUT 3 16\n";
        db += "FRAME " + hex(cob_id(kRpdo2, n)) + " OUT 2 32\n";
        db += "FRAME " + hex(cob_id(kTpdo1, n)) + " IN 3 16\n";
        db += "FRAME " + hex(cob_id(kTpdo2, n)) + " IN 2 32\n";
        db += "FRAME " + hex(cob_id(kHeartbeat, n)) + " IN 1 8\n";
        db += "FRAME " + hex(cob_id(chimera::canrobot::sdo::kRequest, n)) + " OUT 8 8\n";
        db += "FRAME " + hex(cob_id(chimera::canrobot::sdo::kResponse, n)) + " IN 8 8\nEND\n";
    }
    db += "DEVICE " + interface + ".sync RCB socketcan\nPATH " + interface + "\nFRAME 0x080 OUT 1 8\nEND\n";
    db += "DEVICE " + interface + ".nmt RCB socketcan\nPATH " + interface + "\nFRAME 0x000 OUT 2 8\nEND\nEOF\n";
    return db;
}

std::int64_t realtime_ns() noexcept {  // the clock of the kernel's receive stamps
    timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    return ts.tv_sec * 1'000'000'000LL + ts.tv_nsec;
}

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kCanRobotLocalKeys[] = {
    {"ROBOT", chimera::LocalType::text, -chimera::unbounded, chimera::unbounded, false, "puma560 | planar2 | urdf FILE ROOT-LINK TIP-LINK", "puma560"},
    {"MODE", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "torque | position", "torque"},
    {"INTERFACE", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "SocketCAN interface (vcan0, can0)", ""},
    {"NODES", chimera::LocalType::numbers, 1.0, 127.0, false, "CANopen node id per joint", ""},
    {"COUNTS_PER_REV", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "encoder counts per revolution per joint", "1048576"},
    {"RATED_TORQUE", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "drive rated torque per joint (N m)", ""},
    {"TLIMIT", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "torque limit per joint (N m)", ""},
    {"VLIMIT", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "joint speed limit per joint (rad/s); none: no limit", ""},
    {"TRATE", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "torque rate limit per joint (N m/s), torque mode; none: no limit", ""},
    {"HEARTBEAT_TIMEOUT", chimera::LocalType::number, 0.0, chimera::unbounded, false, "seconds without a drive heartbeat before failing", "0.5"},
    {"FEEDBACK_MISSES", chimera::LocalType::integer, 0.0, 1000000.0, false, "cycles without feedback before failing", "10"},
    {"ENABLE_TIMEOUT", chimera::LocalType::number, 0.0, chimera::unbounded, false, "seconds to enable the drives in on()", "1"},
    {"ON_TOLERANCE", chimera::LocalType::number, 0.0, chimera::unbounded, false, "largest Q_REF - Q_MEZ accepted by on() (rad)", "0.05"},
    {"STABILITY", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "hold | none while the configuration is illegal", "hold"},
    {"Q0", chimera::LocalType::numbers, -chimera::unbounded, chimera::unbounded, false, "drive simulator: initial joint positions", "0"},
    {"DRIVE_*", chimera::LocalType::numbers, -chimera::unbounded, chimera::unbounded, false, "drive simulator settings (DRIVE_KP, DRIVE_HEARTBEAT, ...)", ""},
};

class CanRobot : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kCanRobotLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        model_ = rb::robot_from_local(t);
        n_ = model_.ndof();
        try {
            bus_ = chimera::canrobot::BusConfig::from_local(t.local(), n_);
        } catch (const std::invalid_argument& e) {
            rb::module_error(t, e.what());
        }
        const std::string mode = rb::local_word(t, "MODE", "torque");
        if (mode != "torque" && mode != "position")
            rb::module_error(t, "LOCAL MODE '" + mode + "': expected torque or position");
        position_mode_ = mode == "position";
        try {
            limiter_.emplace(bus_, position_mode_);
        } catch (const std::invalid_argument& e) {
            rb::module_error(t, std::string("LOCAL ") + e.what());
        }
        if (limiter_->active() && !position_mode_) dyn_ = std::make_unique<rb::Dynamics>(model_);
        q_now_.setZero(static_cast<Eigen::Index>(n_));
        qd_now_.setZero(static_cast<Eigen::Index>(n_));
        gravity_.setZero(static_cast<Eigen::Index>(n_));
        q_cmd_.setZero(static_cast<Eigen::Index>(n_));
        qd_cmd_.setZero(static_cast<Eigen::Index>(n_));
        tau_cmd_.setZero(static_cast<Eigen::Index>(n_));
        hold_on_illegal_ = rb::local_word(t, "STABILITY", "hold") == "hold";
        heartbeat_timeout_ns_ = static_cast<std::int64_t>(rb::local_number(t, "HEARTBEAT_TIMEOUT", 0.5) * 1e9);
        feedback_misses_ = static_cast<int>(rb::local_number(t, "FEEDBACK_MISSES", 10));
        enable_timeout_ = rb::local_number(t, "ENABLE_TIMEOUT", 1.0);
        on_tolerance_ = rb::local_number(t, "ON_TOLERANCE", 0.05);
        if (heartbeat_timeout_ns_ <= 0 || feedback_misses_ < 1 || !(enable_timeout_ > 0) || !(on_tolerance_ > 0))
            rb::module_error(t, "LOCAL HEARTBEAT_TIMEOUT, FEEDBACK_MISSES, ENABLE_TIMEOUT and ON_TOLERANCE must be positive");

        if (rb::listed(t.rmod_file().out_consts, "NDOF"))
            *t.translate<std::int32_t>("NDOF") = static_cast<std::int32_t>(n_);
        if (rb::listed(t.rmod_file().out_consts, "DH")) {
            if (!model_.has_dh())
                rb::module_error(t, "robot " + model_.name() + " has no DH parameters; remove DH from OUTCONST");
            model_.pack_dh(std::span<double>(rb::vec_port(t, "DH", rb::dh_size(n_)), rb::dh_size(n_)));
        }
        if (position_mode_) {
            q_ref_ = rb::vec_port(t, "Q_REF", n_);
            if (rb::has_in_var(t, "Q^_REF")) qd_ref_ = rb::vec_port(t, "Q^_REF", n_);
        } else {
            t_ref_ = rb::vec_port(t, "T_REF", n_);
        }
        q_mez_ = rb::vec_port(t, "Q_MEZ", n_);
        if (rb::has_out_var(t, "Q^_MEZ")) qd_mez_ = rb::vec_port(t, "Q^_MEZ", n_);
        hold_q_.assign(n_, 0.0);

        open_bus(t);
        download_drive_limits(t);
        start_nodes(t);
        return chimera::Result::OK;
    }

    chimera::Result on(chimera::Task& t) override {
        // Every drive one CiA 402 step per round, a SYNC per round for fresh
        // feedback, until all are enabled. Turned on inside a reconfiguration
        // (the illegal-configuration flag is up) with STABILITY hold, the
        // drives are enabled holding where they are, in their own CSP loop:
        // the brakes never open onto a torque command no controller has made
        // yet (T_REF is 0 until the controller runs), and the cycle goes on
        // holding until the flag drops.
        holding_ = hold_on_illegal_ && t.illegal_configuration();
        const bool csp = position_mode_ || holding_;
        const auto deadline = Clock::now() + std::chrono::duration<double>(enable_timeout_);
        auto resend_at = Clock::now();
        for (;;) {
            read_feedback();
            bool all_enabled = true, all_answered = true;
            for (Node& d : nodes_) {
                const bool enabled = d.state == DriveState::operation_enabled && d.seen_tpdo2;
                all_enabled = all_enabled && enabled;
                all_answered = all_answered && (enabled || d.tpdo1_stamp != d.stamp_at_step);
            }
            if (all_enabled) break;
            if (Clock::now() > deadline) {
                std::string why;
                for (std::size_t j = 0; j < n_; ++j) {
                    const Node& d = nodes_[j];
                    if (d.state == DriveState::operation_enabled && d.seen_tpdo2) continue;
                    why += (why.empty() ? "" : "; ") + describe(j) + " is in '" + std::string(to_string(d.state)) + "'";
                    if (d.error) why += " with error " + hex(d.error) + " " + std::string(error_name(d.error));
                    if (!d.seen_tpdo2) why += ", no position (TPDO2) received";
                }
                return t.error(kErrDriveState, "cannot enable the drives within ENABLE_TIMEOUT " +
                                            std::to_string(enable_timeout_) + " s: " + why);
            }
            // The next step goes out once every drive has answered the last
            // (a newer TPDO1), or after kStepResend when one did not (a frame
            // lost): paced by the drives, never faster. A fixed 2 ms pace sent
            // ~6 500 frames a second, which a slow machine (the PREEMPT_RT
            // guest under load) could not take in: the drives answered 14 of
            // 1 384 steps in 5 s and were never enabled (issue #36).
            if (all_answered || Clock::now() >= resend_at) {
                for (std::size_t j = 0; j < n_; ++j) {
                    Node& d = nodes_[j];
                    d.controlword = controlword_toward_enabled(d.state, d.controlword);
                    d.stamp_at_step = d.tpdo1_stamp;
                    // CSP: the arm's own position as the target, enabling never moves
                    // it. CST: the torque the controller asks for now (0 when none
                    // is on yet), as robotsim applies it from its first cycle.
                    const double torque = csp ? 0.0 : clamp_torque(j, t_ref_[j]);
                    send_targets(j, d.controlword, csp ? kModeCsp : kModeCst, torque, d.q, 0);
                }
                send_sync();
                resend_at = Clock::now() + kStepResend;
            }
            std::this_thread::sleep_for(std::chrono::milliseconds(2));
        }
        publish();
        if (position_mode_) {
            for (std::size_t j = 0; j < n_; ++j) {
                if (std::fabs(q_ref_[j] - nodes_[j].q) > on_tolerance_) {
                    char m[200];
                    std::snprintf(m, sizeof m, "Q_REF of joint %zu is %.4f rad from the arm (%.4f vs %.4f), more than "
                                  "ON_TOLERANCE %.4f: refusing to jump",
                                  j + 1, std::fabs(q_ref_[j] - nodes_[j].q), q_ref_[j], nodes_[j].q, on_tolerance_);
                    return t.error(kErrDriveState, m);
                }
            }
        }
        for (std::size_t j = 0; j < n_; ++j) hold_q_[j] = nodes_[j].q;
        start_limits_after_on(csp);
        return chimera::Result::OK;
    }

    // get LIMITS: "speed_clamps N rate_clamps M" (joint-cycles each limit changed
    // the command), or "none" without VLIMIT and TRATE.
    chimera::Result get(chimera::Task& t) override {
        if (t.arg() != "LIMITS") return chimera::Result::OK;
        t.reply(limiter_->report());
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        if (const int failed = check_feedback()) {
            return t.error(failed, failure_);
        }
        publish();

        const bool hold = hold_on_illegal_ && t.illegal_configuration();
        if (hold && !holding_) {
            for (std::size_t j = 0; j < n_; ++j) hold_q_[j] = nodes_[j].q;
        }
        holding_ = hold;
        compute_commands(t.period());
        int unsent = 0;
        for (std::size_t j = 0; j < n_; ++j) {
            const bool csp = holding_ || position_mode_;
            const auto jj = static_cast<Eigen::Index>(j);
            unsent += !send_targets(j, kCwEnableOperation, csp ? kModeCsp : kModeCst, tau_cmd_[jj], q_cmd_[jj],
                                    qd_cmd_[jj]);
        }
        unsent += !send_sync();
        // A transmit queue that stays full is a bus that is down (no ACK, bus-off).
        unsent_cycles_ = unsent ? unsent_cycles_ + 1 : 0;
        if (unsent_cycles_ > feedback_misses_) {
            std::snprintf(failure_, sizeof failure_, "cannot send on %s for %d cycles (bus down, or no other node ACKs?)",
                          bus_.interface.c_str(), unsent_cycles_);
            return t.error(kErrBus, failure_);
        }
        return chimera::Result::OK;
    }

    chimera::Result off(chimera::Task& t) override {
        // Shutdown: ready to switch on, no torque, brakes — confirmed by every
        // drive, or the task errs (and error() tries a quick stop).
        if (!switch_all_confirmed(kCwShutdown)) {
            return t.error(kErrDriveState, failure_);
        }
        publish();
        return chimera::Result::OK;
    }

    chimera::Result kill(chimera::Task& t) override {
        if (nmt_) {
            if (!switch_all_confirmed(kCwShutdown)) t.warning(failure_);
            if (!all_preoperational()) t.warning(failure_);
        }
        nodes_.clear();
        sync_.reset();
        nmt_.reset();
        return chimera::Result::OK;
    }

    chimera::Result error(chimera::Task& t, const chimera::err::Error&) override {
        // Every drive stops and brakes; the operator clears. Unconfirmed, the
        // drives' RPDO timeout is what is left.
        if (!switch_all_confirmed(kCwQuickStop)) t.warning(failure_);
        return chimera::Result::ERROR;
    }

private:
    using Clock = std::chrono::steady_clock;

    struct Node {
        int node = 0;
        std::unique_ptr<iod::Device> rpdo1;     // controlword, mode, target torque
        std::unique_ptr<iod::Device> rpdo2;     // target position, velocity offset (CSP only)
        std::unique_ptr<iod::Device> feedback;  // TPDO1, TPDO2, heartbeat
        std::array<std::int32_t, 6> in{};       // statusword, mode, error, position, velocity, NMT state
        DriveState state = DriveState::not_ready_to_switch_on;
        std::uint16_t error = 0;
        std::uint16_t controlword = 0;
        NmtState nmt = NmtState::boot_up;
        double q = 0, qd = 0;
        long tpdo1_stamp = 0, tpdo2_stamp = 0, heartbeat_stamp = 0;
        long stamp_at_step = 0;  // tpdo1_stamp when on() sent its last step: a newer one answers it
        bool seen_tpdo2 = false;
        int missed = 0;  // cycles in a row without a new TPDO2
    };

    std::string describe(std::size_t joint) const {
        return "node " + std::to_string(nodes_[joint].node) + " (joint " + std::to_string(joint + 1) + ") on " +
               bus_.interface;
    }

    void open_bus(chimera::Task& t) {
        const std::string& ifc = bus_.interface;
        try {
            const auto db = iod::Database::from_string(bus_database(ifc, bus_.nodes),
                                                       std::string(t.rmod()) + ".rmod (CAN devices of " + ifc + ")");
            constexpr unsigned nowait = iod::WAITNONE;
            sync_ = iod::open(db, ifc + ".sync", 0, 0, iod::WRITE | iod::BYTE | nowait);
            nmt_ = iod::open(db, ifc + ".nmt", 0, 1, iod::WRITE | iod::BYTE | nowait);
            for (int id : bus_.nodes) {
                Node d;
                d.node = id;
                const std::string dev = ifc + ".node" + std::to_string(id);
                d.rpdo1 = iod::open(db, dev, kRpdo1Ports, kRpdo2Ports - 1, iod::WRITE | iod::LONG | iod::SIGNED | nowait);
                d.rpdo2 = iod::open(db, dev, kRpdo2Ports, kTpdo1Ports - 1, iod::WRITE | iod::LONG | iod::SIGNED | nowait);
                d.feedback = iod::open(db, dev, kTpdo1Ports, kHeartbeatPort, iod::READ | iod::LONG | iod::SIGNED | nowait);
                nodes_.push_back(std::move(d));
            }
        } catch (const iod::Error& e) {
            nodes_.clear();
            sync_.reset();
            nmt_.reset();
            const std::string m = e.what();
            rb::module_error(t, m + (m.find("already open") != std::string::npos
                                         ? " (another canrobot task or program is the master of this bus or node)"
                                         : ""));
        }
    }

    // With VLIMIT and/or TRATE, every drive gets its own limits by SDO (CiA
    // 301 expedited download; canrobot/sdo.hpp), before NMT start: 0x6080 max
    // motor speed (VLIMIT in counts/s) and 0x6087 torque slope (TRATE in
    // thousandths of the rated torque per second). They act inside the drive,
    // so they hold when this master is late or gone, which the limits of the
    // cycle cannot. A drive that refuses (SDO abort) or does not answer within
    // ENABLE_TIMEOUT fails init, naming node, joint, object and abort code.
    void download_drive_limits(chimera::Task& t) {
        namespace sdo = chimera::canrobot::sdo;
        auto downloads = chimera::canrobot::drive_limit_downloads(bus_);
        if (downloads.empty()) return;
        std::vector<std::unique_ptr<iod::Device>> out_dev, in_dev;
        try {
            const std::string& ifc = bus_.interface;
            const auto db = iod::Database::from_string(bus_database(ifc, bus_.nodes),
                                                       std::string(t.rmod()) + ".rmod (CAN devices of " + ifc + ")");
            for (int id : bus_.nodes) {
                const std::string dev = ifc + ".node" + std::to_string(id);
                out_dev.push_back(iod::open(db, dev, kSdoRequestPorts, kSdoResponsePorts - 1,
                                            iod::WRITE | iod::BYTE | iod::WAITNONE));
                in_dev.push_back(iod::open(db, dev, kSdoResponsePorts, kSdoResponsePorts + 7,
                                           iod::READ | iod::BYTE | iod::WAITNONE));
            }
        } catch (const iod::Error& e) {
            (void)kill(t);
            rb::module_error(t, std::string("opening the drives' SDO channels: ") + e.what());
        }
        sdo::DownloadSequence seq(std::move(downloads), bus_.interface);
        std::vector<Frame> out;
        auto send_all = [&] {
            for (const Frame& f : out) {
                const auto j = static_cast<std::size_t>(std::find(bus_.nodes.begin(), bus_.nodes.end(),
                                                                  static_cast<int>(f.id - sdo::kRequest)) -
                                                        bus_.nodes.begin());
                if (j < out_dev.size()) (void)out_dev[j]->write(f.data, 8);  // lost: resent below
            }
            out.clear();
        };
        seq.start(out);
        send_all();
        const auto deadline = Clock::now() + std::chrono::duration<double>(enable_timeout_);
        auto resend_at = Clock::now() + std::chrono::milliseconds(100);
        while (!seq.done() && !seq.failed() && Clock::now() <= deadline) {
            std::this_thread::sleep_for(std::chrono::milliseconds(2));
            for (std::size_t j = 0; j < in_dev.size(); ++j) {
                Frame f{.id = cob_id(sdo::kResponse, bus_.nodes[j]), .len = 8, .data = {}};
                if (in_dev[j]->read(f.data, 8) > 0) seq.receive(f, out);
            }
            if (Clock::now() >= resend_at) {  // a request or its answer lost
                seq.resend(out);
                resend_at = Clock::now() + std::chrono::milliseconds(100);
            }
            send_all();
        }
        if (seq.done()) return;
        const std::string why = seq.failed() ? seq.failure()
                                             : "no answer within ENABLE_TIMEOUT " + std::to_string(enable_timeout_) +
                                                   " s to the SDO download of the drives' own limits (VLIMIT, TRATE): " +
                                                   seq.unconfirmed();
        out_dev.clear();
        in_dev.clear();
        (void)kill(t);
        rb::module_error(t, "cannot set the drives' own speed and torque-slope limits: " + why);
    }

    void start_nodes(chimera::Task& t) {
        // A drive entering operational answers with its TPDO1 at once; its
        // heartbeat (the liveness the cycle checks) comes within its period,
        // and must say operational: one sent just before the start took
        // effect (pre-operational) may arrive after the TPDO1.
        auto pending = [](const Node& d) { return !d.tpdo1_stamp || d.nmt != NmtState::operational; };
        if (resend_until(pending, [&](std::size_t j) { send_nmt(NmtCommand::start, nodes_[j].node); },
                         std::chrono::milliseconds(100)) < 0)
            return;
        std::string missing;
        for (std::size_t j = 0; j < n_; ++j)
            if (pending(nodes_[j]))
                missing += (missing.empty() ? "" : ", ") + describe(j) +
                           (nodes_[j].tpdo1_stamp ? " (no operational heartbeat)" : " (no TPDO1, no answer to NMT start)");
        (void)kill(t);  // always OK; confirms nothing with the nodes that never answered (they are warned of)
        rb::module_error(t, "no answer within ENABLE_TIMEOUT " + std::to_string(enable_timeout_) + " s from " + missing +
                                ": is the drive powered, on the bus, with that node id?");
    }

    // The command/confirm loop of init, off, kill and error: a frame can be
    // lost (a receiver that did not run for a while), so `send(joint)` goes
    // to every drive `pending` still holds for, again every `every`, with the
    // feedback read in between, until none is pending (-1) or ENABLE_TIMEOUT
    // passes (the first joint still pending).
    template <typename Pending, typename Send>
    int resend_until(Pending pending, Send send, std::chrono::milliseconds every) {
        const auto deadline = Clock::now() + std::chrono::duration<double>(enable_timeout_);
        auto next_send = Clock::now();
        for (;;) {
            read_feedback();
            int first = -1;
            for (std::size_t j = 0; j < nodes_.size() && first < 0; ++j)
                if (pending(nodes_[j])) first = static_cast<int>(j);
            if (first < 0 || Clock::now() > deadline) return first;
            if (Clock::now() >= next_send) {
                for (std::size_t j = 0; j < nodes_.size(); ++j)
                    if (pending(nodes_[j])) send(j);
                next_send = Clock::now() + every;
            }
            std::this_thread::sleep_for(std::chrono::milliseconds(2));
        }
    }

    // Reads every drive's frames (non-blocking); decodes what is new.
    void read_feedback() noexcept {
        for (std::size_t j = 0; j < n_; ++j) {
            Node& d = nodes_[j];
            read_status_ = d.feedback->read(d.in.data(), d.in.size());
            if (read_status_ < 0) return;
            const long s1 = d.feedback->status(iod::Status::CAN_TIMESTAMP, kTpdo1Ports);
            const long s2 = d.feedback->status(iod::Status::CAN_TIMESTAMP, kTpdo2Ports);
            const long hb = d.feedback->status(iod::Status::CAN_TIMESTAMP, kHeartbeatPort);
            if (s1 != d.tpdo1_stamp) {
                d.tpdo1_stamp = s1;
                d.state = decode_statusword(static_cast<std::uint16_t>(d.in[0]));
                d.error = static_cast<std::uint16_t>(d.in[2]);
            }
            d.missed = s2 != d.tpdo2_stamp ? 0 : d.missed + 1;
            if (s2 != d.tpdo2_stamp) {
                d.tpdo2_stamp = s2;
                d.seen_tpdo2 = true;
                const auto jj = static_cast<Eigen::Index>(j);
                d.q = from_counts(d.in[3], bus_.counts_per_rev[jj]);
                d.qd = from_counts(d.in[4], bus_.counts_per_rev[jj]);
            }
            if (hb != d.heartbeat_stamp) {
                d.heartbeat_stamp = hb;
                d.nmt = static_cast<NmtState>(d.in[5] & 0xFF);
            }
        }
    }

    // 0 when every drive is well, else the error number (message in failure_).
    int check_feedback() noexcept {
        read_feedback();
        if (read_status_ < 0) {
            std::snprintf(failure_, sizeof failure_, "reading %s: %s", bus_.interface.c_str(),
                          std::strerror(static_cast<int>(-read_status_)));
            return kErrBus;
        }
        const std::int64_t now = realtime_ns();
        for (std::size_t j = 0; j < n_; ++j) {
            const Node& d = nodes_[j];
            const int node = d.node;
            const int joint = static_cast<int>(j) + 1;
            if (d.state == DriveState::fault || d.state == DriveState::fault_reaction_active) {
                const std::string_view name = error_name(d.error);
                std::snprintf(failure_, sizeof failure_, "node %d (joint %d) on %s: drive fault, error code 0x%04X %.*s",
                              node, joint, bus_.interface.c_str(), d.error, static_cast<int>(name.size()), name.data());
                return kErrDriveFault;
            }
            if (d.state != DriveState::operation_enabled) {
                const std::string_view state = to_string(d.state);
                std::snprintf(failure_, sizeof failure_, "node %d (joint %d) on %s left operation enabled: now '%.*s'",
                              node, joint, bus_.interface.c_str(), static_cast<int>(state.size()), state.data());
                return kErrDriveState;
            }
            if (d.missed > feedback_misses_) {
                std::snprintf(failure_, sizeof failure_,
                              "node %d (joint %d) on %s: no position (TPDO2) for %d cycles (FEEDBACK_MISSES %d)",
                              node, joint, bus_.interface.c_str(), d.missed, feedback_misses_);
                return kErrNoFeedback;
            }
            if (now - d.heartbeat_stamp > heartbeat_timeout_ns_) {
                std::snprintf(failure_, sizeof failure_, "node %d (joint %d) on %s: no heartbeat for %.3f s (HEARTBEAT_TIMEOUT %.3f)",
                              node, joint, bus_.interface.c_str(), static_cast<double>(now - d.heartbeat_stamp) * 1e-9,
                              static_cast<double>(heartbeat_timeout_ns_) * 1e-9);
                return kErrHeartbeat;
            }
            if (d.nmt != NmtState::operational) {
                const std::string_view nmt = to_string(d.nmt);
                std::snprintf(failure_, sizeof failure_, "node %d (joint %d) on %s reports NMT state %.*s",
                              node, joint, bus_.interface.c_str(), static_cast<int>(nmt.size()), nmt.data());
                return kErrHeartbeat;
            }
        }
        return 0;
    }

    void publish() noexcept {
        for (std::size_t j = 0; j < n_; ++j) {
            q_mez_[j] = nodes_[j].q;
            if (qd_mez_) qd_mez_[j] = nodes_[j].qd;
        }
    }

    // RPDO1, and RPDO2 in CSP (after RPDO1: a mode change resets the drive's
    // CSP target to where the joint is). No RPDO2 before the joint's position
    // is known: the drive keeps holding where it is. False when not sent.
    bool send_targets(std::size_t joint, std::uint16_t controlword, std::int16_t mode, double torque, double q,
                      double qd) noexcept {
        const auto j = static_cast<Eigen::Index>(joint);
        const std::array<std::int32_t, 3> rpdo1{controlword, mode, torque_to_permille(torque, bus_.rated_torque[j])};
        if (nodes_[joint].rpdo1->write(rpdo1.data(), rpdo1.size()) < 0) return false;
        if (mode != kModeCsp || !nodes_[joint].seen_tpdo2) return true;
        const double cpr = bus_.counts_per_rev[j];
        const std::array<std::int32_t, 2> rpdo2{to_counts(q, cpr), to_counts(qd, cpr)};
        return nodes_[joint].rpdo2->write(rpdo2.data(), rpdo2.size()) >= 0;
    }

    // This cycle's commands in q_cmd_, qd_cmd_ (CSP) and tau_cmd_ (CST), the
    // limits applied. While holding, the drives hold in their own CSP loop and
    // the limits start again from the hold: in torque mode from the gravity
    // torque (what that loop applies to carry the arm), in position mode from
    // the held position.
    void compute_commands(double dt) noexcept {
        const auto n = static_cast<Eigen::Index>(n_);
        for (Eigen::Index j = 0; j < n; ++j) {
            const auto js = static_cast<std::size_t>(j);
            const bool csp = holding_ || position_mode_;
            tau_cmd_[j] = csp ? 0.0 : clamp_torque(js, t_ref_[js]);
            q_cmd_[j] = holding_ ? hold_q_[js] : position_mode_ ? q_ref_[js] : 0.0;
            qd_cmd_[j] = holding_ || !qd_ref_ ? 0.0 : qd_ref_[js];
            q_now_[j] = nodes_[js].q;
            qd_now_[j] = nodes_[js].qd;
        }
        if (!limiter_->active()) return;
        if (position_mode_) {
            if (holding_) limiter_->reset(q_cmd_);
            else limiter_->limit_target(q_cmd_, qd_cmd_, dt);
            return;
        }
        dyn_->gravity(q_now_, gravity_);
        if (holding_) limiter_->reset(gravity_);
        else limiter_->limit_torque(tau_cmd_, qd_now_, gravity_, dt);
    }

    // After on(): the limits start from what the drives do now — the target
    // they were enabled on (CSP: where the arm is), or the torque the
    // enabling sent (CST; T_REF, 0 before any controller ran). Holding, the
    // cycle resets them from the hold.
    void start_limits_after_on(bool csp) noexcept {
        if (!limiter_->active()) return;
        for (std::size_t j = 0; j < n_; ++j) {
            const auto jj = static_cast<Eigen::Index>(j);
            q_cmd_[jj] = nodes_[j].q;
            tau_cmd_[jj] = csp ? 0.0 : clamp_torque(j, t_ref_[j]);
        }
        limiter_->reset(position_mode_ ? q_cmd_ : tau_cmd_);
    }

    double clamp_torque(std::size_t joint, double torque) const noexcept {
        const double limit = bus_.torque_limit[static_cast<Eigen::Index>(joint)];
        return std::clamp(torque, -limit, limit);
    }

    bool send_sync() noexcept {
        sync_counter_ = static_cast<std::uint8_t>(sync_counter_ % kSyncCounterOverflow + 1);
        return sync_->write(&sync_counter_, 1) >= 0;
    }

    void send_nmt(NmtCommand c, int node) noexcept {
        const std::uint8_t frame[2] = {static_cast<std::uint8_t>(c), static_cast<std::uint8_t>(node)};
        nmt_->write(frame, 2);
    }

    // `controlword` (shutdown or quick stop: it acts on receipt, no SYNC
    // needed) to every drive that answered at init and is still enabled,
    // until none is — or ENABLE_TIMEOUT: false, with the first drive that did
    // not follow named in failure_.
    bool switch_all_confirmed(std::uint16_t controlword) {
        const int first = resend_until(
            [&](const Node& d) { return d.tpdo1_stamp && !silent(d) && d.state == DriveState::operation_enabled; },
            [&](std::size_t j) {
                nodes_[j].controlword = controlword;
                send_targets(j, controlword, position_mode_ ? kModeCsp : kModeCst, 0, nodes_[j].q, 0);
            },
            std::chrono::milliseconds(20));
        if (first < 0) return none_silent();
        std::snprintf(failure_, sizeof failure_,
                      "node %d (joint %d) on %s still enabled after controlword 0x%04X for ENABLE_TIMEOUT %.3f s",
                      nodes_[static_cast<std::size_t>(first)].node, first + 1, bus_.interface.c_str(), controlword,
                      enable_timeout_);
        return false;
    }

    // A drive whose heartbeat stopped (HEARTBEAT_TIMEOUT) cannot confirm
    // anything: the confirming loops do not wait for it.
    bool silent(const Node& d) const noexcept {
        return realtime_ns() - d.heartbeat_stamp > heartbeat_timeout_ns_;
    }
    // True when every drive that answered at init still has a heartbeat; else
    // false with failure_ naming the first silent one.
    bool none_silent() noexcept {
        for (std::size_t j = 0; j < nodes_.size(); ++j) {
            if (!nodes_[j].tpdo1_stamp || !silent(nodes_[j])) continue;
            std::snprintf(failure_, sizeof failure_, "node %d (joint %zu) on %s does not answer (no heartbeat for %.3f s)",
                          nodes_[j].node, j + 1, bus_.interface.c_str(),
                          static_cast<double>(realtime_ns() - nodes_[j].heartbeat_stamp) * 1e-9);
            return false;
        }
        return true;
    }

    // NMT pre-operational to every drive that answered at init, until each
    // one's heartbeat says so (or ENABLE_TIMEOUT: false, failure_ names the
    // first that did not).
    bool all_preoperational() {
        const std::int64_t since = realtime_ns();
        const int first = resend_until(
            [&](const Node& d) {
                return d.tpdo1_stamp && !silent(d) && (d.heartbeat_stamp < since || d.nmt != NmtState::preoperational);
            },
            [&](std::size_t j) { send_nmt(NmtCommand::enter_preoperational, nodes_[j].node); },
            std::chrono::milliseconds(50));
        if (first < 0) return none_silent();
        std::snprintf(failure_, sizeof failure_, "node %d (joint %d) on %s did not confirm NMT pre-operational within %.3f s",
                      nodes_[static_cast<std::size_t>(first)].node, first + 1, bus_.interface.c_str(), enable_timeout_);
        return false;
    }

    rb::RobotModel model_;
    std::size_t n_ = 0;
    chimera::canrobot::BusConfig bus_;
    bool position_mode_ = false;
    bool hold_on_illegal_ = true;
    bool holding_ = false;
    std::int64_t heartbeat_timeout_ns_ = 0;
    int feedback_misses_ = 10;
    double enable_timeout_ = 1.0;
    double on_tolerance_ = 0.05;
    double* t_ref_ = nullptr;
    double* q_ref_ = nullptr;
    double* qd_ref_ = nullptr;
    double* q_mez_ = nullptr;
    double* qd_mez_ = nullptr;
    std::vector<double> hold_q_;
    std::optional<chimera::canrobot::CommandLimiter> limiter_;
    std::unique_ptr<rb::Dynamics> dyn_;  // torque mode with limits: the gravity torque they are centred on
    Eigen::VectorXd q_now_, qd_now_, gravity_;  // the arm as the last feedback says
    Eigen::VectorXd q_cmd_, qd_cmd_, tau_cmd_;  // this cycle's commands, limited
    std::vector<Node> nodes_;
    std::unique_ptr<iod::Device> sync_, nmt_;
    std::uint8_t sync_counter_ = 0;
    long read_status_ = 0;
    int unsent_cycles_ = 0;
    char failure_[256] = {};
};

}  // namespace

CHIMERA_MODULE(canrobot, CanRobot)
