// robotics/dynamics.hpp — inverse dynamics (recursive Newton-Euler), gravity
// compensation, the joint-space inertia matrix, and a rigid-body arm simulator
// integrating the forward dynamics. KDL solvers inside, Eigen at the
// interfaces; sized in the constructor, no allocation per call.
//
//   tau = M(q) qdd + C(q, qd) qd + g(q) + Jm qdd + B qd + Tc(qd)
// where Jm (rotor inertia), B (viscous friction) and Tc (Coulomb friction:
// Tc+ while qd > 0, Tc- while qd < 0, 0 at rest) are the per-joint terms of the
// model (DhLink::rotor_inertia, damping, coulomb_pos, coulomb_neg) — the
// Robotics Toolbox's rne(), sign conventions included.
#pragma once

#include <vector>

#include <Eigen/Core>
#include <Eigen/Cholesky>
#include <kdl/chaindynparam.hpp>
#include <kdl/chainidsolver_recursive_newton_euler.hpp>
#include <kdl/jntarray.hpp>
#include <kdl/jntspaceinertiamatrix.hpp>

#include "robotics/model.hpp"

namespace chimera::robotics {

class Dynamics {
public:
    explicit Dynamics(const RobotModel& model);
    Dynamics(const Dynamics&) = delete;
    Dynamics& operator=(const Dynamics&) = delete;

    std::size_t ndof() const noexcept { return n_; }

    /// Joint torques for motion (q, qd, qdd), including gravity, rotor inertia,
    /// viscous and Coulomb friction. Returns false on a solver error or a size
    /// mismatch.
    bool inverse(const Eigen::Ref<const Eigen::VectorXd>& q,
                 const Eigen::Ref<const Eigen::VectorXd>& qd,
                 const Eigen::Ref<const Eigen::VectorXd>& qdd,
                 Eigen::Ref<Eigen::VectorXd> tau) noexcept;
    /// Gravity torques g(q): the torques that hold the arm still at q.
    bool gravity(const Eigen::Ref<const Eigen::VectorXd>& q, Eigen::Ref<Eigen::VectorXd> tau) noexcept;
    /// Joint-space inertia matrix M(q) + diag(Jm).
    bool mass(const Eigen::Ref<const Eigen::VectorXd>& q, Eigen::Ref<Eigen::MatrixXd> m) noexcept;
    /// The Coulomb friction torque of `joint` turning at `qd`: Tc+ for qd > 0,
    /// Tc- (<= 0) for qd < 0, 0 at rest.
    double coulomb(std::size_t joint, double qd) const noexcept {
        return qd > 0 ? coulomb_pos_[joint] : qd < 0 ? coulomb_neg_[joint] : 0.0;
    }
    /// Tc+ and Tc- of `joint`, the range of torque its friction holds at rest.
    double coulomb_pos(std::size_t joint) const noexcept { return coulomb_pos_[joint]; }
    double coulomb_neg(std::size_t joint) const noexcept { return coulomb_neg_[joint]; }

private:
    // KDL's solvers keep a reference to the chain they were built on, so the
    // chain lives here, before them: a Dynamics built from a temporary model
    // (a module's init reading the DH in-const) stays valid.
    KDL::Chain chain_;
    std::size_t n_;
    std::vector<double> rotor_, damping_, coulomb_pos_, coulomb_neg_;
    KDL::ChainIdSolver_RNE rne_;
    KDL::ChainDynParam dyn_;
    KDL::JntArray q_, qd_, qdd_, tau_;
    KDL::Wrenches fext_;
    KDL::JntSpaceInertiaMatrix m_;
};

/// A simulated arm (§7.3 transparent simulation): integrates
///   qdd = M(q)^-1 (tau - C qd - g(q) - B qd - Tc(qd))
/// with a semi-implicit (symplectic) Euler step, several substeps per call so it
/// runs at its own rate, finer than the task that drives it. Coulomb friction
/// sticks and slips: a joint at rest stays at rest while the torque left at it
/// (with the others' accelerations ignored) is within [Tc-, Tc+], and starts
/// against Tc+ or Tc- when it is not; a moving joint whose velocity friction
/// would reverse within a substep stops instead.
class ArmSimulator {
public:
    explicit ArmSimulator(const RobotModel& model);

    std::size_t ndof() const noexcept { return n_; }
    void reset(const Eigen::Ref<const Eigen::VectorXd>& q,
               const Eigen::Ref<const Eigen::VectorXd>& qd) noexcept;
    /// Advances by `dt` seconds in `substeps` equal steps with the torque held.
    bool step(const Eigen::Ref<const Eigen::VectorXd>& tau, double dt, int substeps = 1) noexcept;
    /// Locks a joint (its brake): from now on it does not move (qd = qdd = 0)
    /// and the others move as the constrained arm does (exact: the locked rows
    /// and columns leave the mass matrix). Unlocking lets it move again.
    void set_locked(std::size_t joint, bool locked) noexcept;
    bool locked(std::size_t joint) const noexcept { return locked_[joint] != 0; }

    const Eigen::VectorXd& q() const noexcept { return q_; }
    const Eigen::VectorXd& qd() const noexcept { return qd_; }
    const Eigen::VectorXd& qdd() const noexcept { return qdd_; }
    /// The factor of the mass matrix the last step solved with (held joints'
    /// rows and columns the identity's): x = M^-1 b is how that step's
    /// accelerations answer a torque change b, with no step taken.
    const Eigen::LLT<Eigen::MatrixXd>& mass_factor() const noexcept { return llt_; }
    double time() const noexcept { return t_; }

private:
    bool stick_or_slip(std::size_t joint) noexcept;
    void hold_joints() noexcept;

    std::size_t n_;
    Dynamics dyn_;
    Eigen::VectorXd q_, qd_, qdd_, bias_, zero_, rhs_;
    Eigen::MatrixXd m_;
    Eigen::LLT<Eigen::MatrixXd> llt_;
    std::vector<char> locked_, held_;
    bool any_locked_ = false;
    bool any_coulomb_ = false;
    double t_ = 0;
};

}  // namespace chimera::robotics
