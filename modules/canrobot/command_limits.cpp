#include "canrobot/command_limits.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace chimera::canrobot {

namespace {
bool any_finite(const Eigen::VectorXd& v) { return v.array().isFinite().any(); }
}  // namespace

CommandLimiter::CommandLimiter(const BusConfig& bus, bool position_mode) : vlimit_(bus.vlimit) {
    if (!any_finite(bus.vlimit) && !any_finite(bus.trate)) return;
    if (!position_mode) {
        torque_.emplace(robotics::JointLimits{bus.torque_limit, bus.vlimit, bus.trate});
        return;
    }
    if (any_finite(bus.trate))
        throw std::invalid_argument("TRATE: in position mode the drive's own loop makes the torque; "
                                    "limit the target's speed with VLIMIT instead");
    // SlewLimiter's message names the element; say which key it is.
    for (Eigen::Index j = 0; j < vlimit_.size(); ++j)
        if (!(vlimit_[j] > 0))
            throw std::invalid_argument("VLIMIT of joint " + std::to_string(j + 1) + " must be > 0");
    target_.emplace(vlimit_);
}

void CommandLimiter::reset(const Eigen::Ref<const Eigen::VectorXd>& now) noexcept {
    if (torque_) torque_->reset(now);
    if (target_) target_->reset(now);
}

void CommandLimiter::limit_torque(Eigen::Ref<Eigen::VectorXd> tau, const Eigen::Ref<const Eigen::VectorXd>& qd,
                                  const Eigen::Ref<const Eigen::VectorXd>& gravity, double dt) noexcept {
    if (torque_) torque_->apply(tau, qd, gravity, dt);
}

void CommandLimiter::limit_target(Eigen::Ref<Eigen::VectorXd> q, Eigen::Ref<Eigen::VectorXd> qd, double dt) noexcept {
    if (!target_) return;
    // A joint-cycle counts once, whether its step, its offset or both were limited.
    Eigen::VectorXd::Index n = q.size();
    for (Eigen::Index j = 0; j < n; ++j) {
        const double wanted_step = q[j] - target_->output()[j];
        const bool step_limited = std::fabs(wanted_step) > vlimit_[j] * dt;
        const double offset = std::clamp(qd[j], -vlimit_[j], vlimit_[j]);
        target_clamps_ += step_limited || offset != qd[j];
        qd[j] = offset;
    }
    target_->step(q, dt, q);
}

std::uint64_t CommandLimiter::speed_clamps() const noexcept {
    return torque_ ? torque_->speed_clamps() : target_clamps_;
}

std::string CommandLimiter::report() const {
    if (!active()) return "none";
    return "speed_clamps " + std::to_string(speed_clamps()) + " rate_clamps " + std::to_string(rate_clamps());
}

}  // namespace chimera::canrobot
