// canrobot/drive_sim.hpp — simulated CANopen joint drives moving a simulated
// arm: the other end of the canrobot module's bus (thesis §7.3, transparent
// simulation: the same control subsystem runs against these drives over a real
// CAN socket, or against robotsim in-process, by swapping one module).
//
// DriveSim is the drives' logic with no I/O and no clock of its own: frames and
// the time come in, frames go out. Everything the protocol promises (NMT,
// heartbeats, the CiA 402 state machine, SYNC-latched feedback, targets taking
// effect at SYNC, the RPDO timeout) is therefore tested exactly on any machine
// (tests/sai/canrobot). run_drive_bus() puts it on a SocketCAN interface;
// the `candrive` program (candrive.cpp) is that plus options.
//
// Physics: one ArmSimulator for the whole arm (the joints are coupled),
// integrated lazily up to the time of each event in steps of at most
// `max_step`. A joint whose drive is not producing torque (any state but
// operation enabled) is held by its brake: its position is frozen and its
// velocity zero (exact when all joints are braked or all free; with some
// braked, the others' accelerations ignore the braked joints' reaction).
//
// The drives' own limits, set by SDO download (canrobot/sdo.hpp; unset after
// power-on and reset node: no limit), act inside every integration step, so
// they hold whatever the master does (late, silent, wrong):
//   0x6087 torque slope (thousandths of the rated torque per second, as the
//     target torque): in CST the torque demand moves toward the target torque
//     at most slope x step per step (from the torque applied when CST began);
//   0x6080 max motor speed (counts/s, the unit of 0x606C velocity actual): in
//     CST and CSP the drive's inner loop, modelled as faster than a step,
//     changes the torque of a joint that would end the step faster than the
//     limit to the torque that ends it at the limit (solved exactly for the
//     joints concerned together, the arm's coupling included), within the
//     torque limit: the speed never exceeds it at the end of any step unless
//     the torque limit cannot hold the joint (gravity beyond it). This
//     correction may change the torque faster than the slope: speed wins;
//   0x6072 max torque (thousandths of the rated torque): lowers the torque
//     limit below the .rmod's TLIMIT.
#pragma once

#include <chimera/sbs_files.hpp>

#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "canrobot/bus_config.hpp"
#include "canrobot/cia402.hpp"
#include "robotics/dynamics.hpp"
#include "robotics/model.hpp"
#include "robotics/pid.hpp"  // PidGains

namespace chimera::canrobot {

/// The drives' parameters. from_rmod() reads them from a canrobot .rmod's
/// LOCAL section (keys in modules/canrobot/README.md), so the module and the
/// simulated drives agree on nodes, units and limits by construction.
struct DriveConfig {
    robotics::RobotModel model;
    BusConfig bus;                         ///< nodes, units, torque limits
    Eigen::VectorXd q0;                    ///< rad, where the arm starts (Q0)
    /// The drive's own position loop in CSP mode (DRIVE_KP, DRIVE_KI,
    /// DRIVE_KD, DRIVE_ILIMIT): torque = KP e + KI integral(e) + KD (v_offset - qd),
    /// limited to the bus's torque limit.
    robotics::PidGains csp;
    std::int64_t heartbeat_ns = 100'000'000;    ///< producer heartbeat time (0x1017)
    std::int64_t rpdo_timeout_ns = 100'000'000; ///< 0: no RPDO deadline monitoring
    std::int64_t tpdo1_event_ns = 100'000'000;  ///< TPDO1 event timer
    double max_step = 0.00025;             ///< s, physics integration step

    /// Throws std::invalid_argument naming the .rmod (and line) on a bad value.
    static DriveConfig from_rmod(const RmodFile& rmod);
};

class DriveSim {
public:
    using Frame = cia402::Frame;
    using Out = std::vector<Frame>;

    explicit DriveSim(DriveConfig config);
    DriveSim(const DriveSim&) = delete;
    DriveSim& operator=(const DriveSim&) = delete;

    /// Power-on at `now` (ns, any monotonic clock): every drive sends its
    /// boot-up heartbeat and waits, pre-operational, switch-on-disabled.
    void power_on(std::int64_t now, Out& out);
    /// A frame seen on the bus at `now` (frames for other nodes are ignored).
    void receive(const Frame& frame, std::int64_t now, Out& out);
    /// Runs the timers due at `now`: heartbeats, TPDO1 event timers, RPDO timeouts.
    void tick(std::int64_t now, Out& out);
    /// When tick() has work next.
    std::int64_t next_timer() const noexcept;

