// PID with clamped integral, conditional integration and output limits.
#include "robotics/pid.hpp"

#include <algorithm>
#include <stdexcept>
#include <string>

namespace chimera::robotics {

Pid::Pid(std::size_t ndof, PidGains gains)
    : n_(ndof), g_(std::move(gains)), integral_(Eigen::VectorXd::Zero(static_cast<Eigen::Index>(ndof))) {
    const auto n = static_cast<Eigen::Index>(ndof);
    const struct { const char* name; const Eigen::VectorXd* v; } all[] = {
        {"KP", &g_.kp}, {"KI", &g_.ki}, {"KD", &g_.kd}, {"ILIMIT", &g_.ilimit}, {"ULIMIT", &g_.ulimit}};
    for (const auto& item : all) {
        if (item.v->size() != n) {
            throw std::invalid_argument(std::string(item.name) + " has " +
                                        std::to_string(item.v->size()) + " values, NDOF is " +
                                        std::to_string(ndof));
        }
    }
    for (Eigen::Index i = 0; i < n; ++i) {
        if (g_.ilimit[i] < 0 || g_.ulimit[i] < 0) {
            throw std::invalid_argument("ILIMIT and ULIMIT must be >= 0 (joint " +
                                        std::to_string(i + 1) + ")");
        }
    }
}

void Pid::update(const Eigen::Ref<const Eigen::VectorXd>& q_ref,
                 const Eigen::Ref<const Eigen::VectorXd>& qd_ref,
                 const Eigen::Ref<const Eigen::VectorXd>& q_mez,
                 const Eigen::Ref<const Eigen::VectorXd>& qd_mez,
                 const Eigen::Ref<const Eigen::VectorXd>& ff, double dt,
                 Eigen::Ref<Eigen::VectorXd> u) noexcept {
    for (Eigen::Index i = 0; i < static_cast<Eigen::Index>(n_); ++i) {
        const double e = q_ref[i] - q_mez[i];
        const double ed = qd_ref[i] - qd_mez[i];
        const double lim = g_.ulimit[i];
        const double unsat_before = g_.kp[i] * e + g_.ki[i] * integral_[i] + g_.kd[i] * ed + ff[i];
        const bool pushing_further = (unsat_before >= lim && e > 0) || (unsat_before <= -lim && e < 0);
        if (!pushing_further) {
            integral_[i] = std::clamp(integral_[i] + e * dt, -g_.ilimit[i], g_.ilimit[i]);
        }
        const double out = g_.kp[i] * e + g_.ki[i] * integral_[i] + g_.kd[i] * ed + ff[i];
        u[i] = std::clamp(out, -lim, lim);
    }
}

}  // namespace chimera::robotics
