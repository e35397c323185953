// invdyn — inverse dynamics by recursive Newton-Euler (thesis Figure 3.13),
// configured from the NDOF and DH out-consts of the robot interface (§3.5):
//
//   tau = M(q) u + C(q, qd) qd + g(q)  (+ rotor inertia and viscous friction of the model)
//
//   INCONST NDOF DH
//   INVAR   Q_MEZ Q^_MEZ   joint positions (rad) and velocities (rad/s)
//           Q^^_U          commanded joint accelerations u (rad/s^2), e.g. the
//                          output x_u of the PID joint position computation
//   OUTVAR  T_REF          joint torques (N m)
// With SVARALIAS (Q_MEZ=Q_REF ...) the same code gives a feed-forward torque
// along a reference trajectory.
#include <chimera/module.hpp>

#include <memory>

#include "robotics/dynamics.hpp"
#include "robotics/ports.hpp"

namespace rb = chimera::robotics;

namespace {

class InvDyn : public chimera::Module {
public:
    chimera::Result init(chimera::Task& t) override {
        const rb::RobotModel model = rb::read_model(t);
        n_ = model.ndof();
        dyn_ = std::make_unique<rb::Dynamics>(model);
        q_ = rb::vec_port(t, "Q_MEZ", n_);
        qd_ = rb::vec_port(t, "Q^_MEZ", n_);
        u_ = rb::vec_port(t, "Q^^_U", n_);
        tau_ = rb::vec_port(t, "T_REF", n_);
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        const auto n = static_cast<Eigen::Index>(n_);
        using CMap = Eigen::Map<const Eigen::VectorXd>;
        Eigen::Map<Eigen::VectorXd> tau(tau_, n);
        if (!dyn_->inverse(CMap(q_, n), CMap(qd_, n), CMap(u_, n), tau)) {
            return t.error(1, "inverse dynamics failed");
        }
        return chimera::Result::OK;
    }

private:
    std::size_t n_ = 0;
    std::unique_ptr<rb::Dynamics> dyn_;
    const double *q_ = nullptr, *qd_ = nullptr, *u_ = nullptr;
    double* tau_ = nullptr;
};

}  // namespace

CHIMERA_MODULE(invdyn, InvDyn)
