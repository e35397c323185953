// pid — PID joint position controller (thesis Figure 3.7), configured from the
// NDOF in-const; gains, limits and anti-windup in LOCAL.
//
//   INCONST NDOF
//   INVAR   Q_REF Q^_REF Q_MEZ Q^_MEZ [T_GRAV]   rad, rad/s, N m (optional feed-forward)
//   OUTVAR  T_REF                                 N m
//   LOCAL   KP KI KD ILIMIT ULIMIT  (1 value for all joints or NDOF values)
#include <chimera/module.hpp>

#include <optional>

#include "robotics/pid.hpp"
#include "robotics/ports.hpp"

namespace rb = chimera::robotics;

namespace {

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kPidModuleLocalKeys[] = {
    {"KP", chimera::LocalType::numbers, 0.0, chimera::unbounded, true, "proportional gain, one per joint (or one for all)", ""},
    {"KI", chimera::LocalType::numbers, 0.0, chimera::unbounded, true, "integral gain per joint", ""},
    {"KD", chimera::LocalType::numbers, 0.0, chimera::unbounded, true, "derivative gain per joint", ""},
    {"ILIMIT", chimera::LocalType::numbers, 0.0, chimera::unbounded, true, "integrator clamp per joint", ""},
    {"ULIMIT", chimera::LocalType::numbers, 0.0, chimera::unbounded, true, "output clamp per joint", ""},
};

class PidModule : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kPidModuleLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        n_ = rb::read_ndof(t);
        try {
            pid_.emplace(n_, gains(t));
        } catch (const std::invalid_argument& e) {
            rb::module_error(t, e.what());
        }
        q_ref_ = rb::vec_port(t, "Q_REF", n_);
        qd_ref_ = rb::vec_port(t, "Q^_REF", n_);
        q_mez_ = rb::vec_port(t, "Q_MEZ", n_);
        qd_mez_ = rb::vec_port(t, "Q^_MEZ", n_);
        if (rb::has_in_var(t, "T_GRAV")) t_grav_ = rb::vec_port(t, "T_GRAV", n_);
        t_ref_ = rb::vec_port(t, "T_REF", n_);
        zero_.setZero(static_cast<Eigen::Index>(n_));
        return chimera::Result::OK;
    }

    chimera::Result on(chimera::Task&) override {
        pid_->reset();  // no integral carried over from an earlier run
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        const auto n = static_cast<Eigen::Index>(n_);
        using CMap = Eigen::Map<const Eigen::VectorXd>;
        Eigen::Map<Eigen::VectorXd> u(t_ref_, n);
        if (t_grav_) {
            pid_->update(CMap(q_ref_, n), CMap(qd_ref_, n), CMap(q_mez_, n), CMap(qd_mez_, n),
                         CMap(t_grav_, n), t.period(), u);
        } else {
            pid_->update(CMap(q_ref_, n), CMap(qd_ref_, n), CMap(q_mez_, n), CMap(qd_mez_, n), zero_,
                         t.period(), u);
        }
        return chimera::Result::OK;
    }

    chimera::Result set(chimera::Task& t) override {
        // sbsSet of a gain or limit: the LOCAL entry is already updated; rebuild
        // the gains between cycles. A bad value leaves the old gains in place.
        return rb::apply_local(t, [&] { pid_ = rb::Pid(n_, gains(t)); });
    }

private:
    rb::PidGains gains(const chimera::Task& t) const {
        return rb::PidGains{rb::local_vector(t, "KP", n_), rb::local_vector(t, "KI", n_, 0.0),
                            rb::local_vector(t, "KD", n_, 0.0), rb::local_vector(t, "ILIMIT", n_, 0.0),
                            rb::local_vector(t, "ULIMIT", n_, 1e9)};
    }

    std::size_t n_ = 0;
    std::optional<rb::Pid> pid_;
    double *q_ref_ = nullptr, *qd_ref_ = nullptr, *q_mez_ = nullptr, *qd_mez_ = nullptr;
    double *t_grav_ = nullptr, *t_ref_ = nullptr;
    Eigen::VectorXd zero_;
};

}  // namespace

CHIMERA_MODULE(pid, PidModule)
