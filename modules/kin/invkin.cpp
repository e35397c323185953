// invkin — inverse kinematics by Newton iteration with the pseudo-inverse
// (thesis Figure 3.15): the desired tool pose becomes reference joint positions.
//
//   INCONST NDOF DH
//   INVAR   X_REF    desired tool pose [x y z roll pitch yaw] (m, rad)
//   OUTVAR  Q_REF    reference joint positions (rad)
//   LOCAL   [WEIGHTS w1..w6]  task components that count (default 1 1 1 1 1 1)
//           [ITER n] (default 20)  [TOL e] (default 1e-9)
//           [MAXSTEP rad]  largest joint change per cycle (default 0.05)
//
// Newton starts from the current Q_REF each cycle — on `on` that is the value
// read from the global table (§3.5), so it continues from whatever the
// previous controller commanded. When the pose is unreachable it keeps the
// last solution and counts a warning.
#include <chimera/module.hpp>

#include <memory>

#include "robotics/kinematics.hpp"
#include "robotics/ports.hpp"

namespace rb = chimera::robotics;

namespace {

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kInvKinLocalKeys[] = {
    {"ITER", chimera::LocalType::integer, 1.0, 10000.0, false, "Newton iterations per cycle", "20"},
    {"TOL", chimera::LocalType::number, 0.0, chimera::unbounded, false, "convergence tolerance", "1e-9"},
    {"MAXSTEP", chimera::LocalType::number, 0.0, chimera::unbounded, false, "largest joint step per iteration (rad)", "0.05"},
    {"WEIGHTS", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "weight of each Cartesian axis (6)", "1"},
};

class InvKin : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kInvKinLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        const rb::RobotModel model = rb::read_model(t);
        n_ = model.ndof();
        const Eigen::VectorXd w = rb::local_vector(t, "WEIGHTS", 6, 1.0);
        ik_ = std::make_unique<rb::DiffIk>(model, rb::Vector6d(w), 0.0);
        iter_ = static_cast<int>(rb::local_number(t, "ITER", 20));
        tol_ = rb::local_number(t, "TOL", 1e-9);
        maxstep_ = rb::local_number(t, "MAXSTEP", 0.05);
        x_ref_ = rb::vec_port(t, "X_REF", 6);
        q_ref_ = rb::vec_port(t, "Q_REF", n_);
        q_.setZero(static_cast<Eigen::Index>(n_));
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        const auto n = static_cast<Eigen::Index>(n_);
        Eigen::Map<Eigen::VectorXd> q_ref(q_ref_, n);
        q_ = q_ref;
        const KDL::Frame target = rb::pose_to_frame(Eigen::Map<const rb::Vector6d>(x_ref_));
        if (ik_->solve_position(q_, target, iter_, tol_) < 0) {
            if (!failing_) t.warning("invkin: desired pose not reached (unreachable or singular)");
            failing_ = true;
            return chimera::Result::OK;  // keep the last solution
        }
        failing_ = false;
        // Rate limit: a far target is approached over several cycles.
        q_ref += (q_ - q_ref).cwiseMax(-maxstep_).cwiseMin(maxstep_);
        return chimera::Result::OK;
    }

private:
    std::size_t n_ = 0;
    std::unique_ptr<rb::DiffIk> ik_;
    int iter_ = 20;
    double tol_ = 1e-9, maxstep_ = 0.05;
    bool failing_ = false;
    const double* x_ref_ = nullptr;
    double* q_ref_ = nullptr;
    Eigen::VectorXd q_;
};

}  // namespace

CHIMERA_MODULE(invkin, InvKin)
