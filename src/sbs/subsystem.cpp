// The subsystem master (§4.2–4.5): init, spawn, control, reconfig, status,
// signals, finish; configuration verification (§3.3.1).
#include "internal.hpp"

#include "chimera/ipc/clock.hpp"
#include "chimera/ipc/futex.hpp"
#include "chimera/ipc/segment.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <map>
#include <sched.h>
#include <pthread.h>
#include <sstream>
#include <thread>

namespace chimera::sbs {

namespace {

bool valid_in(State s, Control c) {
    switch (c) {
        case Control::on: return s == State::OFF;
        case Control::off: return s == State::ON;
        case Control::kill: return s != State::NOT_CREATED;
        case Control::clear: return s == State::ERROR;
    }
    return false;
}

std::string why_refused(State s, Control c) {
    switch (c) {
        case Control::on:
            return s == State::ON ? "it is already ON" : s == State::ERROR ? "it is in ERROR (clear it first)" : "it is NOT-CREATED";
        case Control::off:
            return s == State::OFF ? "it is already OFF" : s == State::ERROR ? "it is in ERROR (clear or kill it)" : "it is NOT-CREATED";
        case Control::kill: return "it is NOT-CREATED";
        case Control::clear:
            return s == State::NOT_CREATED ? "it is NOT-CREATED" : "it is not in ERROR (state " + std::string(to_string(s)) + ")";
    }
    return "";
}

detail::CmdKind kind_of(Control c) {
    switch (c) {
        case Control::on: return detail::CmdKind::on;
        case Control::off: return detail::CmdKind::off;
        case Control::kill: return detail::CmdKind::kill;
        case Control::clear: return detail::CmdKind::clear;
    }
    return detail::CmdKind::none;
}

}  // namespace

std::string_view to_string(Control c) noexcept {
    switch (c) {
        case Control::on: return "on";
        case Control::off: return "off";
        case Control::kill: return "kill";
        case Control::clear: return "clear";
    }
    return "?";
}

// ------------------------------------------------------------------ SubsystemCore

namespace detail {

SubsystemCore::SubsystemCore(SbsFile f) : file(std::move(f)) {
    check_rtpu_cpus(file);
    const std::string seg = ipc::segment_name(file.subsystem, "svar");
    // A name squatted by another user (a fake header naming a live pid) is
    // no running subsystem: root replaces it, anyone else is told whose it is.
    for (const std::string& name : {seg, ipc::segment_name(file.subsystem, "status")})
        if (const std::string why = ipc::squatted(name); !why.empty()) ipc::make_way(name, why);
    if (ipc::Segment::exists(seg)) {
        if (!ipc::Segment::is_stale(seg))
            throw Error("subsystem " + file.subsystem + " is already running (segment " + seg +
                        " exists and its creator process is alive); finish it first");
        // A crashed run left it: its creator is gone, so nobody can be using it as master.
        ipc::make_way(seg, "left by a process that died");
    }
    // The table and the status segment: the watch group reads them (chimtop,
    // a non-owner's queries); everything else stays owner-only (docs/permissions.md).
    svar::TableOptions to;
    to.segment.mode = 0640;
    table = svar::Table::create(seg, file.svarfile, to);
    prof::StatusOptions so;
    so.rtpus = static_cast<std::uint32_t>(std::max<std::size_t>(1, file.rtpus.size()));
    for (const auto& r : file.rtpus) {  // chimtop and `status` name RTPUs as the .sbs does
        so.rtpu_names.push_back(r.name);
        so.rtpu_cpus.push_back(r.cpu);
    }
    try {
        status = prof::StatusSegment::create(file.subsystem, kMaxTasks, so);
        for (std::size_t i = 0; i < file.rtpus.size(); ++i)
            if (file.rtpus[i].half_tick)
                status.set_accounting(static_cast<int>(i), prof::Accounting::half_tick,
                                      static_cast<std::int64_t>(std::llround(file.rtpus[i].tick * 1e9)));
    } catch (...) {
        table.destroy();  // nothing half-built is left behind
        throw;
    }
    reporter = std::thread([this] { report_loop(); });
}

muf::RtpuScheduler& SubsystemCore::scheduler(const RtpuSpec& rtpu) {
    std::lock_guard<std::mutex> lock(schedulers_mu);
    if (schedulers.size() < file.rtpus.size()) schedulers.resize(file.rtpus.size());
    auto& s = schedulers[static_cast<std::size_t>(rtpu_index(rtpu))];
    if (s) return *s;
    muf::RtpuOptions o;
    o.name = rtpu.name;
    o.cpu = rtpu.cpu;
    switch (rtpu.scheduler) {
        case Scheduler::RM: o.policy = muf::Policy::rm; break;
        case Scheduler::EDF: o.policy = muf::Policy::edf; break;
        case Scheduler::MUF: o.policy = muf::Policy::muf; break;
    }
    switch (rtpu.backend) {
        case Backend::fifo: o.backend = muf::Backend::fifo; break;
        case Backend::deadline: o.backend = muf::Backend::deadline; break;
        case Backend::other: o.backend = muf::Backend::other; break;
    }
    o.quiet = true;  // the subsystem says it once (warn_no_privilege)
    try {
        s = std::make_unique<muf::RtpuScheduler>(o);
    } catch (const muf::SchedError& e) {
        throw Error(file.path + ":" + std::to_string(rtpu.line) + ": RTPU " + rtpu.name + ": " + e.what());
    }
    if (!s->privileged())
        warn_no_privilege("the scheduler of RTPU " + rtpu.name + " may not use SCHED_FIFO");
    return *s;
}

void SubsystemCore::warn_no_privilege(const std::string& why) noexcept {
    if (rt_warned.exchange(true)) return;
    std::fprintf(stderr,
                 "chimera: subsystem %s: no real-time privilege (%s); its tasks run best effort under "
                 "SCHED_OTHER, timing failures are still detected, and status shows each task's policy\n",
                 file.subsystem.c_str(), why.c_str());
}

int SubsystemCore::rtpu_index(const RtpuSpec& rtpu) const noexcept {
    for (std::size_t i = 0; i < file.rtpus.size(); ++i)
        if (file.rtpus[i].name == rtpu.name) return static_cast<int>(i);
    return 0;
}

SubsystemCore::~SubsystemCore() {
    reporter_stop.store(true);
    report_bell.ring();
    if (reporter.joinable()) reporter.join();
}

TaskCore* SubsystemCore::task(TaskId id) const {
    std::lock_guard<ipc::PiMutex> lock(tasks_mu);
    if (id.value < 0 || static_cast<std::size_t>(id.value) >= tasks.size() || !tasks[id.value])
        throw Error("subsystem " + file.subsystem + ": no task with id " + std::to_string(id.value));
    return tasks[id.value].get();
}

void SubsystemCore::post_signal(TaskCore& from, int signal) noexcept {
    if (signal < 0 || signal >= sig::COUNT) return;
    const std::uint32_t bit = sig::bit(signal);
    from.signals_sent.fetch_or(bit, std::memory_order_relaxed);
    const std::uint32_t mask = from.own_sigmask.load() ? from.sigmask.load() : wide_mask.load();
    if (!(mask & bit)) return;  // masked: ignored and discarded (§4.5.3)
    if (!signal_queue.push(Pending{signal, from.id})) {
        signals_dropped.fetch_add(1, std::memory_order_relaxed);
        return;
    }
    signal_bell.ring();
}

void SubsystemCore::set_flag(std::uint32_t bit, bool on) noexcept {
    std::lock_guard<ipc::PiMutex> lock(flag_mu);
    std::uint32_t f = table.illegal_configuration();
    f = on ? (f | bit) : (f & ~bit);
    table.set_illegal_configuration(f);
}

// A peer in ERROR is a process outside the master that died (an observer, a
// logger): the real-time tasks lose nothing unless one that is ON reads what
// it produced, so only then is the configuration illegal (and the robot
// interface holds). Any other task halted in ERROR makes it illegal (§3.10).
void SubsystemCore::refresh_error_flag() noexcept {
    const auto read_by_an_on_task = [this](const TaskCore& peer) {
        for (const auto& o : tasks) {
            if (!o || o.get() == &peer || o->state.load() != State::ON) continue;
            for (const auto& v : o->in_vars)
                if (std::find(peer.out_vars.begin(), peer.out_vars.end(), v) != peer.out_vars.end()) return true;
        }
        return false;
    };
    bool any = false;
    {
        std::lock_guard<ipc::PiMutex> lock(tasks_mu);
        for (const auto& t : tasks)
            if (t && t->state.load() == State::ERROR && (!t->peer || read_by_an_on_task(*t))) any = true;
    }
    set_flag(kIllegalError, any);
}

void SubsystemCore::print(const RtpuSpec& r, bool is_error, std::initializer_list<std::string_view> parts) noexcept {
    if (r.errprint == ErrPrint::none) return;
    if (!is_error && r.errprint != ErrPrint::warnings) return;
    Report rep;
    std::size_t n = 0, whole = 0;
    for (std::string_view p : parts) {  // cut to the slot: a line never allocates
        n += p.copy(rep.text + n, sizeof rep.text - 1 - n);
        whole += p.size();
    }
    if (whole > n) {  // cut: the line says so at its end
        const std::size_t keep = sizeof rep.text - 1 - err::kCutMark.size();
        n = keep + err::kCutMark.copy(rep.text + keep, err::kCutMark.size());
    }
    rep.text[n] = '\0';
    if (!reports.push(rep)) {
        reports_dropped.fetch_add(1, std::memory_order_relaxed);
        return;
    }
    report_bell.ring();
}

void SubsystemCore::drain_reports() noexcept {
    Report rep;
    while (reports.pop(rep)) std::fprintf(stderr, "%s\n", rep.text);
    if (const std::uint64_t lost = reports_dropped.exchange(0); lost != 0)
        std::fprintf(stderr, "chimera: subsystem %s: %llu error/warning lines dropped (the queue was full)\n",
                     file.subsystem.c_str(), static_cast<unsigned long long>(lost));
}

// The reporter thread: SCHED_OTHER whatever the master runs at, so printing
// never competes with the tasks.
void SubsystemCore::report_loop() noexcept {
    sched_param sp{};
    pthread_setschedparam(pthread_self(), SCHED_OTHER, &sp);
    pthread_setname_np(pthread_self(), "chimera-report");
    for (;;) {
        const std::uint32_t seen = report_bell.read();
        drain_reports();
        if (reporter_stop.load()) return;
        report_bell.wait(seen);
    }
}

}  // namespace detail

// ------------------------------------------------------------------ Subsystem

Subsystem::Subsystem(std::unique_ptr<detail::SubsystemCore> core) : core_(std::move(core)) {}

std::unique_ptr<Subsystem> Subsystem::init(const std::string& sbs_path) { return init(read_sbs(sbs_path)); }

std::unique_ptr<Subsystem> Subsystem::init(SbsFile file) {
    return std::make_unique<Subsystem>(std::make_unique<detail::SubsystemCore>(std::move(file)));
}

Subsystem::~Subsystem() {
    try {
        finish();
    } catch (...) {
    }
}

const SbsFile& Subsystem::file() const noexcept { return core_->file; }
const std::string& Subsystem::name() const noexcept { return core_->file.subsystem; }
void Subsystem::add_module_path(std::string dir) { core_->module_dirs.push_back(std::move(dir)); }

std::string Subsystem::load_module(const std::string& path) {
    std::string name = detail::load_module_file(path);
    const std::string dir = std::filesystem::absolute(path).parent_path().string();
    auto& dirs = core_->module_dirs;
    if (std::find(dirs.begin(), dirs.end(), dir) == dirs.end()) dirs.push_back(dir);
    return name;
}

TaskId Subsystem::spawn(const std::string& rmod_path, std::string_view rtpu) {
    return spawn_combined({rmod_path}, rtpu);
}

TaskId Subsystem::spawn_combined(const std::vector<std::string>& rmod_paths, std::string_view rtpu_name) {
    auto& c = *core_;
    if (c.finished) throw Error("subsystem " + c.file.subsystem + " is finished");
    std::vector<RmodFile> rmods;
    for (const auto& p : rmod_paths) {
        std::string path = p;
        // A bare name is also looked up beside the .sbs file.
        if (!std::filesystem::exists(path)) {
            const auto beside = std::filesystem::path(c.file.path).parent_path() / p;
            if (std::filesystem::exists(beside)) path = beside.string();
        }
        try {
            rmods.push_back(read_rmod(path));
        } catch (const cfg::ParseError& e) {
            throw Error(std::string("spawn: ") + e.what());
        }
    }
    return spawn_parsed(std::move(rmods), rtpu_name);
}

TaskId Subsystem::spawn_parsed(std::vector<RmodFile> rmods, std::string_view rtpu_name) {
    auto& c = *core_;
    if (c.finished) throw Error("subsystem " + c.file.subsystem + " is finished");
    if (rmods.empty()) throw Error("spawn: no .rmod given");
    const std::string rname = rtpu_name.empty() ? c.file.master : std::string(rtpu_name);
    const RtpuSpec* rtpu = c.file.find_rtpu(rname);
    if (!rtpu) throw Error("spawn: RTPU '" + rname + "' is not in " + c.file.path);

    // §3.5: a task's in-consts must already have been written by the task
    // producing them, so producers are spawned first. A constant the .svar
    // gives an INIT (NDOF 6) has its value from the configuration: no
    // producing task is needed (issue #16.3: no dummy robot for a chain).
    std::vector<std::string> produced_here;
    for (const auto& f : rmods)
        for (const auto& v : f.global_out_consts()) produced_here.push_back(v);
    for (const auto& f : rmods) {
        for (const auto& v : f.global_in_consts()) {
            if (std::find(produced_here.begin(), produced_here.end(), v) != produced_here.end()) continue;
            bool found = false;
            std::lock_guard<ipc::PiMutex> lock(c.tasks_mu);
            for (const auto& t : c.tasks) {
                if (!t || t->state.load() == State::NOT_CREATED) continue;
                if (std::find(t->out_consts.begin(), t->out_consts.end(), v) != t->out_consts.end()) found = true;
            }
            if (const auto ix = c.table.find(v); !found && ix && c.table.var(*ix).has_init()) found = true;
            if (!found)
                throw VerifyError("spawn " + f.name + ": in-const " + v + " of module " + f.module +
                                  " is produced by no task and has no INIT in the .svar (spawn the task whose "
                                  "OUTCONST is " + v + " first, or give it an INIT)");
        }
    }

    int id;
    {
        std::lock_guard<ipc::PiMutex> lock(c.tasks_mu);
        id = static_cast<int>(c.tasks.size());
    }
    auto task = std::make_unique<detail::TaskCore>(c, id, *rtpu, std::move(rmods));
    detail::TaskCore* t = task.get();
    t->scheduler = &c.scheduler(*rtpu);  // the RTPU's, made with its first task

    // Out-const values before the new task writes them: a change means the
    // tasks reading them must re-initialise (§3.5, reinit).
    std::vector<std::pair<std::size_t, std::vector<std::byte>>> before;
    for (const auto& v : t->out_consts) {
        const std::size_t ix = c.table.index_of(v);
        std::vector<std::byte> buf(c.table.var(ix).bytes());
        if (!svar::transferred(c.table.read(ix, buf.data()))) buf.clear();  // unknown: counted as changed
        before.emplace_back(ix, std::move(buf));
    }
    {
        std::lock_guard<ipc::PiMutex> lock(c.tasks_mu);
        c.tasks.push_back(std::move(task));
    }
    t->start();  // throws on init failure; the task stays in the list as NOT-CREATED

    std::vector<std::string> changed;
    for (auto& [ix, old] : before) {
        std::vector<std::byte> now(old.size());
        const bool read = !old.empty() && svar::transferred(c.table.read(ix, now.data()));
        if (!read || now != old) changed.emplace_back(c.table.var(ix).name());
    }
    if (!changed.empty()) {
        std::vector<detail::TaskCore*> readers;
        {
            std::lock_guard<ipc::PiMutex> lock(c.tasks_mu);
            for (const auto& o : c.tasks) {
                if (!o || o.get() == t) continue;
                const State s = o->state.load();
                if (s != State::OFF && s != State::ON) continue;
                for (const auto& v : changed)
                    if (std::find(o->in_consts.begin(), o->in_consts.end(), v) != o->in_consts.end()) {
                        readers.push_back(o.get());
                        break;
                    }
            }
        }
        std::string failures;
        for (auto* r : readers) {
            const std::string res = r->request(detail::CmdKind::reinit);
            if (!res.empty()) failures += (failures.empty() ? "" : "; ") + r->name + ": " + res;
        }
        if (!failures.empty())
            throw Error("spawn " + t->name + ": the task is OFF, but re-initialising the tasks reading its out-consts "
                        "failed: " + failures);
    }
    return TaskId{id};
}

std::optional<TaskId> Subsystem::find(std::string_view rmod) const {
    std::lock_guard<ipc::PiMutex> lock(core_->tasks_mu);
    std::optional<TaskId> dead;
    for (std::size_t i = core_->tasks.size(); i-- > 0;) {
        const auto& t = core_->tasks[i];
        if (!t || t->name != rmod) continue;
        if (t->state.load() != State::NOT_CREATED) return TaskId{static_cast<int>(i)};
        if (!dead) dead = TaskId{static_cast<int>(i)};
    }
    return dead;
}

namespace {

// §3.3.1: (1) no variable has two producers; (2) every input has a producer.
// Every violation, two-producer ones first, in task order: verify() throws
// the first, the web console's port graph marks them all.
std::vector<VerifyProblem> problems_of(const std::vector<detail::TaskCore*>& set) {
    std::vector<VerifyProblem> out;
    std::map<std::string, std::string> producer;
    for (auto* t : set) {
        for (const auto& v : t->out_vars) {
            auto [it, fresh] = producer.emplace(v, t->name);
            if (!fresh)
                out.push_back({VerifyProblem::Kind::two_producers, v, {it->second, t->name},
                               "illegal configuration: variable " + v + " is produced by both " + it->second +
                                   " and " + t->name});
        }
    }
    for (auto* t : set) {
        for (const auto& v : t->in_vars) {
            if (!producer.count(v))
                out.push_back({VerifyProblem::Kind::no_producer, v, {t->name},
                               "illegal configuration: variable " + v + " read by " + t->name +
                                   " is produced by no module in the configuration"});
        }
    }
    return out;
}

void verify_set(const std::vector<detail::TaskCore*>& set) {
    const auto problems = problems_of(set);
    if (!problems.empty()) throw VerifyError(problems.front().message);
}

}  // namespace

void Subsystem::verify(std::span<const TaskId> ids) const {
    std::vector<detail::TaskCore*> set;
    for (TaskId id : ids) set.push_back(core_->task(id));
    verify_set(set);
}

std::vector<VerifyProblem> Subsystem::verification_problems(std::span<const TaskId> ids) const {
    std::vector<detail::TaskCore*> set;
    for (TaskId id : ids) set.push_back(core_->task(id));
    return problems_of(set);
}

void Subsystem::control(TaskId id, Control signal, std::string_view a) {
    auto& c = *core_;
    detail::TaskCore* t = c.task(id);
    const State s = t->state.load();
    if (!valid_in(s, signal))
        throw Refused(std::string(to_string(signal)) + " refused for task " + t->name + ": " + why_refused(s, signal));
    if (signal == Control::on) {
        // Turning one task on must not give a variable a second producer.
        std::lock_guard<ipc::PiMutex> lock(c.tasks_mu);
        for (const auto& o : c.tasks) {
            if (!o || o.get() == t || o->state.load() != State::ON) continue;
            for (const auto& v : t->out_vars)
                if (std::find(o->out_vars.begin(), o->out_vars.end(), v) != o->out_vars.end())
                    throw VerifyError("on " + t->name + " refused: variable " + v + " is already produced by " +
                                      o->name + ", which is ON");
        }
    }
    const std::string res = t->request(kind_of(signal), std::string(a));
    if (signal == Control::kill && t->state.load() == State::NOT_CREATED) t->join();
    if (res.rfind("refused:", 0) == 0) throw Refused(std::string(to_string(signal)) + " " + t->name + " " + res);
    if (!res.empty()) throw Error(std::string(to_string(signal)) + " " + t->name + ": " + res);
}

namespace {

// The tasks ON once `items` would be applied, in creation order; throws
// Error for an item naming no task (the message and `bad_item` say which).
std::vector<detail::TaskCore*> on_after(detail::SubsystemCore& c, std::span<const ReconfigItem> items,
                                        std::size_t& bad_item) {
    std::map<detail::TaskCore*, State> after;
    std::vector<detail::TaskCore*> order;
    {
        std::lock_guard<ipc::PiMutex> lock(c.tasks_mu);
        for (const auto& t : c.tasks)
            if (t) {
                after[t.get()] = t->state.load();
                order.push_back(t.get());
            }
    }
    for (std::size_t i = 0; i < items.size(); ++i) {
        detail::TaskCore* t = nullptr;
        try {
            t = c.task(items[i].task);
        } catch (const Error& e) {
            bad_item = i;
            throw Error("item " + std::to_string(i) + ": " + e.what());
        }
        State& s = after[t];
        switch (items[i].signal) {
            case Control::on: if (s == State::OFF) s = State::ON; break;
            case Control::off: if (s == State::ON) s = State::OFF; break;
            case Control::kill: s = State::NOT_CREATED; break;
            case Control::clear: if (s == State::ERROR) s = State::OFF; break;
        }
    }
    std::vector<detail::TaskCore*> on_set;
    for (auto* t : order)
        if (after[t] == State::ON) on_set.push_back(t);
    return on_set;
}

// §3.10: the illegal-configuration flag is for a reconfiguration that takes
// longer than a single cycle. One done within a period of the fastest
// periodic task ON before or after it loses no cycle, so it raises nothing: a
// critical task would otherwise fall back to locally stable execution, and a
// trajectory with STALE hold restart its segment, at every controller swap.
std::int64_t reconfig_grace_ns(detail::SubsystemCore& c, const std::vector<detail::TaskCore*>& on_after_set) {
    std::int64_t grace = 0;
    const auto shorter = [&grace](const detail::TaskCore& t) {
        const std::int64_t p = t.period_ns.load();
        if (t.type == TaskType::periodic && p > 0 && (grace == 0 || p < grace)) grace = p;
    };
    {
        std::lock_guard<ipc::PiMutex> lock(c.tasks_mu);
        for (const auto& t : c.tasks)
            if (t && t->state.load() == State::ON) shorter(*t);
    }
    for (const auto* t : on_after_set) shorter(*t);
    return grace;
}

// Raises the flag once the grace has passed with the reconfiguration still
// under way, from a thread of its own at the dispatchers' priority (the master
// is waiting for a task then, and may be SCHED_OTHER); lowers it at the end.
class LateReconfigFlag {
public:
    LateReconfigFlag(detail::SubsystemCore& c, std::int64_t grace_ns) : c_(c) {
        if (grace_ns <= 0) {  // no periodic task, no cycle to wait for: raised at once, as ever
            c_.set_flag(detail::SubsystemCore::kIllegalReconfig, true);
            state_.store(kRaised);
            return;
        }
        const std::int64_t deadline = ipc::now_ns() + grace_ns;
        raiser_ = std::thread([this, deadline] { wait_then_raise(deadline); });
    }
    ~LateReconfigFlag() {
        std::uint32_t running = kRunning;
        if (state_.compare_exchange_strong(running, kDone)) ipc::futex_wake_all(state_, ipc::FutexScope::process);
        if (raiser_.joinable()) raiser_.join();
        if (state_.load() == kRaised) c_.set_flag(detail::SubsystemCore::kIllegalReconfig, false);
    }
    LateReconfigFlag(const LateReconfigFlag&) = delete;
    LateReconfigFlag& operator=(const LateReconfigFlag&) = delete;

private:
    static constexpr std::uint32_t kRunning = 0, kDone = 1, kRaised = 2;

