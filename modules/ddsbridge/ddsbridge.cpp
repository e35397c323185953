// ddsbridge — inter-subsystem communication (thesis §5.6) across machines over
// DDS, readable by ROS 2: a port-based object that publishes its in-variables
// and subscribes its out-variables, so a subsystem gets remote data exactly as
// it gets local data (README.md of this folder).
//
//   INVAR   the variables published (double arrays)
//   OUTVAR  the variables subscribed (double arrays)
//   LOCAL   DOMAIN CONFIG AGE_CLOCK NOTIFY JOINT_NAMES JOINT_SUBSET UNNAMED, TOPIC_<port> per port,
//           STAMP_/VLIMIT_/TRATE_<port> where wanted (bridge_config.hpp)
//
// The cycle only copies in-vars into their TBUFs and the newest received
// values out of theirs, and checks each one's age: no network, no allocation,
// no system call (the clocks are read through the vDSO). DDS lives on the
// bridge's own thread (dds_link.hpp).
#include <chimera/cfg.hpp>
#include <chimera/ipc/clock.hpp>
#include <chimera/module.hpp>

#include <pthread.h>
#include <sched.h>

#include <algorithm>
#include <cstring>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "bridge_config.hpp"
#include "dds_link.hpp"

namespace ddsbridge {
namespace {

constexpr chimera::LocalKey kKeys[] = {
    {"DOMAIN", chimera::LocalType::integer, 0, 232, false, "DDS domain id", "0"},
    {"CONFIG", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false,
     "Cyclone DDS XML configuration file (network interface, discovery, lease)", ""},
    {"AGE_CLOCK", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false,
     "receive | source: a received value's age since its arrival here, or since the sender's stamp", "receive"},
    {"NOTIFY", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false,
     "poll | spin | wake: the bridge thread looks when the task's write is due, keeps looking from just before "
     "it is due, or is woken by the task (one system call)", "poll"},
    {"JOINT_NAMES", chimera::LocalType::text, -chimera::unbounded, chimera::unbounded, false,
     "the joints' names in JointState.name: published, and matched on receipt", "joint1 .. jointN"},
    {"JOINT_SUBSET", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false,
     "update | refuse: a received JointState naming some joints updates those, or is refused and counted", "update"},
    {"UNNAMED", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false,
     "refuse | positional: a received JointState without names is refused and counted, or taken by position",
     "refuse"},
    {"VLIMIT_*", chimera::LocalType::numbers, 0.0, chimera::unbounded, false,
     "VLIMIT_<port> per joint (or one for all): a subscribed JointState.position changes at most this much per "
     "second, a JointState.velocity is clamped to it", ""},
    {"TRATE_*", chimera::LocalType::numbers, 0.0, chimera::unbounded, false,
     "TRATE_<port> per joint (or one for all), N m/s: a subscribed JointState.effort changes at most this much "
     "per second", ""},
    {"STAMP_*", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false,
     "STAMP_<port> OUTVAR: 3 doubles per cycle: counter, age (s), 1 new | 0 repeat | -1 stale", ""},
    {"TOPIC_*", chimera::LocalType::text, -chimera::unbounded, chimera::unbounded, false,
     "TOPIC_<port> TOPIC pub|sub MESSAGE state|command [AGE_LIMIT warn|zero|illegal|error]", ""},
};

// The CPUs this (the task's) thread may run on, as a mask of the first 64; 0 if unknown.
std::uint64_t task_cpus() noexcept {
    cpu_set_t cpus;
    if (pthread_getaffinity_np(pthread_self(), sizeof cpus, &cpus) != 0) return 0;
    std::uint64_t mask = 0;
    for (int c = 0; c < 64; ++c)
        if (CPU_ISSET(c, &cpus)) mask |= std::uint64_t{1} << c;
    return mask;
}

std::int64_t realtime_ns() noexcept {
    timespec ts{};
    clock_gettime(CLOCK_REALTIME, &ts);  // vDSO
    return static_cast<std::int64_t>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec;
}

// A subscribed port as the cycle sees it.
struct Sub {
    std::size_t link_index = 0;
    double* var = nullptr;
    double* stamp = nullptr;  // STAMP_<port>: counter, age, new/repeat/stale
    std::size_t nelem = 0;
    std::int64_t age_limit_ns = 0;
    StaleAction action = StaleAction::warn;
    bool stale = false;
    std::string stale_text, fresh_text;  // made in init: no formatting in the cycle
    // For `get STATUS`:
    std::uint64_t counter = 0;
    std::int64_t age_ns = -1;
    bool fresh = false;  // this cycle's read found a new value
    // VLIMIT_/TRATE_: what the cycle writes to the table, limited; counted.
    JointLimiter limiter;
    bool limit_from_zero = false;  // TRATE_: a torque ramps up from zero after on()
    std::uint64_t clamped = 0;     // joint values clamped, since spawn
};

struct Pub {
    std::size_t link_index = 0;
    const double* var = nullptr;
};

class DdsBridge : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kKeys; }

