// robotics/dynamics.hpp — inverse dynamics (recursive Newton-Euler), gravity
// compensation, the joint-space inertia matrix, and a rigid-body arm simulator
// integrating the forward dynamics. KDL solvers inside, Eigen at the
// interfaces; sized in the constructor, no allocation per call.
//
//   tau = M(q) qdd + C(q, qd) qd + g(q) + Jm qdd + B qd
// where Jm (rotor inertia) and B (viscous friction) are the per-joint terms of
// the model (DhLink::rotor_inertia, DhLink::damping).
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

    /// Joint torques for motion (q, qd, qdd), including gravity, rotor inertia and
    /// viscous friction. Returns false on a solver error or a size mismatch.
    bool inverse(const Eigen::Ref<const Eigen::VectorXd>& q,
                 const Eigen::Ref<const Eigen::VectorXd>& qd,
                 const Eigen::Ref<const Eigen::VectorXd>& qdd,
                 Eigen::Ref<Eigen::VectorXd> tau) noexcept;
    /// Gravity torques g(q): the torques that hold the arm still at q.
    bool gravity(const Eigen::Ref<const Eigen::VectorXd>& q, Eigen::Ref<Eigen::VectorXd> tau) noexcept;
    /// Joint-space inertia matrix M(q) + diag(Jm).
    bool mass(const Eigen::Ref<const Eigen::VectorXd>& q, Eigen::Ref<Eigen::MatrixXd> m) noexcept;

private:
    // KDL's solvers keep a reference to the chain they were built on, so the
    // chain lives here, before them: a Dynamics built from a temporary model
    // (a module's init reading the DH in-const) stays valid.
    KDL::Chain chain_;
    std::size_t n_;
    std::vector<double> rotor_, damping_;
    KDL::ChainIdSolver_RNE rne_;
    KDL::ChainDynParam dyn_;
    KDL::JntArray q_, qd_, qdd_, tau_;
    KDL::Wrenches fext_;
    KDL::JntSpaceInertiaMatrix m_;
};

/// A simulated arm (§7.3 transparent simulation): integrates
///   qdd = M(q)^-1 (tau - C qd - g(q) - B qd)
/// with a semi-implicit (symplectic) Euler step, several substeps per call so it
/// runs at its own rate, finer than the task that drives it.
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
    double time() const noexcept { return t_; }

private:
    std::size_t n_;
    Dynamics dyn_;
    Eigen::VectorXd q_, qd_, qdd_, bias_, zero_, rhs_;
    Eigen::MatrixXd m_;
    Eigen::LLT<Eigen::MatrixXd> llt_;
    std::vector<char> locked_;
    bool any_locked_ = false;
    double t_ = 0;
};

}  // namespace chimera::robotics
