// pidacc — the PID joint position computation object of the computed-torque
// controller (thesis §3.8.1, Figure 3.13). Combined with invdyn in one task
// (Subsystem::spawn_combined), its output x_u = Q^^_U stays in the task's local
// table and is never copied to the global one.
//
//   u = qdd_ref + KP (q_ref - q_mez) + KD (qd_ref - qd_mez) + KI * integral   (rad/s^2)
//
//   INCONST NDOF
//   INVAR   Q_REF Q^_REF [Q^^_REF] Q_MEZ Q^_MEZ
//   OUTVAR  Q^^_U
//   LOCAL   KP [KI] [KD] [ILIMIT] [ULIMIT]  (1/s^2, 1/s^3, 1/s, rad s, rad/s^2)
#include <chimera/module.hpp>

#include <optional>

#include "robotics/pid.hpp"
#include "robotics/ports.hpp"

namespace rb = chimera::robotics;

namespace {

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kPidAccLocalKeys[] = {
    {"KP", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "proportional gain per joint (1/s^2)", ""},
    {"KI", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "integral gain per joint", "0"},
    {"KD", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "derivative gain per joint (1/s)", "0"},
    {"ILIMIT", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "integrator clamp per joint", "0"},
    {"ULIMIT", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "acceleration clamp per joint", "1e9"},
};

class PidAcc : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kPidAccLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        n_ = rb::read_ndof(t);
        try {
            pid_.emplace(n_, rb::PidGains{rb::local_vector(t, "KP", n_), rb::local_vector(t, "KI", n_, 0.0),
                                          rb::local_vector(t, "KD", n_, 0.0),
                                          rb::local_vector(t, "ILIMIT", n_, 0.0),
                                          rb::local_vector(t, "ULIMIT", n_, 1e9)});
        } catch (const std::invalid_argument& e) {
            rb::module_error(t, e.what());
        }
        q_ref_ = rb::vec_port(t, "Q_REF", n_);
        qd_ref_ = rb::vec_port(t, "Q^_REF", n_);
        if (rb::has_in_var(t, "Q^^_REF")) qdd_ref_ = rb::vec_port(t, "Q^^_REF", n_);
        q_mez_ = rb::vec_port(t, "Q_MEZ", n_);
        qd_mez_ = rb::vec_port(t, "Q^_MEZ", n_);
        u_ = rb::vec_port(t, "Q^^_U", n_);
        zero_.setZero(static_cast<Eigen::Index>(n_));
        return chimera::Result::OK;
    }

    chimera::Result on(chimera::Task&) override {
        pid_->reset();
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        const auto n = static_cast<Eigen::Index>(n_);
        using CMap = Eigen::Map<const Eigen::VectorXd>;
        Eigen::Map<Eigen::VectorXd> u(u_, n);
        if (qdd_ref_) {
            pid_->update(CMap(q_ref_, n), CMap(qd_ref_, n), CMap(q_mez_, n), CMap(qd_mez_, n),
                         CMap(qdd_ref_, n), t.period(), u);
        } else {
            pid_->update(CMap(q_ref_, n), CMap(qd_ref_, n), CMap(q_mez_, n), CMap(qd_mez_, n), zero_,
                         t.period(), u);
        }
        return chimera::Result::OK;
    }

private:
    std::size_t n_ = 0;
    std::optional<rb::Pid> pid_;
    const double *q_ref_ = nullptr, *qd_ref_ = nullptr, *qdd_ref_ = nullptr;
    const double *q_mez_ = nullptr, *qd_mez_ = nullptr;
    double* u_ = nullptr;
    Eigen::VectorXd zero_;
};

}  // namespace

CHIMERA_MODULE(pidacc, PidAcc)
