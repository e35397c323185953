// chimera/muf/rt.hpp — the Linux backends of the MUF scheduler and timing
// failures (thesis §6.2.3, §6.3; docs/architecture.md §9, §10).
//
// One RtpuScheduler per RTPU (one CPU). The task threads are created by the
// runtime (src/sbs); each one calls, in its own thread:
//
//   attach_current_thread(h);              // once: pin, policy, timers, signals
//   while (...) {
//       if (wait_release(h, &word, seen) != Wake::release) continue;
//       if (sigsetjmp(*cycle_mark(h), 0) == 0) { arm_abort(h); cycle(); }
//       else pthread_sigmask(SIG_SETMASK, &mask_at_start, nullptr);
//       cycle_complete(h);
//   }
//   detach_current_thread(h);
//
// Backends:
//  - fifo, static ranking: when the MUF order of the tasks cannot change
//    between releases — RM, or every period harmonic with the others and every
//    deadline equal to its period, where the earlier deadline always belongs to
//    the shorter period — each task gets a fixed SCHED_FIFO priority in urgency
//    order (criticality, then deadline, then user priority) and sleeps to its
//    own release on a futex with an absolute CLOCK_MONOTONIC timeout: the
//    kernel wakes the task itself, one wake-up per release, with no thread in
//    between (an hrtimer sleeper, which PREEMPT_RT expires in hard interrupt
//    context for real-time tasks, unlike POSIX timers). The dispatcher thread
//    then only re-ranks when the set or a criticality changes.
//  - fifo, dynamic ranking (any other set): each task still sleeps to its own
//    release, at the priority of the job that release begins: every task is
//    ranked by its urgency (Figure 6.2: criticality, then the deadline of its
//    job or, waiting, of its next job, then user priority). When it first runs
//    after its release it looks at the ranking; only where the MUF order no
//    longer holds does it give the task threads SCHED_FIFO priorities in
//    urgency order, changing only those that move and its own last (counted
//    in priority_changes()). Where the order holds, the release costs no
//    system call beyond the wait. The dispatcher thread re-ranks on
//    criticality and set changes and is the DEADLINE watchdog. RM and EDF are
//    the special cases of MUF (§6.2.3).
//  - deadline: tasks of the critical set become SCHED_DEADLINE reservations
//    (runtime = C, or E for a soft task; deadline and period = T) and the
//    kernel's admission control checks the set; a refusal is an error naming
//    the set's utilisation. Other tasks run on SCHED_FIFO below, ordered by the
//    dispatcher. The kernel admits SCHED_DEADLINE to a thread pinned to one CPU
//    only when that CPU is a root domain of its own: a critical task stays on
//    its RTPU's CPU through an exclusive cpuset partition, and is refused,
//    naming what to do, where the CPU is not one (docs/muf.md).
//  - other: SCHED_OTHER, best effort; timing failures still work.
// Without real-time privilege the scheduler warns once on stderr, runs best
// effort, and policy_of() reports what each thread really got.
//
// Timing failures (§6.3), delivered in the failing task's own thread:
//  - DEADLINE: found at the job's end, or by the RTPU's watchdog for a job still
//    running (docs/muf.md); every deadline passed counts one failure, and the
//    handler runs once per report;
//  - MAXEXEC: a timer on the thread's CPU-time clock (fifo/other), SIGXCPU from
//    SCHED_FLAG_DL_OVERRUN (deadline backend);
//  - MINEXEC: detected at the release, when less than the minimum execution
//    time is left before the deadline; that cycle is not started.
// The handler gets the kind; it may change the task's criticality, return
// FailureAction::skip_next or ::abort_cycle (siglongjmp to the mark the runtime
// armed before cycle). Inside enter_critical()/leave_critical() handlers are
// held off and run when the outermost section ends.
//
// Cycle code that may be aborted must not own resources whose destructors must
// run (the jump skips them); such code should not call arm_abort().
#pragma once

