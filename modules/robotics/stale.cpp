// Stale hold and bumpless restart (robotics/stale.hpp).
#include "robotics/stale.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

namespace chimera::robotics {

SlewLimiter::SlewLimiter(Eigen::VectorXd rate) : rate_(std::move(rate)), y_(Eigen::VectorXd::Zero(rate_.size())) {
    for (Eigen::Index i = 0; i < rate_.size(); ++i) {
        if (!(rate_[i] > 0))
            throw std::invalid_argument("slew rate of element " + std::to_string(i + 1) + " must be > 0");
    }
}

std::size_t SlewLimiter::step(const Eigen::Ref<const Eigen::VectorXd>& target, double dt,
                              Eigen::Ref<Eigen::VectorXd> out) noexcept {
    std::size_t limited = 0;
    for (Eigen::Index i = 0; i < y_.size(); ++i) {
        const double max_step = rate_[i] * dt;  // inf * dt: no limit
        const double wanted = target[i] - y_[i];
        if (std::fabs(wanted) > max_step) {
            y_[i] += std::copysign(max_step, wanted);
            ++limited;
        } else {
            y_[i] = target[i];
        }
        out[i] = y_[i];
    }
    return limited;
}

StaleHoldPid::StaleHoldPid(Pid pid, Eigen::VectorXd slew_rate)
    : pid_(std::move(pid)),
      slew_(std::move(slew_rate)),
      out_(Eigen::VectorXd::Zero(static_cast<Eigen::Index>(pid_.ndof()))),
      target_(out_),
      slewing_(pid_.ndof(), 0) {
    if (slew_.rate().size() != out_.size())
        throw std::invalid_argument("SLEW has " + std::to_string(slew_.rate().size()) + " values, NDOF is " +
                                    std::to_string(pid_.ndof()));
}

void StaleHoldPid::reset() noexcept {
    pid_.reset();
    watch_.reset();
    out_.setZero();
    has_output_ = false;
    std::fill(slewing_.begin(), slewing_.end(), 0);
}

std::size_t StaleHoldPid::slewing() const noexcept {
    return static_cast<std::size_t>(std::count(slewing_.begin(), slewing_.end(), 1));
}

Freshness StaleHoldPid::update(bool stale, const Eigen::Ref<const Eigen::VectorXd>& q_ref,
                               const Eigen::Ref<const Eigen::VectorXd>& qd_ref,
                               const Eigen::Ref<const Eigen::VectorXd>& q_mez,
                               const Eigen::Ref<const Eigen::VectorXd>& qd_mez,
                               const Eigen::Ref<const Eigen::VectorXd>& ff, double dt,
                               Eigen::Ref<Eigen::VectorXd> u) noexcept {
    const Freshness f = watch_.update(stale);
    if (f == Freshness::stale) {
        u = out_;  // the last good output; the integral is not touched
        return f;
    }
    // Held ever since reset() (turned on during a reconfiguration), out_ is
    // the zero reset() left, not an output the arm ever got: the first cycle
    // after is the PID's own, as after `on`, with no slew up from that zero
    // (the robot held the arm meanwhile).
    if (f == Freshness::recovered && has_output_) {
        // What the integral gathered before the link went is no guide to the
        // arm now: restart it, and move the output there from the held one.
        pid_.reset();
        slew_.reset(out_);
        std::fill(slewing_.begin(), slewing_.end(), 1);
    }
    pid_.update(q_ref, qd_ref, q_mez, qd_mez, ff, dt, target_);
    if (slewing() > 0) {
        Eigen::VectorXd& slewed = out_;  // the limiter writes the slewed output here
        slew_.step(target_, dt, slewed);
        for (std::size_t j = 0; j < slewing_.size(); ++j) {
            const auto i = static_cast<Eigen::Index>(j);
            if (!slewing_[j]) out_[i] = target_[i];         // caught up earlier: follows the PID
            else if (out_[i] == target_[i]) slewing_[j] = 0;  // caught up now
        }
    } else {
        out_ = target_;
    }
    has_output_ = true;
    u = out_;
    return f;
}

}  // namespace chimera::robotics
