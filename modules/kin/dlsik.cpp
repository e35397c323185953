// dlsik — damped-least-squares inverse kinematics controller (thesis Figure
// 3.16; Wampler 1986, Nakamura & Hanafusa 1986): joint velocities that drive
// the tool towards the desired pose, bounded near singularities. A time
// integrator (integ) turns them into reference joint positions.
//
//   INCONST NDOF DH
//   INVAR   X_REF    desired tool pose [x y z roll pitch yaw] (m, rad)
//           Q_REF    current reference joint positions (rad), the integrator's output
//   OUTVAR  Q^_REF   reference joint velocities (rad/s)
//   LOCAL   LAMBDA l    damping (m), default 0.05
//           [GAIN k]    1/s, Cartesian error to velocity, default 20
//           [WEIGHTS w1..w6]  default 1 1 1 1 1 1
//           [VMAX v]    rad/s per joint, default 2
#include <chimera/module.hpp>

#include <memory>

#include "robotics/kinematics.hpp"
#include "robotics/ports.hpp"

namespace rb = chimera::robotics;

namespace {

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kDlsIkLocalKeys[] = {
    {"LAMBDA", chimera::LocalType::number, 0.0, chimera::unbounded, false, "damping of the least-squares inverse", "0.05"},
    {"GAIN", chimera::LocalType::number, 0.0, chimera::unbounded, false, "Cartesian error gain (1/s)", "20"},
    {"VMAX", chimera::LocalType::number, 0.0, chimera::unbounded, false, "joint speed limit (rad/s)", "2"},
    {"WEIGHTS", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "weight of each Cartesian axis (6)", "1"},
};

class DlsIk : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kDlsIkLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        const rb::RobotModel model = rb::read_model(t);
        n_ = model.ndof();
        const Eigen::VectorXd w = rb::local_vector(t, "WEIGHTS", 6, 1.0);
        const double lambda = rb::local_number(t, "LAMBDA", 0.05);
        if (!(lambda >= 0)) rb::module_error(t, "LOCAL LAMBDA must be >= 0");
        ik_ = std::make_unique<rb::DiffIk>(model, rb::Vector6d(w), lambda);
        gain_ = rb::local_number(t, "GAIN", 20.0);
        vmax_ = rb::local_number(t, "VMAX", 2.0);
        x_ref_ = rb::vec_port(t, "X_REF", 6);
        q_ref_ = rb::vec_port(t, "Q_REF", n_);
        qd_ref_ = rb::vec_port(t, "Q^_REF", n_);
        dq_.setZero(static_cast<Eigen::Index>(n_));
        return chimera::Result::OK;
    }

    chimera::Result on(chimera::Task&) override {
        // Until the first cycle, command no motion.
        Eigen::Map<Eigen::VectorXd>(qd_ref_, static_cast<Eigen::Index>(n_)).setZero();
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        const auto n = static_cast<Eigen::Index>(n_);
        const Eigen::Map<const Eigen::VectorXd> q(q_ref_, n);
        KDL::Frame now;
        if (!ik_->kinematics().fk(q, now)) return chimera::Result::ERROR;
        const KDL::Frame target = rb::pose_to_frame(Eigen::Map<const rb::Vector6d>(x_ref_));
        const rb::Vector6d e = gain_ * rb::pose_error(now, target);
        if (!ik_->solve_velocity(q, e, dq_)) {
            return t.error(1, "damped least squares failed (non-finite solution)");
        }
        Eigen::Map<Eigen::VectorXd>(qd_ref_, n) = dq_.cwiseMax(-vmax_).cwiseMin(vmax_);
        return chimera::Result::OK;
    }

private:
    std::size_t n_ = 0;
    std::unique_ptr<rb::DiffIk> ik_;
    double gain_ = 20, vmax_ = 2;
    const double* x_ref_ = nullptr;
    const double* q_ref_ = nullptr;
    double* qd_ref_ = nullptr;
    Eigen::VectorXd dq_;
};

}  // namespace

CHIMERA_MODULE(dlsik, DlsIk)