#include "chimera/export.hpp"

#include <atomic>
#include <csetjmp>
#include <cstdint>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "chimera/muf/analysis.hpp"

namespace chimera::muf {

enum class Backend { fifo, deadline, other };
CHIMERA_API std::string_view to_string(Backend backend) noexcept;
[[nodiscard]] CHIMERA_API std::optional<Backend> parse_backend(std::string_view text) noexcept;

/// The three timing failures, numbered as in the thesis.
enum class Failure : int { deadline = 1, maxexec = 2, minexec = 3 };
CHIMERA_API std::string_view to_string(Failure kind) noexcept;

/// What the runtime does after a handler returns.
enum class FailureAction {
    resume,       ///< continue where the task was
    skip_next,    ///< continue, and do not start the next cycle
    abort_cycle,  ///< siglongjmp to the cycle mark (if armed; else resume)
};

/// A timing-failure handler. It runs in the failing task's thread, possibly
/// from a signal handler: it may call the functions of this header and other
/// async-signal-safe code only (no allocation, no locks, no stdio).
using FailureHandler = FailureAction (*)(Failure kind, void* user);

/// Error from setting up a scheduler or task (admission refused, bad
/// parameters). Never thrown on the real-time path.
class CHIMERA_API SchedError : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

struct RtpuOptions {
    std::string name = "rtpu";     ///< for messages
    int cpu = 0;                   ///< the CPU this RTPU stands for
    Policy policy = Policy::muf;
    Backend backend = Backend::fifo;
    int fifo_low = 10;             ///< lowest SCHED_FIFO priority given to a task
    int fifo_high = 80;            ///< the dispatcher's priority; tasks get below it
    std::int64_t tick_ns = 1000;   ///< dynamic-priority tick (urgency encoding)
    UrgencyEncoding encoding{6, 32, 6};
    bool quiet = false;            ///< no warning on stderr without privilege
    /// CLOCK_MONOTONIC origin of the release timeline: a task without an
    /// explicit first release is released at epoch + k·period, so tasks of
    /// harmonic rates are released at the same instants whenever they were
    /// turned on. 0: the moment the scheduler is made.
    std::int64_t epoch_ns = 0;
    /// The DEADLINE watchdog's longest sleep: a job still running past its
    /// deadline is signalled at most max(0, watchdog_ns - D) after it (D its
    /// relative deadline), plus the watchdog's wake-up; a job that ends late is
    /// reported at its end whatever this is (docs/muf.md).
    std::int64_t watchdog_ns = 10'000'000;
};

/// One periodic task. Times in nanoseconds.
struct RtTaskParams {
    std::string name;
    std::int64_t period_ns = 0;
    std::int64_t wcet_ns = 0;        ///< C: used for the analysis and as MAXEXEC budget
    std::int64_t effective_ns = 0;   ///< E of a soft task (0: hard, E = C); MAXEXEC budget if set
    std::int64_t minexec_ns = 0;     ///< MINEXEC: 0 disables the check
    std::int64_t deadline_ns = 0;    ///< relative; 0 = period
    std::int64_t first_release_ns = 0;  ///< CLOCK_MONOTONIC; 0 = one period after attach
    bool maxexec_check = true;       ///< arm the MAXEXEC timer with the budget each cycle
    std::optional<int> crit;         ///< explicit criticality; else assign()
    std::optional<int> uprio;        ///< explicit user priority; else from the data flow
    /// State variables the task reads and writes. Flows between the tasks of
    /// one RTPU (an output of one that is an input of another) give the user
    /// priorities of §6.2.4 — a producer above its consumers — which break ties
    /// of equal criticality and deadline, re-derived whenever the set changes;
    /// so data crosses a chain of tasks of one rate within one period.
    std::vector<std::string> inputs, outputs;
};

using TaskHandle = int;

/// Result of wait_release.
enum class Wake {
    release,   ///< a cycle is due: run it
    command,   ///< the watched word changed (the runtime has a request)
    skipped,   ///< a release was skipped (MINEXEC or skip_next); call again
    detached,  ///< the task was removed
};

/// Per-task counters, written by the task and dispatcher, read by anyone.
struct RtTaskStatus {
    std::uint64_t cycles = 0;           ///< cycles completed
    /// Deadlines missed: a job that ended after its deadline (it is also a
    /// cycle) or was aborted, and each release skipped (late, at a handler's
    /// request, or for MINEXEC). Equals deadline_failures where no handler
    /// aborts, skips or moves deadlines.
    std::uint64_t missed = 0;
    std::uint64_t deadline_failures = 0;
    std::uint64_t maxexec_failures = 0;
    std::uint64_t minexec_failures = 0;
    std::uint64_t aborted = 0;          ///< cycles aborted by a handler
    int crit = 0;                       ///< current criticality
    int priority = 0;                   ///< SCHED_FIFO priority now (0 for DEADLINE/OTHER)
    int tid = 0;
};

class CHIMERA_API RtpuScheduler {
public:
    /// Starts the dispatcher (fifo and deadline backends). Throws SchedError.
    explicit RtpuScheduler(RtpuOptions options);
    ~RtpuScheduler();
    RtpuScheduler(const RtpuScheduler&) = delete;
    RtpuScheduler& operator=(const RtpuScheduler&) = delete;

