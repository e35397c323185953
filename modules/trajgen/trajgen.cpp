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
// When not cyclic it sends sig::FINISH once the last point is reached and keeps
// holding it.
#include <chimera/module.hpp>

#include <memory>
#include <vector>

#include "robotics/ports.hpp"
#include "robotics/trajectory.hpp"

namespace rb = chimera::robotics;

namespace {

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kTrajGenLocalKeys[] = {
    {"PROFILE", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "quintic | cubic | linear", "quintic"},
    {"BLEND", chimera::LocalType::number, 0.0, chimera::unbounded, false, "blend time between segments (s)", "0.2"},
    {"CYCLIC", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "yes | no: start over after the last point", "yes"},
    {"START", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "current | first point", "current"},
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
        return chimera::Result::OK;
    }

    chimera::Result on(chimera::Task&) override {
        const auto n = static_cast<Eigen::Index>(n_);
        const Eigen::VectorXd start =
            start_current_ ? Eigen::VectorXd(Eigen::Map<const Eigen::VectorXd>(z_, n)) : first_;
        if (approach_traj_) approach_traj_->set_start(start); else traj_->set_start(start);
        time_ = 0;
        finished_ = false;
        evaluate();
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        time_ += t.period();
        evaluate();
        if (!cyclic_ && !finished_ && time_ >= traj_->total_time()) {
            finished_ = true;
            t.send_signal(chimera::sig::FINISH);
        }
        return chimera::Result::OK;
    }

private:
    void evaluate() noexcept {
        const auto n = static_cast<Eigen::Index>(n_);
        if (approach_traj_ && time_ < approach_) {
            approach_traj_->evaluate(time_, p_, v_, a_);
        } else if (approach_traj_) {
            traj_->evaluate(time_ - approach_, p_, v_, a_);
        } else {
            traj_->evaluate(time_, p_, v_, a_);
        }
        Eigen::Map<Eigen::VectorXd>(z_, n) = p_;
        if (zd_) Eigen::Map<Eigen::VectorXd>(zd_, n) = v_;
        if (zdd_) Eigen::Map<Eigen::VectorXd>(zdd_, n) = a_;
    }

    std::size_t n_ = 0;
    double *z_ = nullptr, *zd_ = nullptr, *zdd_ = nullptr;
    bool cyclic_ = true, start_current_ = true, finished_ = false;
    double time_ = 0, approach_ = 0;
    Eigen::VectorXd first_, p_, v_, a_;
    std::unique_ptr<rb::Trajectory> traj_, approach_traj_;
};

}  // namespace

CHIMERA_MODULE(trajgen, TrajGen)
