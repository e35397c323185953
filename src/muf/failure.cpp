// Timing failures (thesis §6.3): DEADLINE seen by the task at its job's
// completion or signalled by the RTPU's watchdog (dispatcher.cpp) for a job
// still running, the per-task MAXEXEC CPU-time timer, the signal handler that
// runs the user's FailureHandler in the failing task's own thread, critical
// sections that hold handlers off, and the thesis's task API (set_dfhandler,
// set_criticality, set_deadline, pause, execstart/end/left). See docs/muf.md.
//
// Everything reachable from the signal handler is async-signal-safe: atomics,
// timer_settime/timer_gettime, clock_gettime, futex wake, siglongjmp.
#include <pthread.h>
#include <signal.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <mutex>

#include "rt_internal.hpp"

namespace chimera::muf {
namespace detail {
namespace {

constexpr std::int64_t kNsPerSec = 1'000'000'000;

timespec to_ts(std::int64_t ns) noexcept {
    timespec ts;
    ts.tv_sec = static_cast<time_t>(ns / kNsPerSec);
    ts.tv_nsec = static_cast<long>(ns % kNsPerSec);
    return ts;
}

std::int64_t from_ts(const timespec& ts) noexcept {
    return static_cast<std::int64_t>(ts.tv_sec) * kNsPerSec + ts.tv_nsec;
}

std::int64_t thread_cpu_ns() noexcept {
    timespec ts;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
    return from_ts(ts);
}

constexpr unsigned bit(Failure kind) noexcept { return 1u << static_cast<int>(kind); }

// What a thread knows about its own timing failures. Touched by the thread and
// by signal handlers running on it (never by another thread).
struct ThreadState {
    RtpuScheduler::Impl* impl = nullptr;
    TaskSlot* slot = nullptr;
    TaskHandle handle = -1;

    FailureHandler handler = nullptr;
    void* user = nullptr;
    int handler_crit = 0;  // 0: the handler runs at the task's criticality
    int crit_unbound = 0;  // criticality of a thread with no task

    volatile sig_atomic_t critical_depth = 0;
    std::atomic<unsigned> pending{0};  // failures held off by a critical section
    bool raised_while_held = false;    // criticality raised to handler_crit while held
    int crit_before_raise = 0;
    int in_handler = 0;
    bool crit_set_in_handler = false;
    std::uint32_t deadline_sets = 0;  // set_deadline() calls, to see if a handler made one

    volatile sig_atomic_t abort_armed = 0;
    volatile sig_atomic_t skip_next = 0;
    volatile sig_atomic_t cycle_aborted = 0;
    // A job released and not yet begun (between its release and the cycle's
    // start, e.g. waiting for the CPU): an abort at its deadline drops it.
    volatile sig_atomic_t job_unstarted = 0;
    volatile sig_atomic_t drop_job = 0;

    std::int64_t reported_deadline = infinity;  // the job deadline whose failure was delivered
    bool maxexec_timer_set = false;             // the CPU-time timer holds a budget
    bool budget_armed = false;
    std::int64_t budget_ns = infinity;
    std::int64_t budget_cpu_start = 0;  // SCHED_DEADLINE tasks: CPU time at the release