    const RtpuOptions& options() const noexcept;
    /// False when real-time policies were refused (the one warning was given).
    bool privileged() const noexcept;

    /// Adds a task and recomputes the MUF assignment of the whole set (critical
    /// set, criticalities). Throws SchedError on bad parameters; on the deadline
    /// backend, admission is checked when the thread attaches.
    TaskHandle add_task(const RtTaskParams& params);
    /// Removes the task; a thread blocked in wait_release returns Wake::detached.
    void remove_task(TaskHandle h);
    /// Sets a new period (and deadline = period) from the next release.
    void set_period(TaskHandle h, std::int64_t period_ns);

    /// In the task's thread: pin to the CPU, take the policy, create the DEADLINE
    /// and MAXEXEC timers and make this the thread's current task for the
    /// timing-failure API below. Throws SchedError (e.g. admission refused:
    /// the message names the critical set's utilisation).
    void attach_current_thread(TaskHandle h);
    /// In the task's thread: timers deleted, policy back to SCHED_OTHER.
    void detach_current_thread(TaskHandle h) noexcept;

    /// In the task's thread: blocks until the next release, or until `*word` no
    /// longer holds `seen` (when word is given). Releases that passed while the
    /// previous cycle still ran are counted as missed. At the release the
    /// DEADLINE and MAXEXEC timers are armed; MINEXEC is checked here.
    Wake wait_release(TaskHandle h, const std::atomic<std::uint32_t>* word = nullptr,
                      std::uint32_t seen = 0) noexcept;
    /// The same for a runtime whose commands come from this process, and the
    /// cheaper form: `word` is the task's own wake-up word, the one futex the
    /// thread sleeps on (process-private: whoever changes it wakes it with
    /// ipc::futex_wake_all(word, ipc::FutexScope::process)). The scheduler
    /// bumps it too when the thread must look again (removed: Wake::detached
    /// at the next call), so a change the caller did not make is possible.
    Wake wait_release(TaskHandle h, std::atomic<std::uint32_t>& word, std::uint32_t seen) noexcept;
    /// In the task's thread, after cycle: disarms the timers, counts the cycle.
    void cycle_complete(TaskHandle h) noexcept;

