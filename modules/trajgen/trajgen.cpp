// trajgen — trajectory generator, joint or Cartesian (thesis Figures 3.7, 3.14):
// linear, parabolic-blend (LSPB) or quintic profiles through via points.
// Generic ports configured with SVARALIAS (Z=Q_REF for joints, Z=X_REF for a
// Cartesian pose [x y z roll pitch yaw]):
//
//   [INCONST NDOF]   joint space: Z has NDOF elements; without it, the size of Z
//   OUTVAR  Z [Z^] [Z^^]   position, velocity, acceleration
//   LOCAL   PROFILE linear | lspb | quintic     (default quintic)
//           [BLEND f]        LSPB blend fraction of each segment, (0, 0.5], default 0.2
//           [CYCLIC yes|no]  repeat the via points (default yes)
//           [START current|first]  on `on`, start from the current value of Z
//                            (read on `on`, §3.5) or jump to the first POINT
//                            (default current)
//           POINT1 seconds v1 .. vn   via points POINT1, POINT2, ... (numbered,
//                            because LOCAL keys are unique; at least POINT1, no
//                            gaps); `seconds` is the time to reach it from
//                            the previous one (for the first: from the start;
//                            when cyclic, the return from the last POINT to the
//                            first takes the first POINT's time too)
//           [STALE hold|run] with the in-var Z_MEZ (the measured position) and
//                            the optional STAMP (a ddsbridge stamp, 3 doubles,
//                            of the measurements the controller uses): hold
//                            stops the trajectory's clock while the stamp says
//                            stale or the configuration is illegal and, on the
//                            first cycle after, re-anchors it at Z_MEZ
//                            (default run: neither is looked at)
// When not cyclic it sends sig::FINISH once the last point is reached and keeps
// holding it.
//
// STALE hold (issue #29.6): while the measurements are stale or the
// configuration is illegal the arm is held by the robot interface, so a
// trajectory that ran on would be seconds ahead of the arm when they return,
// and the controller would drive it there at its torque limits. Instead the
// reference stops, at the held arm (Z = Z_MEZ, Z^ and Z^^ zero): a controller
// that restarts before this task's next cycle (the PID runs faster) finds no
// error to jump on. On recovery the segment that was under way is planned
// again, with its full duration, from where the arm was measured to the via
// point it was heading for; then the trajectory goes on from there.
#include <chimera/module.hpp>

#include <memory>
#include <vector>

#include "robotics/ports.hpp"
#include "robotics/stale.hpp"
#include "robotics/trajectory.hpp"

namespace rb = chimera::robotics;

