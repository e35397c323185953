// robotics/limits.hpp — the per-joint limits a torque-mode robot interface
// (robotsim, canrobot) applies to the torque it is given, whatever the
// controller asks for (issue #29.6: a lost link must never move the arm fast).
//
// Each cycle, per joint, in this order:
//   1. |torque| <= TLIMIT;
//   2. torque rate: at most TRATE * dt from the torque applied the cycle before;
//   3. speed: the torque allowed in the direction of motion falls linearly
//      with the joint's speed, from `bias` + TLIMIT at rest to `bias` at VLIMIT
//      (and below it beyond), a drive's torque-speed envelope:
//        bias - k (VLIMIT + qd) <= torque <= bias + k (VLIMIT - qd),  k = TLIMIT / VLIMIT,
//      where `bias` is the torque that holds the joint still (gravity), so
//      at VLIMIT the joint can no longer be accelerated, only held or braked;
//   4. |torque| <= TLIMIT again.
// The speed limit comes after the rate limit: a speed limit is never traded for
// a smooth torque. Each limit counts the joint-cycles it changed the torque.
#pragma once

#include <cstdint>

#include <Eigen/Core>

namespace chimera::robotics {

struct JointLimits {
    Eigen::VectorXd tlimit;  ///< N m, >= 0
    Eigen::VectorXd vlimit;  ///< rad/s, > 0; infinity: none
    Eigen::VectorXd trate;   ///< N m/s, > 0; infinity: none
};

class JointLimiter {
public:
    /// Three vectors of one size, in range; std::invalid_argument naming the key otherwise.
    explicit JointLimiter(JointLimits limits);

    std::size_t ndof() const noexcept { return static_cast<std::size_t>(l_.tlimit.size()); }
    const JointLimits& limits() const noexcept { return l_; }
    /// The torque applied now (where the rate limit starts from).
    void reset(const Eigen::Ref<const Eigen::VectorXd>& applied) noexcept { last_ = applied; }
    /// `tau`: in, the torque asked for; out, the torque to apply. `qd` the
    /// joints' speeds, `bias` the torque that holds them (zero without a model).
    void apply(Eigen::Ref<Eigen::VectorXd> tau, const Eigen::Ref<const Eigen::VectorXd>& qd,
               const Eigen::Ref<const Eigen::VectorXd>& bias, double dt) noexcept;

    std::uint64_t rate_clamps() const noexcept { return rate_clamps_; }
    std::uint64_t speed_clamps() const noexcept { return speed_clamps_; }

private:
    JointLimits l_;
    Eigen::VectorXd last_;
    std::uint64_t rate_clamps_ = 0, speed_clamps_ = 0;
};

}  // namespace chimera::robotics
