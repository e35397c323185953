// teleop — teleoperation input module (thesis Figure 6.10, the jtball of
// Table 1): joint set-points from an operator in ANOTHER process, through a
// triple buffer (TBUF, §5.6; layout in teleop/feed.hpp), become the reference
// joint positions. The operator's process never blocks the controller and the
// controller never waits for the operator: each cycle takes the newest item.
//
//   INCONST NDOF
//   OUTVAR  Q_REF    reference joint positions (rad)
//   LOCAL   TBUF name           the operator feed, segment /chimera.tbuf.<name>
//           [MAXSPEED v...]     rad/s, 1 or NDOF values: Q_REF moves towards the
//                               operator's set-point at most this fast (default 1)
//           [MIN q...] [MAX q...]  rad, set-points are clamped into [MIN, MAX]
//           [TIMEOUT s]         operator silent this long while the arm is still
//                               moving towards the set-point: stop where it is
//                               and warn (deadman); 0 = never (default 0.5)
//
// On `on` the set-point is the current Q_REF (the out-var is read before `on`,
// §3.5), and items written before `on` are dropped: nothing moves until the
// operator sends a set-point.
#include <chimera/ipc/clock.hpp>
#include <chimera/module.hpp>

#include <cmath>
#include <cstring>

#include "robotics/ports.hpp"
#include "teleop/feed.hpp"

namespace rb = chimera::robotics;

namespace {

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kTeleopLocalKeys[] = {
    {"TBUF", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "the triple buffer the operator's device writes", ""},
    {"MAXSPEED", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "joint speed limit (rad/s)", "1"},
    {"MIN", chimera::LocalType::numbers, -chimera::unbounded, chimera::unbounded, false, "lower joint limit (rad)", "-1e300"},
    {"MAX", chimera::LocalType::numbers, -chimera::unbounded, chimera::unbounded, false, "upper joint limit (rad)", "1e300"},
    {"TIMEOUT", chimera::LocalType::number, 0.0, chimera::unbounded, false, "seconds without input before holding", "0.5"},
};

class Teleop : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kTeleopLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        n_ = rb::read_ndof(t);
        q_ref_ = rb::vec_port(t, "Q_REF", n_);
        const std::string name = rb::local_word(t, "TBUF", "");
        if (name.empty()) rb::module_error(t, "LOCAL TBUF (the operator feed's name) is missing");
        maxspeed_ = rb::local_vector(t, "MAXSPEED", n_, 1.0);
        if ((maxspeed_.array() <= 0).any()) rb::module_error(t, "LOCAL MAXSPEED must be > 0");
        lo_ = rb::local_vector(t, "MIN", n_, -1e300);
        hi_ = rb::local_vector(t, "MAX", n_, 1e300);
        if ((lo_.array() > hi_.array()).any()) rb::module_error(t, "LOCAL MIN exceeds MAX");
        const double timeout = rb::local_number(t, "TIMEOUT", 0.5);
        if (!(timeout >= 0)) rb::module_error(t, "LOCAL TIMEOUT must be >= 0");
        timeout_ns_ = static_cast<std::int64_t>(timeout * 1e9);
        try {
            feed_ = chimera::teleop::open_feed(name, n_);
        } catch (const std::exception& e) {
            rb::module_error(t, std::string("operator feed: ") + e.what());
        }
        target_.setZero(static_cast<Eigen::Index>(n_));
        return chimera::Result::OK;
    }

    chimera::Result on(chimera::Task&) override {
        target_ = Eigen::Map<const Eigen::VectorXd>(q_ref_, static_cast<Eigen::Index>(n_));
        chimera::tbuf::ReadResult r;
        feed_.read_view(r);  // drop what the operator sent before `on`
        last_item_ns_ = chimera::ipc::now_ns();
        silent_ = false;
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        const auto n = static_cast<Eigen::Index>(n_);
        Eigen::Map<Eigen::VectorXd> q_ref(q_ref_, n);
        chimera::tbuf::ReadResult r;
        const auto* item = static_cast<const double*>(feed_.read_view(r));
        const std::int64_t now = chimera::ipc::now_ns();
        if (r.status == chimera::tbuf::ReadStatus::fresh) {
            const Eigen::Map<const Eigen::VectorXd> q_op(item, n);
            if (q_op.allFinite()) {
                target_ = q_op.cwiseMax(lo_).cwiseMin(hi_);
                last_item_ns_ = now;
                silent_ = false;
            } else {
                t.warning("teleop: operator set-point is not a number; ignored");
            }
        } else if (timeout_ns_ > 0 && !silent_ && now - last_item_ns_ > timeout_ns_ && target_ != q_ref) {
            // Deadman: the operator stopped talking while the arm still moves.
            target_ = q_ref;
            silent_ = true;
            t.warning("teleop: operator feed silent, holding position");
        }
        // Rate limit; a joint within one step lands on the set-point exactly.
        const double dt = t.period();
        for (Eigen::Index j = 0; j < n; ++j) {
            const double step = dt * maxspeed_[j], d = target_[j] - q_ref[j];
            q_ref[j] = d > step ? q_ref[j] + step : d < -step ? q_ref[j] - step : target_[j];
        }
        return chimera::Result::OK;
    }

    chimera::Result kill(chimera::Task&) override {
        if (feed_.valid()) feed_.destroy();  // removed when the operator side has gone too
        return chimera::Result::OK;
    }

private:
    std::size_t n_ = 0;
    double* q_ref_ = nullptr;
    chimera::tbuf::Tbuf feed_;
    Eigen::VectorXd target_, maxspeed_, lo_, hi_;
    std::int64_t timeout_ns_ = 0, last_item_ns_ = 0;
    bool silent_ = false;
};

}  // namespace

CHIMERA_MODULE(teleop, Teleop)