    // --- what the drives are doing (tests, candrive's status line) ------------
    const DriveConfig& config() const noexcept { return cfg_; }
    std::size_t ndof() const noexcept { return drives_.size(); }
    cia402::DriveState state(std::size_t joint) const noexcept { return drives_[joint].state; }
    cia402::NmtState nmt(std::size_t joint) const noexcept { return drives_[joint].nmt; }
    std::uint16_t error_code(std::size_t joint) const noexcept { return drives_[joint].error; }
    std::int16_t mode(std::size_t joint) const noexcept { return drives_[joint].mode; }
    /// Torque the motor produces now (N m; 0 while braked).
    double torque(std::size_t joint) const noexcept { return tau_[static_cast<Eigen::Index>(joint)]; }
    const Eigen::VectorXd& q() const noexcept { return sim_.q(); }
    const Eigen::VectorXd& qd() const noexcept { return sim_.qd(); }
    std::uint64_t syncs() const noexcept { return syncs_; }
    /// The drive's max motor speed (0x6080) in rad/s; infinity while unset.
    double max_speed(std::size_t joint) const noexcept;
    /// The drive's torque slope (0x6087) in N m/s; infinity while unset.
    double torque_slope(std::size_t joint) const noexcept;
    /// The drive's torque limit: TLIMIT, or 0x6072 when lower (N m).
    double torque_limit(std::size_t joint) const noexcept;
    /// Steps in which the max motor speed changed a joint's torque (any joint).
    std::uint64_t speed_limited_steps() const noexcept { return speed_limited_; }
    /// Frames received for these drives that were ignored (not operational, short).
    std::uint64_t ignored_frames() const noexcept { return ignored_; }

private:
    struct Drive {
        int node = 0;
        cia402::NmtState nmt = cia402::NmtState::boot_up;
        cia402::DriveState state = cia402::DriveState::not_ready_to_switch_on;
        std::uint16_t controlword = 0;
        std::uint16_t error = 0;
        std::int16_t mode = cia402::kModeNone;          // mode display
        std::int16_t pending_torque = 0;                 // received, applied at SYNC
        std::int32_t pending_position = 0, pending_velocity = 0;
        bool pending_position_valid = false;
        std::int16_t torque_target = 0;                  // in effect
        double position_target = 0, velocity_offset = 0; // rad, rad/s, in effect (CSP)
        std::int64_t last_rpdo1 = 0;
        std::int64_t next_heartbeat = 0;
        std::int64_t next_tpdo1 = 0;
        std::uint16_t sent_statusword = 0xFFFF;          // last TPDO1 contents, for "on change"
        std::int16_t sent_mode = -1;
        std::uint16_t sent_error = 0xFFFF;
        // Set by SDO download (0: unset, no limit); reset node clears them.
        std::uint32_t max_speed = 0;     // 0x6080, counts/s
        std::uint32_t torque_slope = 0;  // 0x6087, thousandths of the rated torque per second
        std::uint16_t max_torque = 0;    // 0x6072, thousandths of the rated torque
    };

    int joint_of(int node) const noexcept;
    /// Integrates the arm up to `now`; false when the simulation diverged.
    bool advance(std::int64_t now);
    void advance_or_fault(std::int64_t now, Out& out);
    void update_brake(std::size_t joint);
    void set_state(Drive& d, std::size_t joint, cia402::DriveState s, std::int64_t now, Out& out);
    void fault(Drive& d, std::size_t joint, std::uint16_t code, std::int64_t now, Out& out);
    void nmt_command(Drive& d, std::size_t joint, cia402::NmtCommand c, std::int64_t now, Out& out);
    void send_tpdo1(Drive& d, std::int64_t now, Out& out, bool only_if_changed);
    void send_tpdo2(std::size_t joint, Out& out);
    void sdo_request(Drive& d, const Frame& f, Out& out);
    /// One integration step of `h` with the drives' torques and limits.
    bool step_once(double h);
    bool find_over() noexcept;
    bool correct_over(double h);
    static bool solve_in_place(Eigen::Ref<Eigen::MatrixXd> a, Eigen::Ref<Eigen::VectorXd> b) noexcept;
    bool producing_torque(const Drive& d) const noexcept {
        return d.state == cia402::DriveState::operation_enabled &&
               (d.mode == cia402::kModeCst || d.mode == cia402::kModeCsp);
    }

    DriveConfig cfg_;
    std::vector<Drive> drives_;
    robotics::ArmSimulator sim_;
    Eigen::VectorXd tau_, integral_, last_good_q_;
    Eigen::VectorXd demand_;          // CST torque demand after the torque slope (N m)
    std::vector<char> in_cst_;        // the joint produced CST torque in the last step
    // The speed limit's re-steps: the joints over it, their response to a
    // unit torque, the change wanted (sized at construction).
    Eigen::VectorXd q_before_, qd_before_, qd_base_, tau_try_;
    std::vector<Eigen::Index> over_;
    Eigen::MatrixXd response_;
    Eigen::VectorXd want_;
    std::uint64_t speed_limited_ = 0;
    std::int64_t now_ = 0;       // time the physics has reached
    bool powered_ = false;
    std::uint64_t syncs_ = 0;
    std::uint64_t ignored_ = 0;
};

/// Runs `sim` on the SocketCAN interface `interface` until `stop` is set:
/// powers it on, then feeds it every frame, at the time the kernel received
/// it, and the timers. `each_second` (if
/// set) is called about once a second with the simulation, for a status line.
/// Throws std::runtime_error when the interface cannot be opened (naming it,
/// and saying when the kernel has no AF_CAN).
void run_drive_bus(DriveSim& sim, const std::string& interface, const std::atomic<bool>& stop,
                   const std::function<void(const DriveSim&)>& each_second = {});

}  // namespace chimera::canrobot
