// Inverse dynamics, gravity, inertia matrix, and the forward-dynamics simulator.
#include "robotics/dynamics.hpp"

#include <algorithm>
#include <cmath>

namespace chimera::robotics {

namespace {
KDL::Vector kdl_gravity(const RobotModel& m) {
    return KDL::Vector(m.gravity().x(), m.gravity().y(), m.gravity().z());
}
}  // namespace

Dynamics::Dynamics(const RobotModel& model)
    : chain_(model.chain()),
      n_(chain_.getNrOfJoints()),
      rne_(chain_, kdl_gravity(model)),
      dyn_(chain_, kdl_gravity(model)),
      q_(static_cast<unsigned>(n_)),
      qd_(static_cast<unsigned>(n_)),
      qdd_(static_cast<unsigned>(n_)),
      tau_(static_cast<unsigned>(n_)),
      fext_(chain_.getNrOfSegments(), KDL::Wrench::Zero()),
      m_(static_cast<unsigned>(n_)) {
    rotor_.assign(n_, 0.0);
    damping_.assign(n_, 0.0);
    coulomb_pos_.assign(n_, 0.0);
    coulomb_neg_.assign(n_, 0.0);
    if (model.links().size() == n_) {
        for (std::size_t i = 0; i < n_; ++i) {
            rotor_[i] = model.links()[i].rotor_inertia;
            damping_[i] = model.links()[i].damping;
            coulomb_pos_[i] = model.links()[i].coulomb_pos;
            coulomb_neg_[i] = model.links()[i].coulomb_neg;
        }
    }
}

bool Dynamics::inverse(const Eigen::Ref<const Eigen::VectorXd>& q,
                       const Eigen::Ref<const Eigen::VectorXd>& qd,
                       const Eigen::Ref<const Eigen::VectorXd>& qdd,
                       Eigen::Ref<Eigen::VectorXd> tau) noexcept {
    const auto n = static_cast<Eigen::Index>(n_);
    if (q.size() != n || qd.size() != n || qdd.size() != n || tau.size() != n) return false;
    q_.data = q;
    qd_.data = qd;
    qdd_.data = qdd;
    if (rne_.CartToJnt(q_, qd_, qdd_, fext_, tau_) < 0) return false;
    for (Eigen::Index i = 0; i < n; ++i) {
        const auto j = static_cast<std::size_t>(i);
        tau[i] = tau_(static_cast<unsigned>(i)) + rotor_[j] * qdd[i] + damping_[j] * qd[i] +
                 coulomb(j, qd[i]);
    }
    return true;
}

bool Dynamics::gravity(const Eigen::Ref<const Eigen::VectorXd>& q,
                       Eigen::Ref<Eigen::VectorXd> tau) noexcept {
    const auto n = static_cast<Eigen::Index>(n_);
    if (q.size() != n || tau.size() != n) return false;
    q_.data = q;
    qd_.data.setZero();
    qdd_.data.setZero();
    if (rne_.CartToJnt(q_, qd_, qdd_, fext_, tau_) < 0) return false;
    tau = tau_.data;
    return true;
}

bool Dynamics::mass(const Eigen::Ref<const Eigen::VectorXd>& q,
                    Eigen::Ref<Eigen::MatrixXd> m) noexcept {
    const auto n = static_cast<Eigen::Index>(n_);
    if (q.size() != n || m.rows() != n || m.cols() != n) return false;
    q_.data = q;
    if (dyn_.JntToMass(q_, m_) < 0) return false;
    m = m_.data;
    for (Eigen::Index i = 0; i < n; ++i) m(i, i) += rotor_[i];
    return true;
}

ArmSimulator::ArmSimulator(const RobotModel& model)
    : n_(model.chain().getNrOfJoints()),
      dyn_(model),
      q_(Eigen::VectorXd::Zero(static_cast<Eigen::Index>(n_))),
      qd_(Eigen::VectorXd::Zero(static_cast<Eigen::Index>(n_))),
      qdd_(Eigen::VectorXd::Zero(static_cast<Eigen::Index>(n_))),
      bias_(Eigen::VectorXd::Zero(static_cast<Eigen::Index>(n_))),
      zero_(Eigen::VectorXd::Zero(static_cast<Eigen::Index>(n_))),
      rhs_(Eigen::VectorXd::Zero(static_cast<Eigen::Index>(n_))),
      m_(Eigen::MatrixXd::Zero(static_cast<Eigen::Index>(n_), static_cast<Eigen::Index>(n_))),
      llt_(static_cast<Eigen::Index>(n_)),
      locked_(n_, 0),
      held_(n_, 0) {
    for (std::size_t j = 0; j < n_; ++j) {
        if (dyn_.coulomb_pos(j) != 0 || dyn_.coulomb_neg(j) != 0) any_coulomb_ = true;
    }
}

void ArmSimulator::set_locked(std::size_t joint, bool locked) noexcept {
    if (joint >= n_) return;
    locked_[joint] = locked ? 1 : 0;
    if (locked) qd_[static_cast<Eigen::Index>(joint)] = 0;
    any_locked_ = std::find(locked_.begin(), locked_.end(), 1) != locked_.end();
}

void ArmSimulator::reset(const Eigen::Ref<const Eigen::VectorXd>& q,
                         const Eigen::Ref<const Eigen::VectorXd>& qd) noexcept {
    q_ = q;
    qd_ = qd;
    qdd_.setZero();
    t_ = 0;
}

bool ArmSimulator::step(const Eigen::Ref<const Eigen::VectorXd>& tau, double dt,
                        int substeps) noexcept {
    if (tau.size() != q_.size() || substeps < 1 || !(dt > 0)) return false;
    const double h = dt / substeps;
    for (int s = 0; s < substeps; ++s) {
        // bias = C(q,qd) qd + g(q) + B qd + Tc(qd): inverse dynamics with zero
        // acceleration (Tc is 0 for a joint at rest, decided below).
        if (!dyn_.inverse(q_, qd_, zero_, bias_)) return false;
        if (!dyn_.mass(q_, m_)) return false;
        rhs_ = tau - bias_;
        bool any_held = any_locked_;
        for (std::size_t j = 0; j < n_; ++j) {
            held_[j] = locked_[j];
            if (any_coulomb_ && !held_[j] && stick_or_slip(j)) any_held = true;
        }
        if (any_held) hold_joints();
        llt_.compute(m_);
        if (llt_.info() != Eigen::Success) return false;
        llt_.solveInPlace(rhs_);
        qdd_ = rhs_;
        // Semi-implicit Euler: velocity first, then position with the new velocity.
        for (Eigen::Index i = 0; i < qd_.size(); ++i) {
            const double before = qd_[i];
            qd_[i] += h * qdd_[i];
            // Friction stops a joint; it does not turn it round.
            if (any_coulomb_ && before * qd_[i] < 0 &&
                dyn_.coulomb(static_cast<std::size_t>(i), before) != 0) {
                qd_[i] = 0;
            }
        }
        q_ += h * qd_;
        t_ += h;
    }
    for (Eigen::Index i = 0; i < q_.size(); ++i) {
        if (!std::isfinite(q_[i]) || !std::isfinite(qd_[i])) return false;
    }
    return true;
}

bool ArmSimulator::stick_or_slip(std::size_t j) noexcept {
    const auto i = static_cast<Eigen::Index>(j);
    if (qd_[i] != 0) return false;  // moving: bias_ has its Coulomb term
    const double net = rhs_[i];
    if (net <= dyn_.coulomb_pos(j) && net >= dyn_.coulomb_neg(j)) {
        held_[j] = 1;  // static friction holds it
        return true;
    }
    rhs_[i] -= net > 0 ? dyn_.coulomb_pos(j) : dyn_.coulomb_neg(j);  // breaks away
    return false;
}

void ArmSimulator::hold_joints() noexcept {
    // A held joint's row and column become the identity's and its right-hand
    // side 0: its qdd is 0 and the free joints solve their own block of M, the
    // constrained dynamics.
    for (Eigen::Index j = 0; j < m_.rows(); ++j) {
        if (!held_[static_cast<std::size_t>(j)]) continue;
        m_.row(j).setZero();
        m_.col(j).setZero();
        m_(j, j) = 1;
        rhs_[j] = 0;
        qd_[j] = 0;
    }
}

}  // namespace chimera::robotics