    void wait_then_raise(std::int64_t deadline) noexcept {
        pthread_setname_np(pthread_self(), "chimera-reconfig");
        sched_param sp{};
        sp.sched_priority = muf::RtpuOptions{}.fifo_high;
        pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp);  // refused without privilege: late, not lost
        while (state_.load() == kRunning && ipc::now_ns() < deadline)
            ipc::futex_wait_until(state_, kRunning, deadline, ipc::FutexScope::process);
        std::uint32_t running = kRunning;
        if (!state_.compare_exchange_strong(running, kRaised)) return;
        c_.late_reconfigs.fetch_add(1, std::memory_order_relaxed);
        c_.set_flag(detail::SubsystemCore::kIllegalReconfig, true);
    }

    detail::SubsystemCore& c_;
    std::atomic<std::uint32_t> state_{kRunning};
    std::thread raiser_;
};

// While it applies the items, a SCHED_OTHER caller runs at the priority the
// idle task threads answer at (just below every job): on a loaded machine a
// master left to the fair scheduler would stretch a swap past the cycle.
class PromptCaller {
public:
    PromptCaller() {
        if (pthread_getschedparam(pthread_self(), &policy_, &param_) != 0 || policy_ != SCHED_OTHER) return;
        sched_param sp{};
        sp.sched_priority = muf::RtpuOptions{}.fifo_low - 1;
        boosted_ = pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp) == 0;  // refused: as it was
    }
    ~PromptCaller() {
        if (boosted_) pthread_setschedparam(pthread_self(), policy_, &param_);
    }
    PromptCaller(const PromptCaller&) = delete;
    PromptCaller& operator=(const PromptCaller&) = delete;

private:
    int policy_ = SCHED_OTHER;
    sched_param param_{};
    bool boosted_ = false;
};

}  // namespace

