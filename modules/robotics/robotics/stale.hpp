// robotics/stale.hpp — what a controller does while its measurements are
// stale, and how it restarts when fresh ones return (issue #29.6).
//
// The DDS bridge marks each port it receives in a STAMP out-var of 3 doubles,
// [counter, age (s), 1 new | 0 repeat | -1 stale] (modules/ddsbridge). A
// consumer that reads the stamp of its measurements can, with LOCAL STALE hold:
//   - while they are stale: keep its last good output and freeze its
//     integrators (a PID fed the same old measurement winds up; a trajectory
//     that runs on leaves the arm behind);
//   - on the first fresh cycle: restart bumplessly (the PID's integral reset
//     and its output slewed from the held one; the trajectory re-anchored at
//     the measured position, trajgen.cpp).
// The same key holds, and restarts the same way, while the subsystem's
// configuration is illegal (must_hold): the robot interface then holds the arm.
#pragma once

#include <cstdint>
#include <vector>

#include <Eigen/Core>

#include "robotics/pid.hpp"

namespace chimera::robotics {

/// A bridge stamp [counter, age, 1 | 0 | -1] says stale; no stamp (nullptr) never does.
inline bool stamp_says_stale(const double* stamp) noexcept { return stamp != nullptr && stamp[2] < 0; }

/// What STALE hold holds on: measurements the bridge's stamp says are stale,
/// or the illegal-configuration flag (§3.10, Task::illegal_configuration).
/// While the flag is set the robot interface (robotsim's STABILITY hold) holds
/// the arm and ignores its command: the loop is as open as with stale data, and
/// a PID or trajectory that ran on would make the arm lunge when let go.
inline bool must_hold(const double* stamp, bool illegal_configuration) noexcept {
    return illegal_configuration || stamp_says_stale(stamp);
}

enum class Freshness : std::uint8_t {
    fresh,      ///< fresh now and on the cycle before
    stale,      ///< stale now
    recovered,  ///< fresh now after stale cycles: the one cycle to restart on
};

/// Tells the first fresh cycle after stale ones from the others.
class StaleWatch {
public:
    Freshness update(bool stale) noexcept {
        const bool was_stale = stale_;
        stale_ = stale;
        if (stale) return Freshness::stale;
        return was_stale ? Freshness::recovered : Freshness::fresh;
    }
    void reset() noexcept { stale_ = false; }

private:
    bool stale_ = false;
};

/// Per-element slew-rate limit: the output moves toward its target by at most
/// rate * dt per step.
class SlewLimiter {
public:
    /// Every rate > 0 (infinity: no limit); std::invalid_argument otherwise.
    explicit SlewLimiter(Eigen::VectorXd rate);
    /// The output starts from `y`.
    void reset(const Eigen::Ref<const Eigen::VectorXd>& y) noexcept { y_ = y; }
    /// One step toward `target`, written to `out`; element i is limited when
    /// |target - output| > rate * dt. Returns how many were limited.
    std::size_t step(const Eigen::Ref<const Eigen::VectorXd>& target, double dt,
                     Eigen::Ref<Eigen::VectorXd> out) noexcept;
    const Eigen::VectorXd& output() const noexcept { return y_; }
    const Eigen::VectorXd& rate() const noexcept { return rate_; }

private:
    Eigen::VectorXd rate_, y_;
};

/// A Pid with STALE hold: while stale its output is the last good one and its
/// integral frozen; on the first fresh cycle the integral is reset and the
/// output slewed from the held value toward the PID's at `slew_rate` (per
/// joint, N m/s) until it reaches it, after which that joint follows the PID
/// directly again (until the next recovery). Stale from reset() on, the held
/// output is zero and the first fresh cycle starts the PID as reset() would.
class StaleHoldPid {
public:
    StaleHoldPid(Pid pid, Eigen::VectorXd slew_rate);

    /// `on`: no integral, no hold, no slew, held output zero.
    void reset() noexcept;
    /// One cycle; `u` receives the output (the held one while stale).
    Freshness update(bool stale, const Eigen::Ref<const Eigen::VectorXd>& q_ref,
                     const Eigen::Ref<const Eigen::VectorXd>& qd_ref, const Eigen::Ref<const Eigen::VectorXd>& q_mez,
                     const Eigen::Ref<const Eigen::VectorXd>& qd_mez, const Eigen::Ref<const Eigen::VectorXd>& ff,
                     double dt, Eigen::Ref<Eigen::VectorXd> u) noexcept;

    const Pid& pid() const noexcept { return pid_; }
    /// Joints whose output is still slewing toward the PID's since the last recovery.
    std::size_t slewing() const noexcept;

private:
    Pid pid_;
    SlewLimiter slew_;
    StaleWatch watch_;
    Eigen::VectorXd out_, target_;
    bool has_output_ = false;    // an output computed since reset(): one worth holding and slewing from
    std::vector<char> slewing_;  // per joint: still behind the PID since the recovery
};

}  // namespace chimera::robotics
