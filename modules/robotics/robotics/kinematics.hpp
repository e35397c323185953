// robotics/kinematics.hpp — forward kinematics, Jacobian, inverse kinematics
// (Newton with pseudo-inverse, and damped least squares) on KDL solvers, with
// Eigen at the interfaces. Everything is sized by the constructor from the
// model; the per-cycle calls neither allocate nor make system calls.
//
// A Cartesian pose X is a 6-vector [x y z roll pitch yaw] (m, rad): position of
// the tool frame and its orientation as fixed-axis roll (X), pitch (Y), yaw (Z)
// angles in the base frame (KDL::Rotation::GetRPY). Cartesian velocities are
// twists [vx vy vz wx wy wz] in the base frame, at the tool point.
#pragma once

#include <memory>

#include <Eigen/Core>
#include <Eigen/Cholesky>
#include <kdl/chainfksolverpos_recursive.hpp>
#include <kdl/chainjnttojacsolver.hpp>
#include <kdl/frames.hpp>
#include <kdl/jacobian.hpp>
#include <kdl/jntarray.hpp>

#include "robotics/model.hpp"

namespace chimera::robotics {

using Vector6d = Eigen::Matrix<double, 6, 1>;
using Matrix6Xd = Eigen::Matrix<double, 6, Eigen::Dynamic>;

/// Pose 6-vector <-> KDL frame.
Vector6d frame_to_pose(const KDL::Frame& f) noexcept;
KDL::Frame pose_to_frame(const Eigen::Ref<const Vector6d>& x) noexcept;
/// Twist that moves frame `from` to `to` in unit time, in the base frame
/// (position difference, and rotation vector of to * from^-1).
Vector6d pose_error(const KDL::Frame& from, const KDL::Frame& to) noexcept;

class Kinematics {
public:
    explicit Kinematics(const RobotModel& model);
    Kinematics(const Kinematics&) = delete;
    Kinematics& operator=(const Kinematics&) = delete;

    std::size_t ndof() const noexcept { return n_; }

    /// Tool frame at joint positions q. Returns false on a solver error.
    bool fk(const Eigen::Ref<const Eigen::VectorXd>& q, KDL::Frame& out) noexcept;
    bool fk(const Eigen::Ref<const Eigen::VectorXd>& q, Eigen::Ref<Vector6d> pose) noexcept;
    /// Geometric Jacobian (6 x NDOF) at the tool point, base frame.
    bool jacobian(const Eigen::Ref<const Eigen::VectorXd>& q, Eigen::Ref<Matrix6Xd> j) noexcept;

private:
    // KDL's solvers keep a reference to the chain: it lives here, before them
    // (see Dynamics).
    KDL::Chain chain_;
    std::size_t n_;
    KDL::ChainFkSolverPos_recursive fk_;
    KDL::ChainJntToJacSolver jac_;
    KDL::JntArray q_;
    KDL::Jacobian j_;
};

/// Differential inverse kinematics:
///   dq = (J^T W J + lambda^2 I)^-1 J^T W e   (NDOF <= 6)
///   dq = J^T (J W J^T + lambda^2 I)^-1 W e   (NDOF > 6, redundant)
/// with W = diag(task weights) choosing which Cartesian components count (a
/// planar arm uses x, y and yaw). lambda = 0 is the pseudo-inverse (Newton);
/// lambda > 0 is damped least squares (Wampler 1986; Nakamura & Hanafusa 1986),
/// which stays bounded through singularities.
class DiffIk {
public:
    DiffIk(const RobotModel& model, const Vector6d& task_weights, double lambda);
    DiffIk(const DiffIk&) = delete;
    DiffIk& operator=(const DiffIk&) = delete;

    void set_lambda(double lambda) noexcept { lambda_ = lambda; }
    double lambda() const noexcept { return lambda_; }
    Kinematics& kinematics() noexcept { return kin_; }

    /// Joint velocity for a Cartesian twist e at configuration q.
    bool solve_velocity(const Eigen::Ref<const Eigen::VectorXd>& q,
                        const Eigen::Ref<const Vector6d>& e,
                        Eigen::Ref<Eigen::VectorXd> dq) noexcept;

    /// Position IK by Newton iteration from q (in: seed, out: solution) towards
    /// the tool frame `target`; returns the number of iterations used, or -1 if
    /// the weighted error did not fall below `tol` within `max_iter`.
    int solve_position(Eigen::Ref<Eigen::VectorXd> q, const KDL::Frame& target, int max_iter,
                       double tol) noexcept;

private:
    std::size_t n_;
    Kinematics kin_;
    Vector6d w_;
    double lambda_;
    Matrix6Xd j_;
    Matrix6Xd wj_;          // weighted Jacobian
    Eigen::MatrixXd a_;     // n x n or 6 x 6 normal matrix
    Eigen::VectorXd rhs_;   // its right-hand side
    Eigen::VectorXd sol_;
    Eigen::LDLT<Eigen::MatrixXd> ldlt_;
    KDL::Frame f_;
    Eigen::VectorXd dq_;
};

}  // namespace chimera::robotics