std::vector<VerifyProblem> Subsystem::reconfig_problems(std::span<const ReconfigItem> items) const {
    std::size_t bad_item = 0;
    return problems_of(on_after(*core_, items, bad_item));
}

ReconfigResult Subsystem::reconfig(std::span<const ReconfigItem> items) {
    auto& c = *core_;
    ReconfigResult out;
    // The configuration after the whole list, verified before anything runs.
    std::vector<detail::TaskCore*> on_set;
    std::size_t bad_item = 0;
    try {
        on_set = on_after(c, items, bad_item);
    } catch (const Error& e) {
        out.ok = false;
        out.failed = bad_item;
        out.message = e.what();
        return out;
    }
    try {
        verify_set(on_set);
    } catch (const VerifyError& e) {
        out.ok = false;
        out.failed = 0;
        out.message = std::string("verification before any item was sent: ") + e.what();
        return out;
    }

    const std::int64_t grace_ns = reconfig_grace_ns(c, on_set);
    PromptCaller prompt;
    LateReconfigFlag late(c, grace_ns);
    for (std::size_t i = 0; i < items.size(); ++i) {
        try {
            control(items[i].task, items[i].signal, items[i].arg);
            ++out.processed;
        } catch (const std::exception& e) {
            out.ok = false;
            out.failed = i;
            std::string n;
            try {
                n = c.task(items[i].task)->name;
            } catch (...) {
            }
            out.message = "item " + std::to_string(i) + " (" + std::string(to_string(items[i].signal)) + " " + n +
                          "): " + e.what();
            break;
        }
    }
    return out;
}

