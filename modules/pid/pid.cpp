// pid — PID joint position controller (thesis Figure 3.7), configured from the
// NDOF in-const; gains, limits and anti-windup in LOCAL.
//
//   INCONST NDOF
//   INVAR   Q_REF Q^_REF Q_MEZ Q^_MEZ [T_GRAV]   rad, rad/s, N m (optional feed-forward)
//   OUTVAR  T_REF                                 N m
//   [INVAR  STAMP]                                a ddsbridge stamp of Q_MEZ (3 doubles)
//   LOCAL   KP KI KD ILIMIT ULIMIT  (1 value for all joints or NDOF values)
//           [STALE hold|run] [SLEW]  hold: while Q_MEZ is stale (by STAMP) or the
//                            configuration is illegal (the robot interface
//                            holds the arm), hold the last good T_REF and
//                            freeze the integral; on the first cycle after,
//                            reset the integral and slew T_REF from the held
//                            value to the PID's at SLEW N m/s (issue #29.6;
//                            default run: neither is looked at)
#include <chimera/module.hpp>

#include <limits>
#include <optional>

#include "robotics/pid.hpp"
#include "robotics/ports.hpp"
#include "robotics/stale.hpp"

namespace rb = chimera::robotics;

namespace {

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kPidModuleLocalKeys[] = {
    {"KP", chimera::LocalType::numbers, 0.0, chimera::unbounded, true, "proportional gain, one per joint (or one for all)", ""},
    {"KI", chimera::LocalType::numbers, 0.0, chimera::unbounded, true, "integral gain per joint", ""},
    {"KD", chimera::LocalType::numbers, 0.0, chimera::unbounded, true, "derivative gain per joint", ""},
    {"ILIMIT", chimera::LocalType::numbers, 0.0, chimera::unbounded, true, "integrator clamp per joint", ""},
    {"ULIMIT", chimera::LocalType::numbers, 0.0, chimera::unbounded, true, "output clamp per joint", ""},
    {"STALE", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "hold | run: what stale measurements (in-var STAMP) and an illegal configuration do", "run"},
    {"SLEW", chimera::LocalType::numbers, 0.0, chimera::unbounded, true, "after a hold: T_REF slew rate per joint (N m/s; none: no limit)", ""},
};

class PidModule : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kPidModuleLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        n_ = rb::read_ndof(t);
        try {
            pid_.emplace(rb::Pid(n_, gains(t)), slew(t));
        } catch (const std::invalid_argument& e) {
            rb::module_error(t, e.what());
        }
        const std::string stale = rb::local_word(t, "STALE", "run");
        if (stale != "hold" && stale != "run") rb::module_error(t, "LOCAL STALE '" + stale + "': expected hold or run");
        hold_ = stale == "hold";
        if (hold_ && rb::has_in_var(t, "STAMP")) stamp_ = rb::vec_port(t, "STAMP", 3);
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
        pid_->reset();  // no integral, hold or slew carried over from an earlier run
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        const auto n = static_cast<Eigen::Index>(n_);
        using CMap = Eigen::Map<const Eigen::VectorXd>;
        Eigen::Map<Eigen::VectorXd> u(t_ref_, n);
        const bool stale = hold_ && rb::must_hold(stamp_, t.illegal_configuration());  // STALE run: never
        if (t_grav_) {
            pid_->update(stale, CMap(q_ref_, n), CMap(qd_ref_, n), CMap(q_mez_, n), CMap(qd_mez_, n),
                         CMap(t_grav_, n), t.period(), u);
        } else {
            pid_->update(stale, CMap(q_ref_, n), CMap(qd_ref_, n), CMap(q_mez_, n), CMap(qd_mez_, n), zero_,
                         t.period(), u);
        }
        return chimera::Result::OK;
    }

    chimera::Result set(chimera::Task& t) override {
        // sbsSet of a gain or limit: the LOCAL entry is already updated; rebuild
        // the gains between cycles. A bad value leaves the old gains in place.
        return rb::apply_local(t, [&] { pid_.emplace(rb::Pid(n_, gains(t)), slew(t)); });
    }

private:
    rb::PidGains gains(const chimera::Task& t) const {
        return rb::PidGains{rb::local_vector(t, "KP", n_), rb::local_vector(t, "KI", n_, 0.0),
                            rb::local_vector(t, "KD", n_, 0.0), rb::local_vector(t, "ILIMIT", n_, 0.0),
                            rb::local_vector(t, "ULIMIT", n_, 1e9)};
    }

    Eigen::VectorXd slew(const chimera::Task& t) const {
        return rb::local_vector(t, "SLEW", n_, std::numeric_limits<double>::infinity());
    }

    std::size_t n_ = 0;
    std::optional<rb::StaleHoldPid> pid_;
    bool hold_ = false;              // STALE hold
    const double* stamp_ = nullptr;  // STALE hold with STAMP: the bridge's stamp of Q_MEZ
    double *q_ref_ = nullptr, *qd_ref_ = nullptr, *q_mez_ = nullptr, *qd_mez_ = nullptr;
    double *t_grav_ = nullptr, *t_ref_ = nullptr;
    Eigen::VectorXd zero_;
};

}  // namespace

CHIMERA_MODULE(pid, PidModule)