    std::int64_t exec_start_wall = 0;
    std::int64_t exec_start_cpu = 0;
};

// Initial-exec: libchimera's TLS block is static already (ipc's owner id),
// so no access needs __tls_get_addr — the task loop reads this every cycle.
[[gnu::tls_model("initial-exec")]] thread_local ThreadState tl;

int g_timer_signal = 0;
std::once_flag g_signals_once;

void set_crit_internal(ThreadState& t, int c) noexcept {
    if (!t.slot) {
        t.crit_unbound = c;
        return;
    }
    if (t.slot->crit.exchange(c, std::memory_order_acq_rel) == c) return;
    if (t.impl && t.slot->pacing.load(std::memory_order_relaxed) == Pacing::dispatched)
        t.impl->notify();
}

int current_crit(const ThreadState& t) noexcept {
    return t.slot ? t.slot->crit.load(std::memory_order_acquire) : t.crit_unbound;
}

// Timer value left: 0 when the one-shot timer has expired and not been re-armed.
std::int64_t timer_left(timer_t timer) noexcept {
    itimerspec its{};
    if (timer_gettime(timer, &its) != 0) return 0;
    return from_ts(its.it_value);
}

// Does a signal still stand for a failure of the job running now? A signal
// from a timer that has been re-armed or a job already complete is stale.
bool still_applies(ThreadState& t, Failure kind, bool from_kernel_overrun) noexcept {
    TaskSlot& s = *t.slot;
    if (s.phase.load(std::memory_order_acquire) != Phase::job) return false;
    switch (kind) {
        case Failure::deadline: {
            // From the watchdog: the job it saw late may have ended since, and a
            // failure already reported (at completion) is not reported twice.
            const std::int64_t d = s.job_deadline_ns.load(std::memory_order_acquire);
            return d != infinity && d != t.reported_deadline && clock_ns() >= d;
        }
        case Failure::maxexec:
            if (from_kernel_overrun) return s.deadline_reserved.load(std::memory_order_relaxed);
            return t.budget_armed && s.maxexec_timer_created && timer_left(s.maxexec_timer) == 0;
        case Failure::minexec: return true;
    }
    return false;
}

void count_failure(TaskSlot& s, Failure kind) noexcept {
    switch (kind) {
        case Failure::deadline: s.deadline_failures.fetch_add(1, std::memory_order_relaxed); break;
        case Failure::maxexec: s.maxexec_failures.fetch_add(1, std::memory_order_relaxed); break;
        case Failure::minexec: s.minexec_failures.fetch_add(1, std::memory_order_relaxed); break;
    }
}

// The cycle (or a job dropped before it began) is aborted: counted, and the
// thread jumps back to the mark armed before the cycle.
[[noreturn]] void abort_to_mark(ThreadState& t) noexcept {
    t.abort_armed = 0;
    t.cycle_aborted = 1;
    t.slot->aborted.fetch_add(1, std::memory_order_relaxed);
    siglongjmp(t.slot->mark, 1);
}

// Runs the user's handler at the handler priority and applies its action. May
// not return (abort_cycle jumps to the cycle mark).
FailureAction run_handler(ThreadState& t, Failure kind) noexcept {
    TaskSlot& s = *t.slot;
    const int before = t.raised_while_held ? t.crit_before_raise : current_crit(t);
    t.raised_while_held = false;
    const std::uint32_t sets_before = t.deadline_sets;
    if (t.handler_crit > 0) set_crit_internal(t, t.handler_crit);
    t.crit_set_in_handler = false;
    ++t.in_handler;
    const FailureAction action = t.handler ? t.handler(kind, t.user) : FailureAction::resume;
    --t.in_handler;
    if (!t.crit_set_in_handler) set_crit_internal(t, before);
    if (kind == Failure::deadline && t.deadline_sets == sets_before &&
        s.phase.load(std::memory_order_acquire) == Phase::job) {
        // The job goes on with the next period's time: its deadline moves one
        // period on, so a task that never completes fails once per period (the
        // watchdog sees the new deadline).
        const std::int64_t period = s.period_ns.load(std::memory_order_relaxed);
        const std::int64_t d = s.job_deadline_ns.load(std::memory_order_acquire);
        if (period > 0 && d != infinity) {
            s.job_deadline_ns.store(d + period, std::memory_order_release);
            // Under dynamic ranking the job now ranks by the later deadline:
            // the dispatcher re-ranks (no release may come to do it).
            if (t.impl && t.impl->ranks_at_release(s)) t.impl->notify();
        }
    }
    if (action == FailureAction::skip_next) t.skip_next = 1;
    // Failures raised while the handler ran (set_deadline's MINEXEC) follow it.
    if (t.in_handler == 0 && t.critical_depth == 0)
        for (unsigned more = t.pending.exchange(0); more != 0; more = t.pending.exchange(0))
            for (Failure k : {Failure::deadline, Failure::maxexec, Failure::minexec})
                if (more & bit(k)) run_handler(t, k);
    if (action == FailureAction::abort_cycle && !t.abort_armed && t.job_unstarted && kind == Failure::deadline)
        t.drop_job = 1;  // never begun: it is dropped when its cycle would start
    if (action == FailureAction::abort_cycle && t.abort_armed) abort_to_mark(t);
    return action;
}

// Delivers a failure now, or holds it off until the critical section ends.
void deliver(ThreadState& t, Failure kind) noexcept {
    count_failure(*t.slot, kind);
    if (t.critical_depth > 0) {
        t.pending.fetch_or(bit(kind), std::memory_order_relaxed);
        // §6.3: a handler of higher priority lifts the task at once, so a lock
        // holder is never left at the lower criticality.
        const int now_crit = current_crit(t);
        if (t.handler_crit > now_crit) {
            if (!t.raised_while_held) {
                t.raised_while_held = true;
                t.crit_before_raise = now_crit;
            }
            set_crit_internal(t, t.handler_crit);
        }
        return;
    }
    run_handler(t, kind);
}

void on_failure_signal(int sig, siginfo_t* info, void*) {
    const int saved_errno = errno;
    ThreadState& t = tl;
    if (t.slot) {
        const bool overrun = sig == SIGXCPU;
        const Failure kind =
            overrun ? Failure::maxexec : static_cast<Failure>(info->si_value.sival_int);
        if (still_applies(t, kind, overrun)) {
            if (kind == Failure::maxexec) t.budget_armed = false;
            if (kind == Failure::deadline) t.reported_deadline = t.slot->job_deadline_ns.load();
            deliver(t, kind);
        }
    }
    errno = saved_errno;
}

void install_once() {
    g_timer_signal = SIGRTMIN + 3;
    struct sigaction sa;
    std::memset(&sa, 0, sizeof sa);
    sa.sa_sigaction = on_failure_signal;
    sa.sa_flags = SA_SIGINFO | SA_RESTART;
    sigemptyset(&sa.sa_mask);
    sigaddset(&sa.sa_mask, g_timer_signal);
    sigaddset(&sa.sa_mask, SIGXCPU);
    if (sigaction(g_timer_signal, &sa, nullptr) != 0 || sigaction(SIGXCPU, &sa, nullptr) != 0)
        throw SchedError(std::string("muf: cannot install the timing-failure signal handlers: ") +
                         std::strerror(errno));
}

timer_t make_timer(clockid_t clock, Failure kind, pid_t tid, const char* what) {
    sigevent sev;
    std::memset(&sev, 0, sizeof sev);
    sev.sigev_notify = SIGEV_THREAD_ID;
    sev.sigev_signo = g_timer_signal;
    sev.sigev_value.sival_int = static_cast<int>(kind);
    sev._sigev_un._tid = tid;  // sigev_notify_thread_id; glibc 2.36 has no macro for it
    timer_t timer{};
    if (timer_create(clock, &sev, &timer) != 0)
        throw SchedError(std::string("muf: timer_create for the ") + what +
                         " timer failed: " + std::strerror(errno));
    return timer;
}

}  // namespace

void install_failure_signals() { std::call_once(g_signals_once, install_once); }

int timer_signal() noexcept { return g_timer_signal; }

void bind_thread(RtpuScheduler::Impl* impl, TaskSlot* slot, TaskHandle h) noexcept {
    ThreadState& t = tl;  // first touch allocates the thread's TLS block, outside any signal
    if (slot) t.crit_unbound = 0;
    t.impl = impl;
    t.slot = slot;
    t.handle = h;
    t.pending.store(0);
    t.abort_armed = 0;
    t.skip_next = 0;
    t.cycle_aborted = 0;
    t.reported_deadline = infinity;
    t.maxexec_timer_set = false;
    t.budget_armed = false;
    t.raised_while_held = false;
}

void create_budget_timer(TaskSlot& s) {
    const pid_t tid = static_cast<pid_t>(syscall(SYS_gettid));
    clockid_t cpu_clock;
    if (const int rc = pthread_getcpuclockid(pthread_self(), &cpu_clock); rc != 0)
        throw SchedError(std::string("muf: pthread_getcpuclockid failed: ") + std::strerror(rc));
    s.maxexec_timer = make_timer(cpu_clock, Failure::maxexec, tid, "MAXEXEC");
    s.maxexec_timer_created = true;
}

void delete_budget_timer(TaskSlot& s) noexcept {
    if (s.maxexec_timer_created) timer_delete(s.maxexec_timer);
    s.maxexec_timer_created = false;
}

int signal_deadline(pid_t tid) noexcept {
    siginfo_t info;
    std::memset(&info, 0, sizeof info);
    info.si_signo = g_timer_signal;
    info.si_code = SI_QUEUE;
    info.si_pid = getpid();
    info.si_uid = getuid();
    info.si_value.sival_int = static_cast<int>(Failure::deadline);
    return syscall(SYS_rt_tgsigqueueinfo, getpid(), tid, g_timer_signal, &info) == 0 ? 0 : errno;
}

void arm_budget(TaskSlot& s, std::int64_t budget_ns) noexcept {
    ThreadState& t = tl;
    const bool finite = budget_ns > 0 && budget_ns != infinity;
    t.budget_ns = finite ? budget_ns : infinity;
    t.budget_armed = finite;
    if (s.maxexec_timer_created && (finite || t.maxexec_timer_set)) {
        // Relative on the CPU clock: the budget counts from the CPU time now.
        // A task without a budget never arms it, so it costs no system call;
        // disarming (0) a budget set before matters: it must not fire later.
        const itimerspec its{{0, 0}, to_ts(finite ? budget_ns : 0)};
        timer_settime(s.maxexec_timer, 0, &its, nullptr);
        t.maxexec_timer_set = finite;
    } else if (finite && s.deadline_reserved.load(std::memory_order_relaxed)) {
        t.budget_cpu_start = thread_cpu_ns();
    }
}

bool job_ended(TaskSlot& s) noexcept {
    ThreadState& t = tl;
    const std::int64_t now = clock_ns();
    // Its own deadline, not the one a DEADLINE handler moved on.
    const std::int64_t own =
        s.job_release_ns.load(std::memory_order_relaxed) + s.rel_deadline_ns.load(std::memory_order_relaxed);
    const std::int64_t d = s.job_deadline_ns.load(std::memory_order_acquire);
    if (d != infinity && d != t.reported_deadline && now > d) {
        // Every deadline that passed unreported is a failure (the watchdog,
        // starved, may have reported none of them), the handler runs once.
        const std::int64_t period = s.period_ns.load(std::memory_order_relaxed);
        const std::int64_t passed = period > 0 ? 1 + (now - d) / period : 1;
        t.reported_deadline = d + (passed - 1) * period;
        if (passed > 1)
            s.deadline_failures.fetch_add(static_cast<std::uint64_t>(passed - 1), std::memory_order_relaxed);
        raise_failure_here(Failure::deadline);
    }
    return d != infinity && now > own;
}

void releases_skipped(TaskSlot& s, std::int64_t first_release, std::int64_t count) noexcept {
    ThreadState& t = tl;
    const std::int64_t period = s.period_ns.load(std::memory_order_relaxed);
    if (count <= 0 || period <= 0) return;
    // A skipped release's deadline may already be reported: a late job's
    // deadline moves one period on (to the next release's) at each report.
    const std::int64_t first_deadline = first_release + s.rel_deadline_ns.load(std::memory_order_relaxed);
    std::int64_t covered = 0;
    if (t.reported_deadline != infinity && t.reported_deadline >= first_deadline)
        covered = std::min(count, 1 + (t.reported_deadline - first_deadline) / period);
    const std::int64_t uncovered = count - covered;
    if (uncovered == 0) return;
    t.reported_deadline = first_deadline + (count - 1) * period;
    if (uncovered > 1)
        s.deadline_failures.fetch_add(static_cast<std::uint64_t>(uncovered - 1), std::memory_order_relaxed);
    raise_failure_here(Failure::deadline);
}

void deadline_passed_unstarted(TaskSlot& s, std::int64_t now) noexcept {
    ThreadState& t = tl;
    const std::int64_t d = s.job_deadline_ns.load(std::memory_order_acquire);
    if (d == infinity || d > now || d == t.reported_deadline) return;
    t.reported_deadline = d;
    raise_failure_here(Failure::deadline);
}

FailureAction raise_failure_here(Failure kind) noexcept {
    ThreadState& t = tl;
    if (!t.slot) return FailureAction::resume;
    count_failure(*t.slot, kind);
    if (t.critical_depth > 0 || t.in_handler > 0) {
        t.pending.fetch_or(bit(kind), std::memory_order_relaxed);
        return FailureAction::resume;
    }
    const sig_atomic_t armed = t.abort_armed;
    t.abort_armed = 0;  // no cycle to abort at a release
    const FailureAction action = run_handler(t, kind);
    t.abort_armed = armed;
    return action;
}

bool take_skip_next() noexcept {
    ThreadState& t = tl;
    const bool skip = t.skip_next != 0;
    t.skip_next = 0;
    return skip;
}

void clear_abort() noexcept {
    tl.abort_armed = 0;
    std::atomic_signal_fence(std::memory_order_seq_cst);
}

void set_abort_armed() noexcept {
    ThreadState& t = tl;
    t.cycle_aborted = 0;
    std::atomic_signal_fence(std::memory_order_seq_cst);
    t.abort_armed = 1;
    t.job_unstarted = 0;
    std::atomic_signal_fence(std::memory_order_seq_cst);
    if (t.drop_job && t.slot) {
        // Aborted at its deadline before it began: not run, counted as aborted.
        t.drop_job = 0;
        abort_to_mark(t);
    }
}

void mark_job_unstarted() noexcept {
    tl.drop_job = 0;
    std::atomic_signal_fence(std::memory_order_seq_cst);
    tl.job_unstarted = 1;
}

bool take_cycle_aborted() noexcept {
    const bool aborted = tl.cycle_aborted != 0;
    tl.cycle_aborted = 0;
    return aborted;
}

}  // namespace detail

// ------------------------------------------------------------------ task API

using detail::tl;

std::int64_t clock_ns() noexcept {
    timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return detail::from_ts(ts);
}

std::string_view to_string(Failure kind) noexcept {
    switch (kind) {
        case Failure::deadline: return "DEADLINE";
        case Failure::maxexec: return "MAXEXEC";
        case Failure::minexec: return "MINEXEC";
    }
    return "?";
}

void set_dfhandler(FailureHandler handler, int crit, void* user) noexcept {
    tl.handler = handler;
    tl.user = user;
    tl.handler_crit = crit;
}

void set_criticality(int crit) noexcept {
    if (tl.in_handler > 0) tl.crit_set_in_handler = true;
    tl.raised_while_held = false;  // an explicit choice replaces the temporary raise
    detail::set_crit_internal(tl, crit);
}

int criticality() noexcept { return detail::current_crit(tl); }

void set_deadline(std::int64_t start_ns, std::int64_t min_c_ns, std::int64_t max_c_ns,
                  std::int64_t deadline_ns) noexcept {
    detail::ThreadState& t = tl;
    if (!t.slot) return;
    detail::TaskSlot& s = *t.slot;
    const std::int64_t abs_deadline =
        deadline_ns == infinity ? infinity : start_ns + deadline_ns;
    ++t.deadline_sets;
    s.self_timed.store(true, std::memory_order_relaxed);
    s.job_release_ns.store(start_ns, std::memory_order_relaxed);
    s.job_deadline_ns.store(abs_deadline, std::memory_order_release);
    s.phase.store(detail::Phase::job, std::memory_order_release);
    detail::arm_budget(s, max_c_ns);
    if (t.impl && s.pacing.load(std::memory_order_relaxed) == detail::Pacing::dispatched)
        t.impl->notify();
    if (min_c_ns > 0 && abs_deadline != infinity) {
        const std::int64_t now = clock_ns();
        const std::int64_t from = now > start_ns ? now : start_ns;
        if (abs_deadline - from < min_c_ns) detail::raise_failure_here(Failure::minexec);
    }
}

void pause(std::int64_t restart_ns, std::int64_t min_c_ns, std::int64_t max_c_ns,
           std::int64_t deadline_ns) noexcept {
    detail::ThreadState& t = tl;
    if (t.slot) {
        detail::Phase job = detail::Phase::job;
        if (t.slot->phase.compare_exchange_strong(job, detail::Phase::waiting, std::memory_order_acq_rel) &&
            detail::job_ended(*t.slot))
            t.slot->missed.fetch_add(1, std::memory_order_relaxed);
    }
    const timespec ts = detail::to_ts(restart_ns);
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr) == EINTR) {
    }
    set_deadline(restart_ns, min_c_ns, max_c_ns, deadline_ns);
}

