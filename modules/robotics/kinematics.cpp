// Forward kinematics, Jacobian and differential / Newton inverse kinematics.
#include "robotics/kinematics.hpp"

#include <cmath>

namespace chimera::robotics {

Vector6d frame_to_pose(const KDL::Frame& f) noexcept {
    Vector6d x;
    x[0] = f.p.x();
    x[1] = f.p.y();
    x[2] = f.p.z();
    f.M.GetRPY(x[3], x[4], x[5]);
    return x;
}

KDL::Frame pose_to_frame(const Eigen::Ref<const Vector6d>& x) noexcept {
    return KDL::Frame(KDL::Rotation::RPY(x[3], x[4], x[5]), KDL::Vector(x[0], x[1], x[2]));
}

Vector6d pose_error(const KDL::Frame& from, const KDL::Frame& to) noexcept {
    const KDL::Twist t = KDL::diff(from, to);
    Vector6d e;
    for (int i = 0; i < 6; ++i) e[i] = t[i];
    return e;
}

Kinematics::Kinematics(const RobotModel& model)
    : chain_(model.chain()),
      n_(chain_.getNrOfJoints()),
      fk_(chain_),
      jac_(chain_),
      q_(static_cast<unsigned>(n_)),
      j_(static_cast<unsigned>(n_)) {}

bool Kinematics::fk(const Eigen::Ref<const Eigen::VectorXd>& q, KDL::Frame& out) noexcept {
    if (static_cast<std::size_t>(q.size()) != n_) return false;
    q_.data = q;
    return fk_.JntToCart(q_, out) >= 0;
}

bool Kinematics::fk(const Eigen::Ref<const Eigen::VectorXd>& q, Eigen::Ref<Vector6d> pose) noexcept {
    KDL::Frame f;
    if (!fk(q, f)) return false;
    pose = frame_to_pose(f);
    return true;
}

bool Kinematics::jacobian(const Eigen::Ref<const Eigen::VectorXd>& q,
                          Eigen::Ref<Matrix6Xd> j) noexcept {
    if (static_cast<std::size_t>(q.size()) != n_ || static_cast<std::size_t>(j.cols()) != n_) {
        return false;
    }
    q_.data = q;
    if (jac_.JntToJac(q_, j_) < 0) return false;
    j = j_.data;
    return true;
}

DiffIk::DiffIk(const RobotModel& model, const Vector6d& task_weights, double lambda)
    : n_(model.chain().getNrOfJoints()),
      kin_(model),
      w_(task_weights),
      lambda_(lambda),
      j_(6, static_cast<Eigen::Index>(n_)),
      wj_(6, static_cast<Eigen::Index>(n_)),
      a_(n_ <= 6 ? n_ : 6, n_ <= 6 ? n_ : 6),
      rhs_(n_ <= 6 ? n_ : 6),
      sol_(n_ <= 6 ? n_ : 6),
      ldlt_(n_ <= 6 ? n_ : 6),
      dq_(static_cast<Eigen::Index>(n_)) {}

bool DiffIk::solve_velocity(const Eigen::Ref<const Eigen::VectorXd>& q,
                            const Eigen::Ref<const Vector6d>& e,
                            Eigen::Ref<Eigen::VectorXd> dq) noexcept {
    if (!kin_.jacobian(q, j_)) return false;
    const double l2 = lambda_ * lambda_;
    if (n_ <= 6) {
        wj_ = w_.asDiagonal() * j_;
        a_.noalias() = j_.transpose() * wj_;
        a_.diagonal().array() += l2;
        rhs_.noalias() = j_.transpose() * w_.cwiseProduct(e);
        ldlt_.compute(a_);
        if (ldlt_.info() != Eigen::Success) return false;
        sol_ = rhs_;
        ldlt_.solveInPlace(sol_);
        dq = sol_;
    } else {
        // Symmetric form with S = sqrt(W): (S J J^T S + lambda^2 I) y = S e,
        // dq = J^T S y. Components with zero weight get a unit diagonal so the
        // matrix stays positive definite and they solve to zero.
        const Vector6d s = w_.cwiseSqrt();
        wj_ = s.asDiagonal() * j_;
        a_.noalias() = wj_ * wj_.transpose();
        a_.diagonal().array() += l2;
        for (int i = 0; i < 6; ++i) {
            if (w_[i] == 0) a_(i, i) = 1;
        }
        rhs_ = s.cwiseProduct(e);
        ldlt_.compute(a_);
        if (ldlt_.info() != Eigen::Success) return false;
        sol_ = rhs_;
        ldlt_.solveInPlace(sol_);
        sol_ = s.cwiseProduct(sol_);
        dq.noalias() = j_.transpose() * sol_;
    }
    for (Eigen::Index i = 0; i < dq.size(); ++i) {
        if (!std::isfinite(dq[i])) return false;
    }
    return true;
}

int DiffIk::solve_position(Eigen::Ref<Eigen::VectorXd> q, const KDL::Frame& target, int max_iter,
                           double tol) noexcept {
    for (int it = 0; it <= max_iter; ++it) {
        if (!kin_.fk(q, f_)) return -1;
        const Vector6d e = pose_error(f_, target);
        if (w_.cwiseProduct(e).norm() < tol) return it;
        if (it == max_iter) break;
        if (!solve_velocity(q, e, dq_)) return -1;
        q += dq_;
    }
    return -1;
}

}  // namespace chimera::robotics