    chimera::Result init(chimera::Task& t) override {
        try {
            config_ = parse_config(t.rmod_file());
            std::vector<Port> ports;
            for (const TopicSpec& spec : config_.topics) ports.push_back(port_of(t, spec));
            link_ = std::make_unique<Link>(config_, std::move(ports));
        } catch (const std::exception& e) {
            throw std::invalid_argument(std::string(t.rmod()) + ".rmod: " + e.what());
        }
        for (std::size_t i = 0; i < link_->size(); ++i) {
            const Port& p = link_->port(i);
            if (p.spec.direction == Direction::pub) {
                pubs_.push_back({i, t.translate<double>(p.spec.port)});
                continue;
            }
            Sub s;
            s.link_index = i;
            s.var = t.translate<double>(p.spec.port);
            if (!p.spec.stamp_port.empty()) s.stamp = stamp_port(t, p.spec);
            s.nelem = p.nelem;
            s.age_limit_ns = static_cast<std::int64_t>(p.spec.age_limit * 1e9);
            s.action = p.spec.stale;
            if (std::vector<double> limits = limits_for(p.spec, p.nelem, t.rmod_file().local.file); !limits.empty()) {
                const bool magnitude = p.spec.message == Message::joint_velocity;
                s.limiter = JointLimiter(magnitude ? JointLimiter::Kind::magnitude : JointLimiter::Kind::rate,
                                         std::move(limits));
                s.limit_from_zero = p.spec.message == Message::joint_effort;
            }
            s.stale_text = p.spec.port + " from " + p.spec.dds_topic() + ": stale (no value newer than " +
                           chimera::cfg::number_text(p.spec.age_limit) + " s; " + to_string(p.spec.stale) + ")";
            s.fresh_text = p.spec.port + " from " + p.spec.dds_topic() + ": fresh values again";
            subs_.push_back(std::move(s));
        }
        return chimera::Result::OK;
    }

    chimera::Result on(chimera::Task& t) override {
        on_ns_ = chimera::ipc::now_ns();
        for (Sub& s : subs_) {
            s.stale = false;
            start_limiter(s, t.period());
        }
        raised_illegal_ = false;
        link_->set_period_ns(static_cast<std::int64_t>(t.period() * 1e9));
        link_->set_task_cpus(task_cpus());
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        const std::int64_t now = chimera::ipc::now_ns();
        for (const Pub& p : pubs_) (void)link_->buffer(p.link_index).write(p.var, now);
        if (!pubs_.empty() && config_.notify == Notify::wake) link_->notify();
        bool ok = true;
        aborted_ = false;
        for (Sub& s : subs_) {
            tell_refusals(t, s);
            ok = take(t, s, now) && ok;
            if (aborted_) break;  // t.error() aborted the cycle: return at once (module.hpp)
        }
        return ok ? chimera::Result::OK : chimera::Result::ERROR;
    }