double Subsystem::freq_get(TaskId id) const {
    const std::int64_t p = core_->task(id)->period_ns.load();
    return p > 0 ? 1e9 / static_cast<double>(p) : 0.0;
}

void Subsystem::freq_set(TaskId id, double hz) {
    detail::TaskCore* t = core_->task(id);
    if (const std::string why = frequency_problem(hz); !why.empty()) throw Error("freq_set " + t->name + ": " + why);
    if (t->state.load() == State::NOT_CREATED) throw Refused("freq_set refused for task " + t->name + ": it is NOT-CREATED");
    const std::string res = t->request(detail::CmdKind::freq, {}, {}, hz);
    if (!res.empty()) throw Error("freq_set " + t->name + ": " + res);
}

namespace {

// The declaration of `key` among the objects of a task (the first object
// declaring it), or nullptr.
const LocalKey* declared_key(const detail::TaskCore& t, std::string_view key) {
    for (const auto& ob : t.objects)
        if (ob.module != nullptr)
            if (const LocalKey* k = find_local_key(ob.module->local_keys(), key)) return k;
    return nullptr;
}

// Why `set key value` must be refused for task `t` ("" when the objects'
// declarations allow it): every object declaring the key must accept the
// value; when none declares it, the first object's refusal is the answer.
std::string set_refusal(const detail::TaskCore& t, std::string_view key, std::string_view value) {
    std::vector<std::string> values;
    for (std::size_t i = 0; i < value.size();) {
        while (i < value.size() && (value[i] == ' ' || value[i] == '\t')) ++i;
        std::size_t j = i;
        while (j < value.size() && value[j] != ' ' && value[j] != '\t') ++j;
        if (j > i) values.emplace_back(value.substr(i, j - i));
        i = j;
    }
    std::string first;
    bool declared = false;
    for (const auto& ob : t.objects) {
        if (ob.module == nullptr) continue;
        const auto keys = ob.module->local_keys();
        const std::string why = check_local_set(keys, ob.rmod.module, key, values);
        if (find_local_key(keys, key) != nullptr) {
            if (!why.empty()) return why;
            declared = true;
        } else if (first.empty()) {
            first = why;
        }
    }
    return declared ? std::string() : first;
}

}  // namespace

