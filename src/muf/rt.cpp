// RtpuScheduler: the set-up calls (tasks, periods, attach/detach with the
// backend's policy) and the task thread's real-time path (wait_release,
// cycle_complete). See chimera/muf/rt.hpp; the dispatcher is dispatcher.cpp,
// timing failures failure.cpp, scheduling classes policy.cpp.
#include <algorithm>
#include <linux/futex.h>
#include <sys/prctl.h>
#include <sys/syscall.h>
#include <sys/sysinfo.h>
#include <unistd.h>

#include <cerrno>
#include <cctype>
#include <cstdio>
#include <cstring>
#include <future>

#include "chimera/ipc/futex.hpp"
#include "rt_internal.hpp"

namespace chimera::muf {

using detail::Pacing;
using detail::Phase;
using detail::SlotState;
using detail::TaskSlot;

namespace {

std::atomic<bool> g_warned_no_privilege{false};

void warn_no_privilege(const RtpuOptions& o, int err) {
    if (o.quiet || g_warned_no_privilege.exchange(true)) return;
    std::fprintf(stderr,
                 "chimera: rtpu '%s': no real-time privilege (SCHED_FIFO refused: %s); tasks run "
                 "best effort under SCHED_OTHER, timing failures are still detected\n",
                 o.name.c_str(), std::strerror(err));
}

std::string ms(std::int64_t ns) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.3f ms", static_cast<double>(ns) / 1e6);
    return buf;
}

// Waits until `release_word` moves from `rw`, `word` from `seen` (when given),
// or the absolute CLOCK_MONOTONIC `until` (infinity: no limit). One system call.
// A `word` of the task's own (wait_release's reference form) is the only futex:
// the scheduler bumps it where it bumps release_word (interrupt_wait), so one
// process-private futex serves both, with no page lookup and no allocation in
// the kernel (futex_waitv allocates its vector on every call).
void wait_words(std::atomic<std::uint32_t>& release_word, std::uint32_t rw,
                const std::atomic<std::uint32_t>* word, std::uint32_t seen,
                std::int64_t until, bool own_word) noexcept {
    if (own_word) {
        // The futex only reads the word; the reference form gave it non-const.
        auto& w = const_cast<std::atomic<std::uint32_t>&>(*word);
        if (until == infinity) ipc::futex_wait(w, seen, -1, ipc::FutexScope::process);
        else ipc::futex_wait_until(w, seen, until, ipc::FutexScope::process);
        return;
    }
    if (!word) {
        if (until == infinity) ipc::futex_wait(release_word, rw);
        else ipc::futex_wait_until(release_word, rw, until);
        return;
    }
    // Shared (not private) futexes, so that a word in shared memory, woken
    // from another process, reaches us.
    futex_waitv waiters[2]{};
    waiters[0].val = rw;
    waiters[0].uaddr = reinterpret_cast<std::uintptr_t>(&release_word);
    waiters[0].flags = FUTEX_32;
    waiters[1].val = seen;
    waiters[1].uaddr = reinterpret_cast<std::uintptr_t>(word);
    waiters[1].flags = FUTEX_32;
    timespec ts{};
    if (until != infinity) {
        ts.tv_sec = static_cast<time_t>(until / 1'000'000'000);
        ts.tv_nsec = static_cast<long>(until % 1'000'000'000);
    }
    const long rc = syscall(SYS_futex_waitv, waiters, 2u, 0u, until == infinity ? nullptr : &ts,
                            CLOCK_MONOTONIC);
    if (rc < 0 && errno == ENOSYS) {
        // Kernels before 5.16: watch the command word by polling every millisecond.
        const std::int64_t poll = clock_ns() + 1'000'000;
        ipc::futex_wait_until(release_word, rw, until < poll ? until : poll);
    }
}

// A thread in wait_release must look again: removed, or its ranking changed.
// Sequentially consistent with wait_release's store of own_word and load of
// release_word: either this sees the task's word and bumps it, or the task's
// next look sees release_word moved.
void interrupt_wait(TaskSlot& s) noexcept {
    s.release_word.fetch_add(1, std::memory_order_seq_cst);
    ipc::futex_wake_all(s.release_word);
    if (std::atomic<std::uint32_t>* w = s.own_word.load(std::memory_order_seq_cst)) {
        w->fetch_add(1, std::memory_order_release);
        ipc::futex_wake_all(*w, ipc::FutexScope::process);
    }
}

}  // namespace

// ------------------------------------------------------------------ names

std::string_view to_string(Backend backend) noexcept {
    switch (backend) {
        case Backend::fifo: return "fifo";
        case Backend::deadline: return "deadline";
        case Backend::other: return "other";
    }
    return "?";
}

std::optional<Backend> parse_backend(std::string_view text) noexcept {
    auto eq = [&](std::string_view a, std::string_view b) {
        if (a.size() != b.size()) return false;
        for (std::size_t i = 0; i < a.size(); ++i)
            if (std::tolower(static_cast<unsigned char>(a[i])) != b[i]) return false;
        return true;
    };
    if (eq(text, "fifo")) return Backend::fifo;
    if (eq(text, "deadline")) return Backend::deadline;
    if (eq(text, "other")) return Backend::other;
    return std::nullopt;
}

// ------------------------------------------------------------------ Impl

namespace {

// The MUF order of pending jobs never changes between releases when no
// deadline takes part (RM), or when every deadline equals its period and the
// periods divide one another: a shorter period's current deadline is then
// never after a longer one's (the longer period's boundaries are among the
// shorter's), so the order by relative deadline is the order by absolute
// deadline. Ties of equal deadline go to the shorter period here, where the
// dynamic dispatcher would take user priority first.
bool ranking_is_static(const std::vector<TaskSpec>& specs, bool uses_deadline) {
    if (!uses_deadline) return true;
    for (const TaskSpec& t : specs) {
        if (t.deadline > 0 && t.deadline != t.period) return false;
        const auto p = static_cast<std::int64_t>(t.period);
        for (const TaskSpec& u : specs) {
            const auto q = static_cast<std::int64_t>(u.period);
            if (p <= 0 || q <= 0) return false;
            if (std::max(p, q) % std::min(p, q) != 0) return false;
        }
    }
    return true;
}

}  // namespace

RtpuScheduler::Impl::Impl(RtpuOptions o) : options(std::move(o)) {
    const std::string who = "rtpu '" + options.name + "': ";
    if (options.cpu < 0 || options.cpu >= get_nprocs())
        throw SchedError(who + "CPU " + std::to_string(options.cpu) + " does not exist (" +
                         std::to_string(get_nprocs()) + " online)");
    if (options.fifo_low < 1 || options.fifo_high > 99 || options.fifo_low >= options.fifo_high)
        throw SchedError(who + "SCHED_FIFO band [" + std::to_string(options.fifo_low) + ", " +
                         std::to_string(options.fifo_high) + "] must satisfy 1 <= low < high <= 99");
    if (options.tick_ns <= 0) throw SchedError(who + "tick_ns must be positive");
    const auto& e = options.encoding;
    if (e.crit_bits == 0 || e.user_bits == 0 || e.dyn_bits == 0 ||
        e.crit_bits + e.dyn_bits + e.user_bits > 64 || e.dyn_bits > 62)
        throw SchedError(who + "urgency encoding must have 1..64 bits in all (c, d, u > 0, d <= 62)");
    if (options.watchdog_ns <= 0) throw SchedError(who + "watchdog_ns must be positive");
    detail::install_failure_signals();
    epoch_ns = options.epoch_ns > 0 ? options.epoch_ns : clock_ns();

    // The dispatcher is also the DEADLINE watchdog, so every backend has one:
    // at SCHED_FIFO options.fifo_high where it may, else (backend other, no
    // privilege) a best-effort watchdog under SCHED_OTHER.
    const bool want_fifo = options.backend != Backend::other;
    std::promise<int> started;
    auto result = started.get_future();
    dispatcher = std::thread([this, &started, want_fifo] {
        dispatcher_tid.store(static_cast<int>(syscall(SYS_gettid)));
        pthread_setname_np(pthread_self(), "muf-dispatch");
        const int pin = detail::pin_to_cpu(options.cpu);
        const int rc = want_fifo ? detail::set_fifo(0, options.fifo_high) : 0;
        started.set_value(rc != 0 ? rc : want_fifo ? pin : 0);
        if (rc != 0 && rc != EPERM) return;
        dispatcher_main();
    });
    const int rc = result.get();
    if (!want_fifo) return;
    if (rc == EPERM) {
        privileged = false;
        warn_no_privilege(options, rc);
        return;
    }
    if (rc != 0) {
        stopping = true;
        notify();
        dispatcher.join();
        throw SchedError(who + "cannot start the dispatcher on CPU " + std::to_string(options.cpu) +
                         ": " + std::strerror(rc));
    }
    dispatcher_running = true;
    // Privileged real-time tasks are coming: no page fault in their cycles.
    static std::atomic<bool> memory_note_said{false};
    if (const std::string note = detail::lock_memory(); !note.empty() && !memory_note_said.exchange(true))
        std::fprintf(stderr, "chimera: %s\n", note.c_str());
    static std::atomic<bool> latency_note_said{false};
    if (const std::string note = detail::hold_cpu_wakeup_latency();
        !note.empty() && !latency_note_said.exchange(true))
        std::fprintf(stderr, "chimera: %s\n", note.c_str());
}

RtpuScheduler::Impl::~Impl() {
    stopping.store(true, std::memory_order_release);
    if (dispatcher.joinable()) {
        notify();
        dispatcher.join();
    }
}

TaskSlot* RtpuScheduler::Impl::slot(TaskHandle h) noexcept {
    if (h < 0 || h >= slot_count_seen.load(std::memory_order_acquire)) return nullptr;
    return &slots[static_cast<std::size_t>(h)];
}

const TaskSlot* RtpuScheduler::Impl::slot(TaskHandle h) const noexcept {
    if (h < 0 || h >= slot_count_seen.load(std::memory_order_acquire)) return nullptr;
    return &slots[static_cast<std::size_t>(h)];
}

TaskSlot& RtpuScheduler::Impl::checked_slot(TaskHandle h, const char* what) {
    TaskSlot* s = slot(h);
    const SlotState st = s ? s->state.load() : SlotState::free;
    if (!s || st == SlotState::free || st == SlotState::removed)
        throw SchedError("rtpu '" + options.name + "': " + what + ": no task with handle " +
                         std::to_string(h));
    return *s;
}

void RtpuScheduler::Impl::reassign() {
    std::vector<TaskSpec> specs;
    std::vector<int> handles;
    const int count = slot_count_seen.load();
    for (int h = 0; h < count; ++h) {
        const TaskSlot& s = slots[static_cast<std::size_t>(h)];
        const SlotState st = s.state.load();
        if (st != SlotState::added && st != SlotState::attached) continue;
        TaskSpec t;
        t.name = s.params.name;
        t.period = static_cast<double>(s.params.period_ns);
        t.wcet = static_cast<double>(s.params.wcet_ns);
        t.deadline = static_cast<double>(s.params.deadline_ns);
        t.effective = static_cast<double>(s.params.effective_ns);
        t.crit = s.params.crit;
        t.uprio = s.params.uprio;
        specs.push_back(std::move(t));
        handles.push_back(h);
    }
    Assignment a = assign(specs, options.policy, data_flows(handles));
    for (std::size_t i = 0; i < handles.size(); ++i) {
        TaskSlot& s = slots[static_cast<std::size_t>(handles[i])];
        const int old_base = s.base_crit.exchange(a.crit[i]);
        // A criticality the task set itself (a handler, set_criticality) stays.
        int cur = old_base;
        s.crit.compare_exchange_strong(cur, a.crit[i]);
        s.uprio.store(a.uprio[i]);
    }
    uses_deadline.store(a.uses_deadline);
    const bool was_static = static_ranking.load();
    const bool now_static = ranking_is_static(specs, a.uses_deadline);
    static_ranking.store(now_static, std::memory_order_release);
    current_assignment = std::move(a);
    assignment_handles = std::move(handles);
    if (now_static != was_static) {
        // Tasks waiting for the dispatcher (or for their own timeout) must
        // see the change: they wait the other way from their next release.
        for (int h = 0; h < count; ++h) {
            TaskSlot& s = slots[static_cast<std::size_t>(h)];
            if (s.state.load() != SlotState::attached) continue;
            interrupt_wait(s);
        }
    }
}

std::vector<Flow> RtpuScheduler::Impl::data_flows(const std::vector<int>& handles) const {
    std::vector<Flow> flows;
    for (std::size_t i = 0; i < handles.size(); ++i) {
        const RtTaskParams& producer = slots[static_cast<std::size_t>(handles[i])].params;
        for (std::size_t j = 0; j < handles.size(); ++j) {
            if (i == j) continue;
            const RtTaskParams& consumer = slots[static_cast<std::size_t>(handles[j])].params;
            const bool feeds = std::any_of(producer.outputs.begin(), producer.outputs.end(), [&](const auto& v) {
                return std::find(consumer.inputs.begin(), consumer.inputs.end(), v) != consumer.inputs.end();
            });
            if (feeds) flows.push_back({i, j});
        }
    }
    return flows;
}

std::int64_t RtpuScheduler::Impl::aligned_release(std::int64_t period_ns) const noexcept {
    const std::int64_t now = clock_ns();
    if (now < epoch_ns) return epoch_ns;
    return epoch_ns + ((now - epoch_ns) / period_ns + 1) * period_ns;
}

// ------------------------------------------------------------------ RtpuScheduler

RtpuScheduler::RtpuScheduler(RtpuOptions options) : impl_(std::make_unique<Impl>(std::move(options))) {}
RtpuScheduler::~RtpuScheduler() = default;

const RtpuOptions& RtpuScheduler::options() const noexcept { return impl_->options; }
bool RtpuScheduler::privileged() const noexcept { return impl_->privileged; }

TaskHandle RtpuScheduler::add_task(const RtTaskParams& p) {
    Impl& m = *impl_;
    const std::string who = "rtpu '" + m.options.name + "', task '" + p.name + "': ";
    if (p.period_ns <= 0) throw SchedError(who + "PERIOD must be positive");
    if (p.wcet_ns < 0 || p.effective_ns < 0 || p.minexec_ns < 0 || p.deadline_ns < 0)
        throw SchedError(who + "times must not be negative");
    if (p.deadline_ns > p.period_ns)
        throw SchedError(who + "DEADLINE " + ms(p.deadline_ns) + " beyond the period " +
                         ms(p.period_ns) + " (jobs would overlap)");
    if (p.effective_ns > 0 && p.wcet_ns > 0 && p.effective_ns > p.wcet_ns)
        throw SchedError(who + "effective time E " + ms(p.effective_ns) + " exceeds WCET " +
                         ms(p.wcet_ns));
    const std::int64_t deadline = p.deadline_ns > 0 ? p.deadline_ns : p.period_ns;
    if (p.minexec_ns > deadline)
        throw SchedError(who + "MINEXEC " + ms(p.minexec_ns) + " exceeds the deadline " + ms(deadline));
    std::lock_guard<ipc::PiMutex> lock(m.mutex);
    int live = 0;
    for (int h = 0; h < m.slot_count_seen.load(); ++h) {
        const SlotState st = m.slots[static_cast<std::size_t>(h)].state.load();
        if (st == SlotState::added || st == SlotState::attached) ++live;
    }
    const int band = m.options.fifo_high - m.options.fifo_low;
    if (live >= detail::kMaxTasks || (m.options.backend != Backend::other && live >= band))
        throw SchedError(who + "too many tasks on this RTPU (" + std::to_string(live) +
                         "; at most " + std::to_string(std::min(band, detail::kMaxTasks)) +
                         ", one SCHED_FIFO priority each in [" + std::to_string(m.options.fifo_low) +
                         ", " + std::to_string(m.options.fifo_high) + "))");
    // A removed slot whose thread has left is reused; else a fresh one.
    int h = -1;
    for (int i = 0; i < m.slot_count_seen.load() && h < 0; ++i) {
        const TaskSlot& s = m.slots[static_cast<std::size_t>(i)];
        if (s.state.load() == SlotState::removed && s.tid.load() == 0) h = i;
    }
    if (h < 0) {
        if (m.slot_count_seen.load() >= detail::kMaxTasks)
            throw SchedError(who + "no free task slot (" + std::to_string(detail::kMaxTasks) + ")");
        h = m.slot_count_seen.load();
    }
    TaskSlot& s = m.slots[static_cast<std::size_t>(h)];
    s.params = p;
    if (s.params.name.empty()) s.params.name = "task" + std::to_string(h);
    s.policy_text.clear();
    s.period_ns = p.period_ns;
    s.rel_deadline_ns = deadline;
    s.phase = Phase::waiting;
    s.self_timed = false;
    s.job_deadline_ns = infinity;
    s.crit = 0;
    s.base_crit = 0;
    s.fifo_prio = 0;
    s.deadline_reserved = false;
    for (auto* c : {&s.cycles, &s.missed, &s.deadline_failures, &s.maxexec_failures,
                    &s.minexec_failures, &s.aborted})
        c->store(0);
    s.state.store(SlotState::added, std::memory_order_release);
    if (h == m.slot_count_seen.load()) m.slot_count_seen.store(h + 1, std::memory_order_release);
    m.reassign();
    m.notify();
    return h;
}

void RtpuScheduler::remove_task(TaskHandle h) {
    Impl& m = *impl_;
    std::lock_guard<ipc::PiMutex> lock(m.mutex);
    TaskSlot& s = m.checked_slot(h, "remove_task");
    s.state.store(SlotState::removed, std::memory_order_release);
    s.phase.store(Phase::detached, std::memory_order_release);
    interrupt_wait(s);
    m.reassign();
    m.notify();
}

void RtpuScheduler::set_period(TaskHandle h, std::int64_t period_ns) {
    Impl& m = *impl_;
    std::lock_guard<ipc::PiMutex> lock(m.mutex);
    TaskSlot& s = m.checked_slot(h, "set_period");
    if (period_ns <= 0)
        throw SchedError("rtpu '" + m.options.name + "', task '" + s.params.name +
                         "': set_period: the period must be positive");
    const std::int64_t budget = s.params.effective_ns > 0 ? s.params.effective_ns : s.params.wcet_ns;
    if (s.deadline_reserved.load()) {
        const int rc = detail::set_deadline_policy(s.tid.load(), std::max<std::int64_t>(budget, 1024),
                                                   period_ns, period_ns);
        if (rc != 0)
            throw SchedError("rtpu '" + m.options.name + "', task '" + s.params.name +
                             "': SCHED_DEADLINE refused the period " + ms(period_ns) + ": " +
                             std::strerror(rc));
    }
    s.params.period_ns = period_ns;
    s.params.deadline_ns = 0;
    s.rel_deadline_ns.store(period_ns);
    s.period_ns.store(period_ns, std::memory_order_release);
    m.reassign();
    m.notify();
}

void RtpuScheduler::attach_current_thread(TaskHandle h) {
    Impl& m = *impl_;
    std::unique_lock<ipc::PiMutex> lock(m.mutex);
    TaskSlot& s = m.checked_slot(h, "attach_current_thread");
    const std::string who = "rtpu '" + m.options.name + "', task '" + s.params.name + "': ";
    if (s.state.load() == SlotState::attached)
        throw SchedError(who + "a thread is attached already");
    const pid_t tid = static_cast<pid_t>(syscall(SYS_gettid));
    std::size_t index = 0;
    bool critical = false;
    for (; index < m.assignment_handles.size(); ++index)
        if (m.assignment_handles[index] == h) {
            critical = m.current_assignment.critical.member[index];
            break;
        }

    std::string note;
    Pacing pacing = Pacing::self_paced;
    bool reserved = false;
    const std::int64_t budget = s.params.effective_ns > 0 ? s.params.effective_ns : s.params.wcet_ns;
    if (m.options.backend == Backend::deadline && critical && m.privileged && budget > 0) {
        // Pinned first: the kernel admits SCHED_DEADLINE to a thread pinned to
        // one CPU only where that CPU is a root domain of its own (an exclusive
        // cpuset partition). A reservation that floats over other CPUs would
        // not be this RTPU's, so without a partition the task is refused.
        if (const int pin = detail::pin_to_cpu(m.options.cpu); pin != 0)
            throw SchedError(who + "cannot pin to CPU " + std::to_string(m.options.cpu) + " of RTPU " +
                             m.options.name + " (" + detail::process_cpus_text() + "): " + std::strerror(pin));
        const std::int64_t runtime = std::max<std::int64_t>(budget, 1024);
        // The whole critical set shares the CPU's bandwidth: a set that cannot
        // fit is refused here, whatever the kernel says of this one reservation
        // (it admits per root domain, and a partition just made may not have
        // its own yet: the guest once admitted 0.97 on one).
        const int rc = m.current_assignment.critical.utilisation > detail::deadline_bandwidth_per_cpu()
                           ? EBUSY
                           : detail::set_deadline_policy(0, runtime, s.rel_deadline_ns.load(), s.period_ns.load());
        if (rc == 0) {
            reserved = true;
            note = " (CPU " + std::to_string(m.options.cpu) + ", a root domain of its own)";
        } else if (rc == EPERM) {
            throw SchedError(who + "SCHED_DEADLINE on RTPU " + m.options.name + " needs CPU " +
                             std::to_string(m.options.cpu) +
                             " to be an exclusive cpuset partition (a root domain of its own): the kernel "
                             "refuses a reservation pinned inside a wider root domain (" +
                             detail::process_cpus_text() +
                             "). Make one (docs/muf.md, \"Deadline backend: a CPU of its own\") or run "
                             "this RTPU on BACKEND fifo");
        } else if (rc == EBUSY) {
            char buf[256];
            std::snprintf(buf, sizeof buf,
                          "SCHED_DEADLINE admission refused (runtime %s, period %s): the critical "
                          "set's utilisation is %.3f on this RTPU, and the kernel admits at most "
                          "%.2f of CPU %d, shared with every SCHED_DEADLINE task there",
                          ms(runtime).c_str(), ms(s.period_ns.load()).c_str(),
                          m.current_assignment.critical.utilisation,
                          detail::deadline_bandwidth_per_cpu(), m.options.cpu);
            throw SchedError(who + buf);
        } else if (rc == EINVAL) {
            throw SchedError(who + "SCHED_DEADLINE refused the parameters (runtime " + ms(runtime) +
                             ", deadline " + ms(s.rel_deadline_ns.load()) + ", period " +
                             ms(s.period_ns.load()) + "): " + std::strerror(rc));
        } else {
            note = std::string(" (SCHED_DEADLINE refused: ") + std::strerror(rc) + "; on SCHED_FIFO)";
        }
    }
    if (!reserved) {
        const int pin = detail::pin_to_cpu(m.options.cpu);
        if (pin != 0) note += std::string(" (not pinned: ") + std::strerror(pin) + ")";
        if (m.options.backend != Backend::other && m.privileged && m.dispatcher_running) {
            const int rc = detail::set_fifo(0, m.options.fifo_low);
            if (rc == 0) {
                pacing = Pacing::dispatched;
                // Runs at the bottom of the band until ranked, but counts as
                // not placed (0): the ranking keeps placed priorities where it
                // can, and a task kept at fifo_low would sit below every other
                // real-time thread of the machine (threaded IRQs are at 50 on
                // PREEMPT_RT) for good. Unplaced, it is placed from the top.
                s.fifo_prio.store(0);
            } else {
                warn_no_privilege(m.options, rc);
                note += std::string(" (SCHED_FIFO refused: ") + std::strerror(rc) + ")";
            }
        } else if (!m.privileged) {
            note += " (no privilege)";
        }
    }
    // A futex timeout is an hrtimer with the thread's timer slack (50 µs by
    // default): the release would come up to that late. Real-time threads
    // sleep to the nanosecond, as clock_nanosleep does for them.
    prctl(PR_SET_TIMERSLACK, 1UL, 0UL, 0UL, 0UL);
    try {
        if (!reserved) detail::create_budget_timer(s);  // SCHED_DEADLINE has its own (DL_OVERRUN)
    } catch (...) {
        if (reserved || pacing == Pacing::dispatched) detail::set_other(0);
        throw;
    }
    detail::bind_thread(&m, &s, h);
    s.deadline_reserved.store(reserved);
    s.pacing.store(pacing);
    s.policy_text = note;
    s.tid.store(tid);
    s.phase.store(Phase::waiting);
    s.self_timed.store(false);
    s.own_word.store(nullptr);
    s.release_word.fetch_add(1);
    s.control_seen = s.release_word.load();
    const std::int64_t first =
        s.params.first_release_ns > 0 ? s.params.first_release_ns : m.aligned_release(s.period_ns.load());
    s.next_release_ns.store(first);
    s.state.store(SlotState::attached, std::memory_order_release);
    m.notify();
}

void RtpuScheduler::detach_current_thread(TaskHandle h) noexcept {
    Impl& m = *impl_;
    std::lock_guard<ipc::PiMutex> lock(m.mutex);
    TaskSlot* s = m.slot(h);
    if (!s || s->tid.load() != static_cast<int>(syscall(SYS_gettid))) return;
    if (s->state.load() == SlotState::attached) s->state.store(SlotState::added);
    s->own_word.store(nullptr);  // no later interrupt touches a word that may be gone
    detail::delete_budget_timer(*s);
    detail::bind_thread(nullptr, nullptr, -1);
    detail::set_other(0);
    s->fifo_prio.store(0);
    s->deadline_reserved.store(false);
    s->tid.store(0);
    m.notify();
}

// ------------------------------------------------------------------ real-time path

namespace {

// Releases every `period` from `release` on that passed before `now` while
// the task was busy: each is a miss, and each deadline among them not
// reported yet a failure, so that misses and failures agree. Returns how many.
std::int64_t count_skipped_releases(TaskSlot& s, std::int64_t release, std::int64_t period,
                                    std::int64_t now) noexcept {
    if (period <= 0 || now < release) return 0;
    const std::int64_t late = (now - release) / period;
    if (late > 0) {
        s.missed.fetch_add(static_cast<std::uint64_t>(late), std::memory_order_relaxed);
        detail::releases_skipped(s, release, late);
    }
    return late;
}

}  // namespace

Wake RtpuScheduler::wait_release(TaskHandle h, const std::atomic<std::uint32_t>* word,
                                 std::uint32_t seen) noexcept {
    return impl_->wait_for_release(h, word, seen, /*own_word=*/false);
}

Wake RtpuScheduler::wait_release(TaskHandle h, std::atomic<std::uint32_t>& word, std::uint32_t seen) noexcept {
    TaskSlot* sp = impl_->slot(h);
    if (!sp) return Wake::detached;
    // Registered before release_word is read (interrupt_wait); once is enough:
    // an earlier store of this thread precedes its later reads all the same,
    // and the same word comes every cycle (no atomic exchange per cycle).
    if (sp->own_word.load(std::memory_order_relaxed) != &word) sp->own_word.store(&word, std::memory_order_seq_cst);
    return impl_->wait_for_release(h, &word, seen, /*own_word=*/true);
}

Wake RtpuScheduler::Impl::wait_for_release(TaskHandle h, const std::atomic<std::uint32_t>* word,
                                           std::uint32_t seen, bool own_word) noexcept {
    TaskSlot* sp = slot(h);
    if (!sp) return Wake::detached;
    TaskSlot& s = *sp;
    bool slept = false;
    std::int64_t now = 0;
    for (;;) {
        const std::uint32_t rw = s.release_word.load(std::memory_order_seq_cst);
        const Phase phase = s.phase.load(std::memory_order_acquire);
        const SlotState state = s.state.load(std::memory_order_acquire);
        if (phase == Phase::detached || state != SlotState::attached) {
            // A task removed (remove_task) waits for no more releases: those its
            // last job overran are counted now, as the next release would have.
            if (state == SlotState::removed)
                (void)count_skipped_releases(s, s.next_release_ns.load(std::memory_order_relaxed),
                                             s.period_ns.load(std::memory_order_acquire), clock_ns());
            return Wake::detached;
        }
        // The thread keeps its own timeline: the kernel wakes it at its release.
        if (phase == Phase::job) break;  // a job begun by set_deadline()
        std::int64_t release = s.next_release_ns.load(std::memory_order_relaxed);
        if (!slept) {
            // Straight to sleep without reading the clock: a release already
            // past makes the futex return at once. The clock is read once per
            // cycle, after the wake-up (where the vDSO cannot serve it, as
            // under emulation, every read is a system call).
            if (word && word->load(std::memory_order_acquire) != seen) return Wake::command;
            wait_words(s.release_word, rw, word, seen, release, own_word);
            slept = true;
            continue;
        }
        now = clock_ns();
        if (now >= release) {
            const std::int64_t period = s.period_ns.load(std::memory_order_acquire);
            release += count_skipped_releases(s, release, period, now) * period;
            // The deadline before the phase, the next release after it: a
            // ranking that looks meanwhile sees the same job either way (a
            // release that came late, late > 0, ranks itself again below).
            s.job_release_ns.store(release, std::memory_order_relaxed);
            s.job_deadline_ns.store(release + s.rel_deadline_ns.load(std::memory_order_relaxed),
                                    std::memory_order_release);
            s.phase.store(Phase::job, std::memory_order_release);
            s.next_release_ns.store(release + period, std::memory_order_release);
            detail::mark_job_unstarted();
            if (ranks_at_release(s)) {
                // Dynamic ranking: the job was ranked before its release (by
                // the job its release begins); the order is looked at again
                // before it begins. It may have waited for the CPU behind more
                // urgent jobs until its deadline passed.
                rank_at_release(now, h);
                detail::deadline_passed_unstarted(s, now);
            }
            break;
        }
        if (word && word->load(std::memory_order_acquire) != seen) return Wake::command;
        wait_words(s.release_word, rw, word, seen, release, own_word);
    }

    // A release: the handler asked to skip it, or MINEXEC cannot be met.
    if (detail::take_skip_next()) {
        s.missed.fetch_add(1, std::memory_order_relaxed);
        s.phase.store(Phase::waiting, std::memory_order_release);
        return Wake::skipped;
    }
    const std::int64_t deadline = s.job_deadline_ns.load(std::memory_order_acquire);
    const std::int64_t minexec = s.params.minexec_ns;
    if (minexec > 0 && deadline - clock_ns() < minexec) {
        s.missed.fetch_add(1, std::memory_order_relaxed);
        s.phase.store(Phase::waiting, std::memory_order_release);
        detail::raise_failure_here(Failure::minexec);
        return Wake::skipped;
    }
    const std::int64_t budget = !s.params.maxexec_check ? infinity
                                : s.params.effective_ns > 0 ? s.params.effective_ns
                                                            : s.params.wcet_ns;
    detail::arm_budget(s, budget);
    return Wake::release;
}

void RtpuScheduler::cycle_complete(TaskHandle h) noexcept {
    TaskSlot* sp = impl_->slot(h);
    if (!sp) return;
    TaskSlot& s = *sp;
    detail::clear_abort();
    // The job ends first: a watchdog signal from now on finds no job and is stale.
    Phase job = Phase::job;
    // A job during which the task was removed (remove_task: detached, which
    // stays) is accounted all the same, or the deadlines the watchdog reported
    // during it would be failures without misses (the releases it overran are
    // counted as the task leaves: wait_for_release).
    const bool ended = s.phase.compare_exchange_strong(job, Phase::waiting, std::memory_order_acq_rel) ||
                       job == Phase::detached;
    const bool ended_late = ended && detail::job_ended(s);
    // A miss per deadline missed: a job aborted, or complete but late (it still counts as a cycle).
    if (detail::take_cycle_aborted()) {
        s.missed.fetch_add(1, std::memory_order_relaxed);
    } else {
        s.cycles.fetch_add(1, std::memory_order_relaxed);
        if (ended_late) s.missed.fetch_add(1, std::memory_order_relaxed);
    }
}

sigjmp_buf* RtpuScheduler::cycle_mark(TaskHandle h) noexcept {
    TaskSlot* s = impl_->slot(h);
    return s ? &s->mark : nullptr;
}

void RtpuScheduler::arm_abort(TaskHandle) noexcept { detail::set_abort_armed(); }
void RtpuScheduler::disarm_abort(TaskHandle) noexcept { detail::clear_abort(); }

// ------------------------------------------------------------------ status

std::string RtpuScheduler::policy_of(TaskHandle h) const {
    const Impl& m = *impl_;
    std::lock_guard<ipc::PiMutex> lock(m.mutex);
    const TaskSlot* s = m.slot(h);
    if (!s) return "no such task";
    const int tid = s->tid.load();
    if (tid == 0) return "not attached";
    return detail::describe_policy(tid) + s->policy_text;
}

RtTaskStatus RtpuScheduler::status(TaskHandle h) const noexcept {
    RtTaskStatus st;
    const TaskSlot* s = impl_->slot(h);
    if (!s) return st;
    st.cycles = s->cycles.load(std::memory_order_relaxed);
    st.missed = s->missed.load(std::memory_order_relaxed);
    st.deadline_failures = s->deadline_failures.load(std::memory_order_relaxed);
    st.maxexec_failures = s->maxexec_failures.load(std::memory_order_relaxed);
    st.minexec_failures = s->minexec_failures.load(std::memory_order_relaxed);
    st.aborted = s->aborted.load(std::memory_order_relaxed);
    st.crit = s->crit.load(std::memory_order_relaxed);
    st.priority = s->deadline_reserved.load() ? 0 : s->fifo_prio.load(std::memory_order_relaxed);
    st.tid = s->tid.load(std::memory_order_relaxed);
    return st;
}

std::int64_t RtpuScheduler::job_release_ns(TaskHandle h) const noexcept {
    const TaskSlot* s = impl_->slot(h);
    return s ? s->job_release_ns.load(std::memory_order_relaxed) : 0;
}

Assignment RtpuScheduler::assignment() const {
    std::lock_guard<ipc::PiMutex> lock(impl_->mutex);
    return impl_->current_assignment;
}

std::uint64_t RtpuScheduler::reschedules() const noexcept { return impl_->reschedules.load(); }
std::uint64_t RtpuScheduler::priority_changes() const noexcept { return impl_->priority_changes.load(); }
std::uint64_t RtpuScheduler::watchdog_signals() const noexcept { return impl_->watchdog_signals.load(); }
bool RtpuScheduler::static_ranking() const noexcept {
    return impl_->options.backend == Backend::fifo && impl_->privileged &&
           impl_->static_ranking.load(std::memory_order_acquire);
}

}  // namespace chimera::muf