    chimera::Result off(chimera::Task& t) override {
        link_->set_period_ns(0);
        link_->set_task_cpus(0);
        if (raised_illegal_) t.set_illegal_configuration(false);
        raised_illegal_ = false;
        return chimera::Result::OK;
    }

    chimera::Result kill(chimera::Task&) override {
        link_.reset();
        return chimera::Result::OK;
    }

    // get STATUS: per subscribed port, "PORT counter C age S stale yes|no received N rejected R
    // length L unnamed U unknown K duplicate D partial P reordered O held H clamped X" (rejected: all refused
    // samples; then by reason; held: JointStates waiting for a joint's first value; clamped: joint
    // values a limit changed); then "published N" (samples of all published ports).
    chimera::Result get(chimera::Task& t) override {
        if (t.arg() != "STATUS") return chimera::Result::OK;
        std::string text;
        for (const Sub& s : subs_) {
            const SubCounts& c = link_->counts(s.link_index);
            text += link_->port(s.link_index).spec.port + " counter " + std::to_string(s.counter) + " age " +
                    (s.age_ns < 0 ? std::string("none") : chimera::cfg::number_text(1e-9 * static_cast<double>(s.age_ns))) +
                    " stale " + (s.stale ? "yes" : "no") + " received " + std::to_string(c.received.load()) +
                    " rejected " + std::to_string(c.rejected.load());
            for (std::size_t r = 1; r < kRefusals; ++r)
                text += std::string(" ") + to_string(static_cast<Refusal>(r)) + " " + std::to_string(c.refused[r].load());
            text += " held " + std::to_string(c.held.load()) + " clamped " + std::to_string(s.clamped) + "\n";
        }
        text += "published " + std::to_string(link_->published());
        t.reply(text);
        return chimera::Result::OK;
    }

private:
    Port port_of(chimera::Task& t, const TopicSpec& spec) {
        Port p;
        p.spec = spec;
        p.global_name = t.global_name(spec.port);
        const chimera::svar::VarInfo info = t.local_table().global().var(p.global_name);
        if (info.type() != chimera::svar::Type::double_)
            throw std::invalid_argument(t.rmod_file().local.file + ":" + std::to_string(spec.line) + ": TOPIC_" +
                                        spec.port + ": " + p.global_name + " is not a double variable (the bridge "
                                        "carries float64 arrays)");
        p.nelem = info.nelem();
        if (spec.message != Message::state_var)
            p.joint_names = joint_names_for(config_, spec, p.nelem, t.rmod_file().local.file);
        return p;
    }

    double* stamp_port(chimera::Task& t, const TopicSpec& spec) {
        const std::string name = t.global_name(spec.stamp_port);
        const chimera::svar::VarInfo info = t.local_table().global().var(name);
        if (info.type() != chimera::svar::Type::double_ || info.nelem() != 3)
            throw std::invalid_argument(t.rmod_file().local.file + ": STAMP_" + spec.port + ": " + name +
                                        " must be a double variable of 3 elements (counter, age, new/repeat/stale)");
        return t.translate<double>(spec.stamp_port);
    }

    // The newest value of a subscription into its port, or the stale action.
    // Not noexcept: an err handler the user installed may throw (err.hpp).
    bool take(chimera::Task& t, Sub& s, std::int64_t now) {
        const bool ok = take_value(t, s, now);
        if (s.stamp) {
            s.stamp[0] = static_cast<double>(s.counter);
            s.stamp[1] = s.age_ns < 0 ? -1.0 : 1e-9 * static_cast<double>(s.age_ns);
            s.stamp[2] = s.stale ? -1.0 : (s.fresh ? 1.0 : 0.0);
        }
        return ok;
    }