std::string Subsystem::get(TaskId id, std::string_view key) {
    detail::TaskCore* t = core_->task(id);
    if (t->state.load() == State::NOT_CREATED) throw Refused("get refused for task " + t->name + ": it is NOT-CREATED");
    std::string reply;
    const std::string res = t->request(detail::CmdKind::get, {}, std::string(key), 0, &reply);
    if (!res.empty()) {
        // A declared key absent from LOCAL: the module runs with its default.
        const LocalKey* k = declared_key(*t, key);
        if (k != nullptr && k->fallback != nullptr && *k->fallback != '\0') return k->fallback;
        throw Error("get " + t->name + ": " + res);
    }
    return reply;
}

std::vector<LocalKey> Subsystem::local_keys(TaskId id) const {
    const detail::TaskCore* t = core_->task(id);
    std::vector<LocalKey> keys;
    if (t->state.load() == State::NOT_CREATED) return keys;
    for (const auto& ob : t->objects)
        if (ob.module != nullptr)
            for (const LocalKey& k : ob.module->local_keys()) keys.push_back(k);
    return keys;
}

void Subsystem::set(TaskId id, std::string_view key, std::string_view value) {
    detail::TaskCore* t = core_->task(id);
    if (t->state.load() == State::NOT_CREATED) throw Refused("set refused for task " + t->name + ": it is NOT-CREATED");
    if (key.empty()) throw Error("set " + t->name + ": empty key");
    if (const std::string why = set_refusal(*t, key, value); !why.empty())
        throw Refused("set " + t->name + " " + std::string(key) + " refused: " + why);
    const std::string res = t->request(detail::CmdKind::set, std::string(value), std::string(key));
    if (!res.empty()) throw Error("set " + t->name + ": " + res);
}

