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

namespace {
std::uint32_t floor_in_range(double v) noexcept {
    if (!(v >= 1)) return 1;
    if (v >= 2147483647.0) return 2147483647u;
    return static_cast<std::uint32_t>(std::floor(v));
}
}  // namespace

std::uint32_t max_motor_speed_counts(double vlimit, double counts_per_rev) noexcept {
    return floor_in_range(vlimit * counts_per_rev / 6.283185307179586);
}

std::uint32_t torque_slope_permille(double trate, double rated_torque) noexcept {
    return floor_in_range(trate * 1000.0 / rated_torque);
}

std::vector<sdo::Download> drive_limit_downloads(const BusConfig& bus) {
    std::vector<sdo::Download> d;
    for (std::size_t j = 0; j < bus.nodes.size(); ++j) {
        const auto jj = static_cast<Eigen::Index>(j);
        if (jj < bus.vlimit.size() && std::isfinite(bus.vlimit[jj]))
            d.push_back({bus.nodes[j], j, sdo::kMaxMotorSpeed, max_motor_speed_counts(bus.vlimit[jj], bus.counts_per_rev[jj]), 4});
        if (jj < bus.trate.size() && std::isfinite(bus.trate[jj]))
            d.push_back({bus.nodes[j], j, sdo::kTorqueSlope, torque_slope_permille(bus.trate[jj], bus.rated_torque[jj]), 4});
    }
    return d;
}

}  // namespace chimera::canrobot
