// fwdkin — forward kinematics and Jacobian (thesis Figures 3.9, 3.15, 3.16),
// configured from the robot interface's NDOF and DH out-consts (§3.5). Port
// names are those of the thesis's fwdkin.rmod (Figure 3.12):
//
//   INCONST NDOF DH
//   INVAR   JPOS     joint positions (rad)
//   OUTVAR  XPOS     tool pose [x y z roll pitch yaw] (m, rad)
//           [J]      geometric Jacobian, 6 x NDOF, column-major (m/rad, rad/rad)
#include <chimera/module.hpp>

#include <memory>

#include "robotics/kinematics.hpp"
#include "robotics/ports.hpp"

namespace rb = chimera::robotics;

namespace {

class FwdKin : public chimera::Module {
public:
    chimera::Result init(chimera::Task& t) override {
        const rb::RobotModel model = rb::read_model(t);
        n_ = model.ndof();
        kin_ = std::make_unique<rb::Kinematics>(model);
        jpos_ = rb::vec_port(t, "JPOS", n_);
        xpos_ = rb::vec_port(t, "XPOS", 6);
        if (rb::has_out_var(t, "J")) jac_ = rb::vec_port(t, "J", 6 * n_);
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        const Eigen::Map<const Eigen::VectorXd> q(jpos_, static_cast<Eigen::Index>(n_));
        Eigen::Map<rb::Vector6d> x(xpos_);
        if (!kin_->fk(q, x)) {
            return t.error(1, "forward kinematics failed");
        }
        if (jac_) {
            Eigen::Map<rb::Matrix6Xd> j(jac_, 6, static_cast<Eigen::Index>(n_));
            kin_->jacobian(q, j);
        }
        return chimera::Result::OK;
    }

private:
    std::size_t n_ = 0;
    std::unique_ptr<rb::Kinematics> kin_;
    const double* jpos_ = nullptr;
    double* xpos_ = nullptr;
    double* jac_ = nullptr;
};

}  // namespace

CHIMERA_MODULE(fwdkin, FwdKin)