void Subsystem::event(TaskId id) noexcept {
    detail::TaskCore* t = nullptr;
    {
        std::lock_guard<ipc::PiMutex> lock(core_->tasks_mu);
        if (id.value < 0 || static_cast<std::size_t>(id.value) >= core_->tasks.size()) return;
        t = core_->tasks[id.value].get();
    }
    if (!t) return;
    t->events.fetch_add(1, std::memory_order_acq_rel);
    t->word.fetch_add(1, std::memory_order_release);
    ipc::futex_wake_all(t->word, ipc::FutexScope::process);
}

namespace {
void fill_profile(TaskStatus& s, const detail::TaskCore& t, const std::vector<prof::TaskStatus>& snapshot) {
    if (!t.slot.valid()) return;
    for (const auto& p : snapshot) {
        if (p.slot == t.slot.index()) {
            s.profile = p;
            return;
        }
    }
}
}  // namespace

TaskStatus Subsystem::status(TaskId id) const {
    TaskStatus s = status_without_profile(id);
    fill_profile(s, *core_->task(id), core_->status.snapshot());
    return s;
}

State Subsystem::state(TaskId id) const { return core_->task(id)->state.load(); }

TaskStatus Subsystem::status_without_profile(TaskId id) const {
    detail::TaskCore* t = core_->task(id);
    TaskStatus s;
    s.id = id;
    s.rmod = t->name;
    for (std::size_t i = 0; i < t->objects.size(); ++i) s.module += (i ? "+" : "") + t->objects[i].rmod.module;
    s.rtpu = t->rtpu.name;
    s.cpu = t->rtpu.cpu;
    s.tid = t->tid.load();
    s.type = status_letter(t->type);
    s.crit = t->crit.load();
    s.state = t->state.load();
    s.cycles = t->cycles.load();
    s.misses = t->misses.load();
    const std::int64_t p = t->period_ns.load();
    s.ref_freq = p > 0 ? 1e9 / static_cast<double>(p) : 0.0;
    s.ref_period = static_cast<double>(p) * 1e-9;
    if (s.state == State::ON && s.cycles > 0) {
        const double elapsed = static_cast<double>(ipc::now_ns() - t->on_since_ns.load()) * 1e-9;
        if (elapsed > 0) s.mez_freq = static_cast<double>(s.cycles) / elapsed;
        if (s.cycles > 1)
            s.mez_period = static_cast<double>(t->last_release_ns.load() - t->on_since_ns.load()) * 1e-9 /
                           static_cast<double>(s.cycles - 1);
    }
    s.max_cycle_time = static_cast<double>(t->max_cycle_ns.load()) * 1e-9;
    if (t->pacer) {
        const detail::TimingCounts tc = t->pacer->counts();
        s.deadline_failures = tc.deadline;
        s.maxexec_failures = tc.maxexec;
        s.minexec_failures = tc.minexec;
        s.aborted = tc.aborted;
    }
    s.warnings = t->warnings.load();
    {
        std::lock_guard<ipc::PiMutex> lock(t->msg_mu);
        s.warning = t->first_warning;
        t->first_warning[0] = '\0';  // shown once (§4.4.1)
        s.policy = std::string(t->policy.view());
        if (s.state == State::ERROR) {
            s.error_code = t->error_code;
            s.error = std::string(t->error_text.view());
        }
    }
    // While the task runs, the dispatcher moves its priority and a handler may
    // move its criticality: show what the kernel and the scheduler say now.
    if (t->pacer && s.state == State::ON && t->pacer->running()) {
        s.policy = t->pacer->policy();
        if (const int c = t->pacer->crit(); c != 0) s.crit = c;
    }
    return s;
}

