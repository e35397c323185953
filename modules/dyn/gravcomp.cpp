// gravcomp — gravity compensation (thesis Figure 6.10, grav_comp): the joint
// torques that hold the arm still at the measured position, g(q), from the
// NDOF and DH out-consts of the robot interface (§3.5).
//
//   INCONST NDOF DH
//   INVAR   Q_MEZ    joint positions (rad)
//   OUTVAR  T_GRAV   joint torques (N m)
//   LOCAL   [SCALE s]  multiplies g(q) (e.g. 0 to switch compensation off), default 1
#include <chimera/module.hpp>

#include <memory>

#include "robotics/dynamics.hpp"
#include "robotics/ports.hpp"

namespace rb = chimera::robotics;

namespace {

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kGravCompLocalKeys[] = {
    {"SCALE", chimera::LocalType::number, 0.0, 10.0, true, "fraction of the gravity torque fed forward", "1"},
};

class GravComp : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kGravCompLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        const rb::RobotModel model = rb::read_model(t);
        n_ = model.ndof();
        dyn_ = std::make_unique<rb::Dynamics>(model);
        q_ = rb::vec_port(t, "Q_MEZ", n_);
        tg_ = rb::vec_port(t, "T_GRAV", n_);
        scale_ = rb::local_number(t, "SCALE", 1.0);
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        const auto n = static_cast<Eigen::Index>(n_);
        Eigen::Map<Eigen::VectorXd> tg(tg_, n);
        if (!dyn_->gravity(Eigen::Map<const Eigen::VectorXd>(q_, n), tg)) {
            return t.error(1, "gravity computation failed");
        }
        tg *= scale_;
        return chimera::Result::OK;
    }

    chimera::Result set(chimera::Task& t) override {
        scale_ = t.local().number("SCALE", 1.0);
        return chimera::Result::OK;
    }

private:
    std::size_t n_ = 0;
    std::unique_ptr<rb::Dynamics> dyn_;
    const double* q_ = nullptr;
    double* tg_ = nullptr;
    double scale_ = 1;
};

}  // namespace

CHIMERA_MODULE(gravcomp, GravComp)
