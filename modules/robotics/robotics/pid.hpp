// robotics/pid.hpp — per-joint PID with output limits and anti-windup.
//
//   u = Kp e + Ki I + Kd ed (+ feed-forward),  e = q_ref - q_mez, ed = qd_ref - qd_mez
//   I += e dt, clamped to [-ilimit, ilimit]; and not integrated while the output
//   is saturated in the direction e would push it further (conditional
//   integration), so the integrator does not wind up against a limit.
//   u is clamped to [-ulimit, ulimit].
#pragma once

#include <Eigen/Core>

namespace chimera::robotics {

struct PidGains {
    Eigen::VectorXd kp, ki, kd;
    Eigen::VectorXd ilimit;  ///< bound on the integral state (rad s), per joint
    Eigen::VectorXd ulimit;  ///< bound on the output, per joint (N m or rad/s)
};

class Pid {
public:
    /// All gain vectors must have ndof elements (std::invalid_argument otherwise).
    Pid(std::size_t ndof, PidGains gains);

    std::size_t ndof() const noexcept { return n_; }
    const PidGains& gains() const noexcept { return g_; }
    void reset() noexcept { integral_.setZero(); }
    const Eigen::VectorXd& integral() const noexcept { return integral_; }
    /// One control step; `ff` is added before the limit (gravity, inverse dynamics).
    void update(const Eigen::Ref<const Eigen::VectorXd>& q_ref,
                const Eigen::Ref<const Eigen::VectorXd>& qd_ref,
                const Eigen::Ref<const Eigen::VectorXd>& q_mez,
                const Eigen::Ref<const Eigen::VectorXd>& qd_mez,
                const Eigen::Ref<const Eigen::VectorXd>& ff, double dt,
                Eigen::Ref<Eigen::VectorXd> u) noexcept;

private:
    std::size_t n_;
    PidGains g_;
    Eigen::VectorXd integral_;
};

}  // namespace chimera::robotics
