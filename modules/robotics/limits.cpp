// Per-joint torque, torque-rate and speed limits (robotics/limits.hpp).
#include "robotics/limits.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

namespace chimera::robotics {

namespace {

void check(const Eigen::VectorXd& v, Eigen::Index n, const char* key, bool zero_allowed) {
    if (v.size() != n)
        throw std::invalid_argument(std::string(key) + " has " + std::to_string(v.size()) + " values, TLIMIT has " +
                                    std::to_string(n));
    for (Eigen::Index i = 0; i < n; ++i) {
        if (zero_allowed ? !(v[i] >= 0) : !(v[i] > 0))
            throw std::invalid_argument(std::string(key) + " of joint " + std::to_string(i + 1) + " must be " +
                                        (zero_allowed ? ">= 0" : "> 0"));
    }
}

}  // namespace

JointLimiter::JointLimiter(JointLimits limits) : l_(std::move(limits)) {
    const Eigen::Index n = l_.tlimit.size();
    check(l_.tlimit, n, "TLIMIT", true);
    check(l_.vlimit, n, "VLIMIT", false);
    check(l_.trate, n, "TRATE", false);
    last_.setZero(n);
}

void JointLimiter::apply(Eigen::Ref<Eigen::VectorXd> tau, const Eigen::Ref<const Eigen::VectorXd>& qd,
                         const Eigen::Ref<const Eigen::VectorXd>& bias, double dt) noexcept {
    for (Eigen::Index i = 0; i < l_.tlimit.size(); ++i) {
        const double tl = l_.tlimit[i];
        double t = std::clamp(tau[i], -tl, tl);
        const double step = l_.trate[i] * dt;  // infinite: no rate limit
        const double rated = std::clamp(t, last_[i] - step, last_[i] + step);
        rate_clamps_ += rated != t;
        t = rated;
        if (std::isfinite(l_.vlimit[i])) {
            const double k = tl / l_.vlimit[i];
            const double hi = bias[i] + k * (l_.vlimit[i] - qd[i]);
            const double lo = bias[i] - k * (l_.vlimit[i] + qd[i]);
            const double enveloped = std::clamp(t, std::min(lo, hi), std::max(lo, hi));
            speed_clamps_ += enveloped != t;
            t = enveloped;
        }
        tau[i] = last_[i] = std::clamp(t, -tl, tl);
    }
}

}  // namespace chimera::robotics