namespace {

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kTrajGenLocalKeys[] = {
    {"PROFILE", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "quintic | cubic | linear", "quintic"},
    {"BLEND", chimera::LocalType::number, 0.0, chimera::unbounded, false, "blend time between segments (s)", "0.2"},
    {"CYCLIC", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "yes | no: start over after the last point", "yes"},
    {"START", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "current | first point", "current"},
    {"STALE", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "hold | run: what stale measurements (in-var STAMP) and an illegal configuration do", "run"},
    {"POINT*", chimera::LocalType::numbers, -chimera::unbounded, chimera::unbounded, false, "POINTn DURATION q1 ... qN: a via point", ""},
};

class TrajGen : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kTrajGenLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        n_ = rb::has_in_const(t, "NDOF") ? rb::read_ndof(t) : rb::port_nelem(t, "Z");
        z_ = rb::vec_port(t, "Z", n_);
        if (rb::has_out_var(t, "Z^")) zd_ = rb::vec_port(t, "Z^", n_);
        if (rb::has_out_var(t, "Z^^")) zdd_ = rb::vec_port(t, "Z^^", n_);
        rb::Profile profile{};
        const std::string pname = rb::local_word(t, "PROFILE", "quintic");
        if (!rb::parse_profile(pname, profile)) {
            rb::module_error(t, "LOCAL PROFILE '" + pname + "': expected linear, lspb or quintic");
        }
        cyclic_ = rb::local_word(t, "CYCLIC", "yes") == "yes";
        start_current_ = rb::local_word(t, "START", "current") == "current";
        // Via points: the start (filled in on `on`) then every POINT line.
        std::vector<Eigen::VectorXd> points{Eigen::VectorXd::Zero(static_cast<Eigen::Index>(n_))};
        std::vector<double> durations;
        for (const auto& e : t.local().entries()) {
            if (e.key.rfind("POINT", 0) != 0) continue;
            if (e.key != "POINT" + std::to_string(durations.size() + 1)) {
                rb::module_error(t, "line " + std::to_string(e.line) + ": LOCAL " + e.key +
                                        " out of order: expected POINT" + std::to_string(durations.size() + 1) +
                                        " (via points are POINT1, POINT2, ... in order)");
            }
            if (e.values.size() != n_ + 1) {
                rb::module_error(t, "line " + std::to_string(e.line) + ": POINT takes a duration and " +
                                        std::to_string(n_) + " values, found " +
                                        std::to_string(e.values.size()) + " values in all");
            }
            Eigen::VectorXd p(static_cast<Eigen::Index>(n_));
            double dur = 0;
            for (std::size_t i = 0; i <= n_; ++i) {
                const auto v = chimera::cfg::parse_double(e.values[i]);
                if (!v) rb::module_error(t, "line " + std::to_string(e.line) + ": '" + e.values[i] + "' is not a number");
                if (i == 0) dur = *v; else p[static_cast<Eigen::Index>(i - 1)] = *v;
            }
            points.push_back(p);
            durations.push_back(dur);
        }
        if (durations.empty()) rb::module_error(t, "LOCAL needs at least one via point (POINT1)");
        first_ = points[1];
        if (cyclic_) {
            // Cyclic: the start is only the approach; the cycle runs over the POINTs.
            approach_ = durations.front();
            std::vector<Eigen::VectorXd> loop(points.begin() + 1, points.end());
            std::vector<double> loop_d(durations.begin() + 1, durations.end());
            if (loop.size() > 1) loop_d.push_back(durations.front());  // last -> first
            try {
                approach_traj_ = std::make_unique<rb::Trajectory>(n_, std::vector<Eigen::VectorXd>{points[0], points[1]},
                                                                  std::vector<double>{durations.front()}, profile, false,
                                                                  rb::local_number(t, "BLEND", 0.2));
                traj_ = std::make_unique<rb::Trajectory>(n_, loop, loop_d, profile, loop.size() > 1,
                                                         rb::local_number(t, "BLEND", 0.2));
            } catch (const std::invalid_argument& ex) {
                rb::module_error(t, ex.what());
            }
        } else {
            try {
                traj_ = std::make_unique<rb::Trajectory>(n_, points, durations, profile, false,
                                                         rb::local_number(t, "BLEND", 0.2));
            } catch (const std::invalid_argument& ex) {
                rb::module_error(t, ex.what());
            }
        }
        p_.setZero(static_cast<Eigen::Index>(n_));
        v_ = p_;
        a_ = p_;
        target_ = p_;
        init_stale_hold(t, profile);
        return chimera::Result::OK;
    }

    chimera::Result on(chimera::Task&) override {
        const auto n = static_cast<Eigen::Index>(n_);
        const Eigen::VectorXd start =
            start_current_ ? Eigen::VectorXd(Eigen::Map<const Eigen::VectorXd>(z_, n)) : first_;
        if (approach_traj_) approach_traj_->set_start(start); else traj_->set_start(start);
        time_ = 0;
        finished_ = false;
        detour_ = false;
        watch_.reset();
        evaluate();
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        switch (watch_.update(hold_ && rb::must_hold(stamp_, t.illegal_configuration()))) {
            case rb::Freshness::stale: hold_still(); return chimera::Result::OK;
            case rb::Freshness::recovered: reanchor(); break;
            case rb::Freshness::fresh: advance(t.period()); break;
        }
        evaluate();
        if (!cyclic_ && !finished_ && !detour_ && time_ >= traj_->total_time()) {
            finished_ = true;
            t.send_signal(chimera::sig::FINISH);
        }
        return chimera::Result::OK;
    }