    /// The mark an aborted cycle jumps to; the runtime does
    /// `if (sigsetjmp(*cycle_mark(h), 0) == 0) { arm_abort(h); cycle(); }`, and
    /// after a jump puts back the signal mask the thread runs with (a jump out
    /// of the failure handler leaves the timer signal blocked; saving the mask
    /// in sigsetjmp instead would cost a system call every cycle).
    sigjmp_buf* cycle_mark(TaskHandle h) noexcept;
    void arm_abort(TaskHandle h) noexcept;
    /// Once cycle has returned: a handler can no longer jump to the mark (the
    /// frame that set it may be gone). cycle_complete() does this too; call it
    /// earlier when the runtime has more to do in the job after cycle.
    void disarm_abort(TaskHandle h) noexcept;

    /// The policy the thread really got, e.g. "SCHED_FIFO 42 CPU 1",
    /// "SCHED_DEADLINE 2000000/10000000", "SCHED_OTHER (no privilege)".
    std::string policy_of(TaskHandle h) const;
    RtTaskStatus status(TaskHandle h) const noexcept;
    /// The release instant (CLOCK_MONOTONIC ns) of the task's current or last
    /// job — the one a released wait_release() returned for; 0 before the first.
    std::int64_t job_release_ns(TaskHandle h) const noexcept;
    /// The assignment in force (per added task, in handle order).
    Assignment assignment() const;
    /// Rankings applied (the dispatcher's, and a task's at a release where the
    /// MUF order no longer held) and the priority changes they made.
    std::uint64_t reschedules() const noexcept;
    std::uint64_t priority_changes() const noexcept;
    /// DEADLINE signals the watchdog sent (jobs found running past their deadline).
    std::uint64_t watchdog_signals() const noexcept;
    /// True while the fifo backend ranks statically (see the top of this file):
    /// tasks release themselves and the dispatcher is off the release path.
    bool static_ranking() const noexcept;

    struct Impl;

private:
    std::unique_ptr<Impl> impl_;
};

// --- The thesis's task API (§6.3–6.5), for the calling task thread ----------
// All are async-signal-safe and may be called from a failure handler. Times
// are CLOCK_MONOTONIC nanoseconds; `infinity` disables a deadline or budget.

inline constexpr std::int64_t infinity = INT64_MAX;

/// CLOCK_MONOTONIC now, in nanoseconds.
CHIMERA_API std::int64_t clock_ns() noexcept;

/// Installs the failure handler and its default criticality (the handler
/// priority: the task takes it while the handler runs, §6.3).
CHIMERA_API void set_dfhandler(FailureHandler handler, int crit, void* user = nullptr) noexcept;
/// Changes the calling task's criticality; the dispatcher re-ranks at once.
CHIMERA_API void set_criticality(int crit) noexcept;
CHIMERA_API int criticality() noexcept;
/// Sets MINEXEC, MAXEXEC and the deadline relative to `start`, without pausing.
CHIMERA_API void set_deadline(std::int64_t start_ns, std::int64_t min_c_ns, std::int64_t max_c_ns,
                              std::int64_t deadline_ns) noexcept;
/// Blocks until `restart_ns`, then set_deadline(restart, ...). A MINEXEC
/// failure is raised when less than min_c is left before the deadline.
CHIMERA_API void pause(std::int64_t restart_ns, std::int64_t min_c_ns, std::int64_t max_c_ns,
                       std::int64_t deadline_ns) noexcept;
/// Marks the start of a piece of work; returns the time now (ns).
CHIMERA_API std::int64_t execstart() noexcept;
/// The execstart() time plus the CPU time used since it, so execend() -
/// execstart() is the execution time of the piece of work.
CHIMERA_API std::int64_t execend() noexcept;
/// MAXEXEC budget left (ns; infinity when none).
CHIMERA_API std::int64_t execleft() noexcept;

/// Critical sections (table lock, queue operations): failure handlers are held
/// off until the outermost leave_critical(), where pending ones run. A held-off
/// handler with a higher criticality raises the task's at once (§6.3).
CHIMERA_API void enter_critical() noexcept;
CHIMERA_API void leave_critical() noexcept;

}  // namespace chimera::muf