    bool take_value(chimera::Task& t, Sub& s, std::int64_t now) {
        chimera::tbuf::ReadResult r;
        const auto* item = static_cast<const std::byte*>(link_->buffer(s.link_index).read_view(r));
        s.fresh = r.status == chimera::tbuf::ReadStatus::fresh;
        std::int64_t age;
        if (r.status == chimera::tbuf::ReadStatus::fresh || r.status == chimera::tbuf::ReadStatus::reused) {
            ReceivedHeader head;
            std::memcpy(&head, item, sizeof head);
            s.counter = head.counter;
            age = config_.age_clock == AgeClock::receive ? now - r.time_ns : realtime_ns() - head.source_ns;
            // A value that arrived after this cycle's release (`now`), or a
            // sender's clock ahead of ours, is as new as can be: age 0, not a
            // negative age that would read as "none" (-1).
            age = std::max<std::int64_t>(age, 0);
            s.age_ns = age;
            if (age <= s.age_limit_ns) {
                const auto* values = reinterpret_cast<const double*>(item + sizeof head);
                if (s.limiter.kind() == JointLimiter::Kind::none)
                    std::memcpy(s.var, values, s.nelem * sizeof(double));
                else
                    s.clamped += s.limiter.apply(values, s.var);
                if (s.stale) recover(t, s);
                return true;
            }
        } else {
            age = now - on_ns_;  // nothing received since on: stale once the limit has passed
            if (age <= s.age_limit_ns) return true;
        }
        if (!s.stale) {
            s.stale = true;
            if (s.action == StaleAction::error) {
                // The task goes to ERROR, naming the port; continued by a handler, the cycle still fails.
                if (t.error(chimera::err::code::timeout, s.stale_text) != chimera::Result::CONTINUE) aborted_ = true;
                return false;
            }
            t.warning(s.stale_text);
            if (s.action == StaleAction::illegal && !t.illegal_configuration()) {
                t.set_illegal_configuration(true);
                raised_illegal_ = true;
            }
        }
        if (s.action == StaleAction::zero) {
            // The safe value at once, not ramped; a limit ramps on from it.
            std::memset(s.var, 0, s.nelem * sizeof(double));
            s.limiter.start_from(s.var);
        }
        return s.action != StaleAction::error;
    }

    // After on(): a torque-rate limit ramps the first command up from zero
    // torque (what the robot had before a command came); a velocity limit on
    // positions takes the first position as it comes (ramping from zero
    // would command a move to zero).
    static void start_limiter(Sub& s, double period) noexcept {
        s.limiter.set_period(period);
        if (s.limit_from_zero) {
            s.limiter.start_from_zero();
        } else {
            s.limiter.start_afresh();
        }
    }

    // The listener's refusals as warnings, each text made on the listener's
    // thread (naming the port, topic and publisher): the cycle only hands it on.
    void tell_refusals(chimera::Task& t, const Sub& s) noexcept {
        for (std::size_t r = 1; r < kRefusals; ++r) {
            const auto reason = static_cast<Refusal>(r);
            if (const char* text = link_->pending_notice(s.link_index, reason)) {
                t.warning(text);
                link_->notice_told(s.link_index, reason);
            }
        }
    }

    void recover(chimera::Task& t, Sub& s) noexcept {
        s.stale = false;
        t.warning(s.fresh_text);
        if (!raised_illegal_) return;
        for (const Sub& o : subs_)
            if (o.stale && o.action == StaleAction::illegal) return;  // another one still stale
        t.set_illegal_configuration(false);
        raised_illegal_ = false;
    }

    BridgeConfig config_;
    std::unique_ptr<Link> link_;
    std::vector<Pub> pubs_;
    std::vector<Sub> subs_;
    std::int64_t on_ns_ = 0;
    bool raised_illegal_ = false;
    bool aborted_ = false;  // this cycle's t.error() aborted it
};

}  // namespace
}  // namespace ddsbridge

CHIMERA_MODULE(ddsbridge, ddsbridge::DdsBridge)