private:
    // STALE hold needs the measured position (the stamp is optional); the re-anchored
    // segment is allocated here, once, and re-aimed in the cycle.
    void init_stale_hold(chimera::Task& t, rb::Profile profile) {
        const std::string stale = rb::local_word(t, "STALE", "run");
        if (stale != "hold" && stale != "run") rb::module_error(t, "LOCAL STALE '" + stale + "': expected hold or run");
        if (stale == "run") return;
        if (!rb::has_in_var(t, "Z_MEZ"))
            rb::module_error(t, "LOCAL STALE hold needs the in-var Z_MEZ (the measured position, to restart from)");
        hold_ = true;
        if (rb::has_in_var(t, "STAMP")) stamp_ = rb::vec_port(t, "STAMP", 3);
        z_mez_ = rb::vec_port(t, "Z_MEZ", n_);
        reanchored_ = std::make_unique<rb::Trajectory>(n_, std::vector<Eigen::VectorXd>{p_, p_}, std::vector<double>{1.0},
                                                       profile, false, rb::local_number(t, "BLEND", 0.2));
    }

    // The plan's time moves on, through the re-anchored segment first if one is under way.
    void advance(double dt) noexcept {
        if (!detour_) {
            time_ += dt;
            return;
        }
        detour_time_ += dt;
        if (detour_time_ < reanchored_->total_time()) return;
        time_ += detour_time_ - reanchored_->total_time();  // back on the plan, at the via point
        detour_ = false;
    }

    // Held: the reference is the held arm, at rest. Not the trajectory's last
    // point: the arm lags it, and a PID restarting on that error would jump.
    void hold_still() noexcept {
        const auto n = static_cast<Eigen::Index>(n_);
        Eigen::Map<Eigen::VectorXd>(z_, n) = Eigen::Map<const Eigen::VectorXd>(z_mez_, n);
        if (zd_) Eigen::Map<Eigen::VectorXd>(zd_, n).setZero();
        if (zdd_) Eigen::Map<Eigen::VectorXd>(zdd_, n).setZero();
    }

    // Fresh again: the segment under way is planned anew, from the measured
    // position to its via point, with its whole duration; the plan resumes there.
    void reanchor() noexcept {
        const auto n = static_cast<Eigen::Index>(n_);
        // A re-anchored segment still under way is replaced: time_ is already its via point's.
        const rb::Trajectory::Span span = detour_ ? rb::Trajectory::Span{time_ - reanchored_->total_time(), time_}
                                                  : plan_segment_at(time_);
        if (!(span.end > span.start)) {  // a finished trajectory: nothing under way
            detour_ = false;
            return;
        }
        plan_evaluate(span.end, target_, v_, a_);
        reanchored_->set_point(0, Eigen::Map<const Eigen::VectorXd>(z_mez_, n));
        reanchored_->set_point(1, target_);
        reanchored_->set_duration(0, span.end - span.start);
        time_ = span.end;
        detour_ = true;
        detour_time_ = 0;
    }

    // The plan: the approach (cyclic) then the via points.
    rb::Trajectory::Span plan_segment_at(double t) const noexcept {
        if (approach_traj_ && t < approach_) return {0, approach_};
        if (!approach_traj_) return traj_->segment_at(t);
        const rb::Trajectory::Span s = traj_->segment_at(t - approach_);
        return {s.start + approach_, s.end + approach_};
    }

    void plan_evaluate(double t, Eigen::VectorXd& p, Eigen::VectorXd& v, Eigen::VectorXd& a) const noexcept {
        if (approach_traj_ && t < approach_) {
            approach_traj_->evaluate(t, p, v, a);
        } else if (approach_traj_) {
            traj_->evaluate(t - approach_, p, v, a);
        } else {
            traj_->evaluate(t, p, v, a);
        }
    }

    void evaluate() noexcept {
        const auto n = static_cast<Eigen::Index>(n_);
        if (detour_) {
            reanchored_->evaluate(detour_time_, p_, v_, a_);
        } else {
            plan_evaluate(time_, p_, v_, a_);
        }
        Eigen::Map<Eigen::VectorXd>(z_, n) = p_;
        if (zd_) Eigen::Map<Eigen::VectorXd>(zd_, n) = v_;
        if (zdd_) Eigen::Map<Eigen::VectorXd>(zdd_, n) = a_;
    }

    std::size_t n_ = 0;
    double *z_ = nullptr, *zd_ = nullptr, *zdd_ = nullptr;
    bool cyclic_ = true, start_current_ = true, finished_ = false;
    double time_ = 0, approach_ = 0;
    Eigen::VectorXd first_, p_, v_, a_, target_;
    std::unique_ptr<rb::Trajectory> traj_, approach_traj_;
    // STALE hold (hold_ false: run on regardless; nullptr stamp_: the flag only).
    bool hold_ = false;
    const double* stamp_ = nullptr;
    const double* z_mez_ = nullptr;
    rb::StaleWatch watch_;
    std::unique_ptr<rb::Trajectory> reanchored_;
    bool detour_ = false;       // the re-anchored segment is under way
    double detour_time_ = 0;    // since it began
};

}  // namespace

CHIMERA_MODULE(trajgen, TrajGen)