std::int64_t execstart() noexcept {
    tl.exec_start_cpu = detail::thread_cpu_ns();
    tl.exec_start_wall = clock_ns();
    return tl.exec_start_wall;
}

std::int64_t execend() noexcept {
    return tl.exec_start_wall + (detail::thread_cpu_ns() - tl.exec_start_cpu);
}

std::int64_t execleft() noexcept {
    detail::ThreadState& t = tl;
    if (!t.slot || t.budget_ns == infinity) return infinity;
    if (!t.budget_armed) return 0;
    if (t.slot->maxexec_timer_created) return detail::timer_left(t.slot->maxexec_timer);
    const std::int64_t left = t.budget_ns - (detail::thread_cpu_ns() - t.budget_cpu_start);
    return left > 0 ? left : 0;
}

void enter_critical() noexcept {
    tl.critical_depth = tl.critical_depth + 1;
    std::atomic_signal_fence(std::memory_order_seq_cst);
}

void leave_critical() noexcept {
    detail::ThreadState& t = tl;
    std::atomic_signal_fence(std::memory_order_seq_cst);
    if (t.critical_depth > 0) t.critical_depth = t.critical_depth - 1;
    if (t.critical_depth > 0 || !t.slot || t.in_handler > 0) return;
    // Held-off failures run now, in the order of their numbers.
    for (unsigned pending = t.pending.exchange(0); pending != 0; pending = t.pending.exchange(0)) {
        for (Failure kind : {Failure::deadline, Failure::maxexec, Failure::minexec})
            if (pending & detail::bit(kind)) detail::run_handler(t, kind);
    }
    if (t.raised_while_held) {
        t.raised_while_held = false;
        detail::set_crit_internal(t, t.crit_before_raise);
    }
}

}  // namespace chimera::muf
