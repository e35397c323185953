// canrobot/command_limits.hpp — canrobot's optional per-joint VLIMIT and
// TRATE (issue #29.6: a lost link must never move the arm fast), applied to
// what the module commands each cycle, by the robotics limiters robotsim uses:
//
//   torque mode (CST): the target torque goes through robotics::JointLimiter
//     (TLIMIT, then TRATE, then the VLIMIT torque-speed envelope around the
//     gravity torque), exactly as robotsim limits the torque it simulates;
//   position mode (CSP): the drive's own loop makes the torque, which canrobot
//     cannot shape, so TRATE is refused; VLIMIT bounds the change of the target
//     position to VLIMIT * dt per cycle (robotics::SlewLimiter) and the
//     velocity offset to +-VLIMIT: a target that jumps (a reference that
//     arrives late, all at once) is followed no faster than VLIMIT.
//
// Each joint-cycle a limit changed the command is counted (`get LIMITS`).
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "canrobot/bus_config.hpp"
#include "canrobot/sdo.hpp"
#include "robotics/limits.hpp"
#include "robotics/stale.hpp"

namespace chimera::canrobot {

class CommandLimiter {
public:
    /// From BusConfig's tlimit, vlimit, trate (infinite: none). active() is
    /// false when both are infinite everywhere. std::invalid_argument naming
    /// the key when a value is out of range, or TRATE is given in position mode.
    CommandLimiter(const BusConfig& bus, bool position_mode);

    bool active() const noexcept { return torque_.has_value() || target_.has_value(); }

    /// Where the limits start from: the torque the drive applies now (torque
    /// mode), or the target position it holds (position mode).
    void reset(const Eigen::Ref<const Eigen::VectorXd>& now) noexcept;

    /// Torque mode: `tau` in, asked for; out, to send. `qd` the joints'
    /// speeds, `gravity` the torque that holds them.
    void limit_torque(Eigen::Ref<Eigen::VectorXd> tau, const Eigen::Ref<const Eigen::VectorXd>& qd,
                      const Eigen::Ref<const Eigen::VectorXd>& gravity, double dt) noexcept;

    /// Position mode: `q` the target position and `qd` the velocity offset,
    /// in asked for, out to send.
    void limit_target(Eigen::Ref<Eigen::VectorXd> q, Eigen::Ref<Eigen::VectorXd> qd, double dt) noexcept;

    std::uint64_t speed_clamps() const noexcept;
    std::uint64_t rate_clamps() const noexcept { return torque_ ? torque_->rate_clamps() : 0; }
    /// The answer to `get LIMITS`: "speed_clamps N rate_clamps M", or "none".
    std::string report() const;

private:
    std::optional<robotics::JointLimiter> torque_;
    std::optional<robotics::SlewLimiter> target_;
    Eigen::VectorXd vlimit_;
    std::uint64_t target_clamps_ = 0;
};

/// The drives' own limits for the declared VLIMIT and TRATE, as canrobot
/// downloads them at init (canrobot/sdo.hpp), joint by joint: 0x6080 max
/// motor speed = VLIMIT in counts/s (the unit of 0x606C velocity actual),
/// rounded down so the drive's limit is never above VLIMIT; 0x6087 torque
/// slope = TRATE in thousandths of RATED_TORQUE per second, rounded down.
/// Both at least 1 and at most 2^31 - 1. Nothing for a joint without them.
std::vector<sdo::Download> drive_limit_downloads(const BusConfig& bus);
std::uint32_t max_motor_speed_counts(double vlimit, double counts_per_rev) noexcept;
std::uint32_t torque_slope_permille(double trate, double rated_torque) noexcept;

}  // namespace chimera::canrobot