std::vector<RtpuRanking> Subsystem::rtpu_ranking() const {
    std::vector<RtpuRanking> out;
    std::lock_guard<std::mutex> lock(core_->schedulers_mu);
    for (std::size_t i = 0; i < core_->file.rtpus.size(); ++i) {
        RtpuRanking r;
        r.rtpu = core_->file.rtpus[i].name;
        if (i < core_->schedulers.size() && core_->schedulers[i]) {
            const muf::RtpuScheduler& s = *core_->schedulers[i];
            r.mode = s.options().backend == muf::Backend::other || !s.privileged() ? "best-effort"
                     : s.static_ranking()                                            ? "static"
                                                                                     : "dynamic";
            r.reschedules = s.reschedules();
            r.priority_changes = s.priority_changes();
        }
        out.push_back(std::move(r));
    }
    return out;
}

std::vector<TaskStatus> Subsystem::status_all() const {
    std::vector<TaskId> ids;
    {
        std::lock_guard<ipc::PiMutex> lock(core_->tasks_mu);
        for (std::size_t i = 0; i < core_->tasks.size(); ++i)
            if (core_->tasks[i] && core_->tasks[i]->state.load() != State::NOT_CREATED)
                ids.push_back(TaskId{static_cast<int>(i)});
    }
    const std::vector<prof::TaskStatus> snapshot = core_->status.snapshot();
    std::vector<TaskStatus> out;
    for (TaskId id : ids) {
        out.push_back(status_without_profile(id));
        fill_profile(out.back(), *core_->task(id), snapshot);
    }
    return out;
}

void Subsystem::set_sigmask(std::uint32_t mask) { core_->wide_mask.store(mask); }
void Subsystem::set_sigmask(TaskId id, std::uint32_t mask) {
    detail::TaskCore* t = core_->task(id);
    t->sigmask.store(mask);
    t->own_sigmask.store(true);
}
void Subsystem::clear_task_sigmask(TaskId id) { core_->task(id)->own_sigmask.store(false); }

std::optional<SignalEvent> Subsystem::sig_wait(std::uint32_t wanted, std::optional<TaskId> from,
                                               std::chrono::nanoseconds timeout) {
    auto& c = *core_;
    const std::int64_t deadline = timeout.count() < 0 ? -1 : ipc::now_ns() + timeout.count();
    bool expired = false;
    for (;;) {
        const std::uint32_t seen = c.signal_bell.read();
        detail::SubsystemCore::Pending p{};
        while (c.signal_queue.pop(p)) {
            if (!(sig::bit(p.signal) & wanted)) continue;  // not of interest: discarded
            if (from && from->value != p.task) continue;
            c.drain_reports();  // a task's error line comes before the master acts on its signal
            SignalEvent ev;
            ev.signal = p.signal;
            ev.task = TaskId{p.task};
            try {
                ev.rmod = c.task(ev.task)->name;
            } catch (...) {
            }
            return ev;
        }
        if (expired) return std::nullopt;
        expired = !c.signal_bell.wait(seen, deadline);  // then looks once more
    }
}

void Subsystem::sig_send(TaskId from, int signal) {
    if (signal < 0 || signal >= sig::COUNT) throw Error("sig_send: signal " + std::to_string(signal) + " is not 0..31");
    core_->post_signal(*core_->task(from), signal);
}

bool Subsystem::illegal_configuration() const noexcept { return core_->table.illegal_configuration() != 0; }
std::uint64_t Subsystem::late_reconfigs() const noexcept { return core_->late_reconfigs.load(); }

void Subsystem::finish() {
    auto& c = *core_;
    if (c.finished) return;
    c.finished = true;
    std::vector<detail::TaskCore*> live;
    {
        std::lock_guard<ipc::PiMutex> lock(c.tasks_mu);
        for (const auto& t : c.tasks)
            if (t) live.push_back(t.get());
    }
    // Off first, everywhere, then kill (two-step termination, §3.5).
    for (auto* t : live) {
        t->stopping.store(true);
        if (t->state.load() == State::ON) {
            const std::string r = t->request(detail::CmdKind::off);
            if (!r.empty()) std::fprintf(stderr, "chimera: finish: off %s: %s\n", t->name.c_str(), r.c_str());
        }
    }
    for (auto* t : live) {
        if (t->state.load() != State::NOT_CREATED) {
            const std::string r = t->request(detail::CmdKind::kill);
            if (!r.empty()) std::fprintf(stderr, "chimera: finish: kill %s: %s\n", t->name.c_str(), r.c_str());
        }
        t->join();
    }
    c.drain_reports();  // every task has ended: its last lines are printed before finish returns
    {
        std::lock_guard<ipc::PiMutex> lock(c.tasks_mu);
        c.tasks.clear();
    }
    {
        std::lock_guard<std::mutex> lock(c.schedulers_mu);
        c.schedulers.clear();  // every task thread has left: the dispatchers stop
    }
    c.status.close();  // removed with the subsystem: a restart can create it again
    // Removed too while another process still maps it (a Python Table kept
    // after the end): the subsystem is over, and its name must not linger.
    c.table.end_for_all();
}

std::string format_status_header() {
    // Every time in µs, as chimtop and the sbs prompt show them.
    char buf[256];
    std::snprintf(buf, sizeof buf, "%-12s %-6s %7s %s %4s %-11s %9s %6s %8s %8s %9s %9s %9s %10s %6s %4s  %s", "rmod",
                  "rtpu", "tid", "S", "crit", "state", "cycle", "miss", "refF", "mezF", "minC[us]", "avgC[us]",
                  "maxC[us]", "latP99[us]", "avgU%", "warn", "policy");
    return buf;
}

std::string format_status(const TaskStatus& s) {
    // §4.4.1's columns; CPU times from the profile and the lateness
    // percentile from its histogram (issue 14.11), in microseconds.
    const prof::TaskStatus& p = s.profile;
    char late[24] = "-";
    if (const auto ns = p.lateness.percentile_ns(990'000); ns && *ns != UINT64_MAX)
        std::snprintf(late, sizeof late, "%.1f", static_cast<double>(*ns) * 1e-3);
    char buf[512];
    std::snprintf(buf, sizeof buf,
                  "%-12s %-6s %7ld %c %4d %-11s %9llu %6llu %8.2f %8.2f %9.1f %9.1f %9.1f %10s %6.2f %4u  %s",
                  s.rmod.c_str(), s.rtpu.c_str(), s.tid, s.type, s.crit, std::string(to_string(s.state)).c_str(),
                  static_cast<unsigned long long>(s.cycles), static_cast<unsigned long long>(s.misses), s.ref_freq,
                  s.mez_freq, p.min_c * 1e6, p.avg_c * 1e6, p.max_c * 1e6, late, p.avg_u, s.warnings, s.policy.c_str());
    std::string out = buf;
    if (!s.warning.empty()) out += "\nWARNING> " + s.warning;
    if (s.state == State::ERROR) out += "\nERROR> " + s.error;
    return out;
}

}  // namespace chimera::sbs
