// Internal structures of the muf Linux backends (not installed): the per-task
// slot shared by the task thread, the dispatcher and the set-up calls; the
// per-thread failure state; the policy helpers. See chimera/muf/rt.hpp.
#pragma once

#include <sys/types.h>
#include <time.h>

#include <array>
#include <atomic>
#include <csetjmp>
#include <cstdint>
#include <mutex>
#include <span>
#include <string>
#include <thread>
#include <vector>

#include "chimera/ipc/pi_mutex.hpp"
#include "chimera/muf/rt.hpp"

namespace chimera::muf::detail {

/// Tasks per RTPU: the user-priority field has 6 bits (§6.2.3: c, u >= log2 n).
inline constexpr int kMaxTasks = 64;

/// Where a task is in its period. Written with release/acquire ordering.
enum class Phase : std::uint32_t {
    waiting,   ///< no job pending: the next release starts one
    job,       ///< released, cycle not complete (the deadline is pending)
    detached,  ///< removed: wait_release returns Wake::detached
};

/// Lifetime of a slot.
enum class SlotState : std::uint32_t { free, added, attached, removed };

/// How the task thread waits for its releases.
enum class Pacing : std::uint32_t {
    dispatched,  ///< SCHED_FIFO by the MUF ranking (fifo backend; non-critical on deadline)
    self_paced,  ///< it sleeps to its own release (other backend, SCHED_DEADLINE, no privilege)
};

struct TaskSlot {
    // --- set-up data, written under Impl::mutex while the slot is not attached ---
    RtTaskParams params;
    std::string policy_text;

    // --- shared state ---
    std::atomic<SlotState> state{SlotState::free};
    std::atomic<Pacing> pacing{Pacing::dispatched};
    std::atomic<Phase> phase{Phase::waiting};
    std::atomic<std::uint32_t> release_word{0};   ///< futex: bumped at each release and at removal
    /// wait_release's reference form: the task's own word, bumped with release_word (interrupt_wait).
    std::atomic<std::atomic<std::uint32_t>*> own_word{nullptr};
    std::atomic<std::int64_t> period_ns{0};
    std::atomic<std::int64_t> rel_deadline_ns{0};
    std::atomic<std::int64_t> next_release_ns{0};  ///< the dispatcher's (or self-paced task's) timeline
    std::atomic<std::int64_t> job_release_ns{0};
    std::atomic<std::int64_t> job_deadline_ns{infinity};  ///< absolute; infinity: none
    std::atomic<bool> self_timed{false};  ///< uses pause()/set_deadline(): not released by the dispatcher
    std::atomic<int> crit{0};             ///< current criticality
    std::atomic<int> base_crit{0};        ///< from the assignment
    std::atomic<int> uprio{0};
    std::atomic<int> tid{0};
    std::atomic<int> fifo_prio{0};        ///< SCHED_FIFO priority set by the dispatcher (0: none)
    std::atomic<bool> deadline_reserved{false};  ///< SCHED_DEADLINE reservation

    // --- counters (RtTaskStatus) ---
    std::atomic<std::uint64_t> cycles{0}, missed{0}, deadline_failures{0}, maxexec_failures{0},
        minexec_failures{0}, aborted{0};

    // --- the task thread's own (read elsewhere only for status) ---
    sigjmp_buf mark;
    timer_t maxexec_timer{};
    bool maxexec_timer_created = false;
    /// The watchdog's: the job deadline it last signalled (no second signal for it).
    std::atomic<std::int64_t> watchdog_signalled{infinity};
    std::uint32_t control_seen = 0;  ///< self-paced: release_word value last seen
};

/// One entry of the urgency ranking (the ready tasks of an RTPU).
struct RankEntry {
    std::uint64_t urgency = 0;
    std::int64_t since_ns = 0;  ///< job release: first come, first served among equals
    int handle = 0;
    int current_prio = 0;       ///< 0: none yet
    int new_prio = 0;
    bool pending = false;       ///< its job is released (begun or not); else it waits for its release
};

/// The urgency a task keeps while its job (or, waiting, its next job) stands:
/// Figure 6.2's fields with the deadline as an absolute time, in ticks from
/// the RTPU's epoch (< 0: none), in the bits the criticality and user fields
/// leave (52 by default), so that two tasks' order does not depend on when it
/// is computed (Figure 6.2's field counts ticks to the deadline from now).
std::uint64_t standing_urgency(const UrgencyEncoding& enc, int crit, std::int64_t deadline_ticks,
                               int uprio) noexcept;
/// Sorts the entries most urgent first (ties first come first served, then by
/// handle). No allocation.
void sort_by_urgency(std::span<RankEntry> entries) noexcept;
/// Whether the current priorities already give MUF's order wherever it can
/// matter (entries sorted by sort_by_urgency): each pending job above every
/// less urgent pending job, each waiting task above every pending job less
/// urgent than its next job, all placed in [low, high). A waiting task may
/// stand above a more urgent pending job: released, it runs first and ranks
/// itself down before its job begins (RtpuScheduler::Impl::rank_at_release).
bool ranking_holds(std::span<const RankEntry> sorted, int low, int high) noexcept;
/// Gives the entries SCHED_FIFO priorities in [low, high) in urgency order
/// (highest urgency highest priority, ties first come first served), keeping a
/// task's current priority wherever the order allows so that only the tasks
/// that move are changed. Sorts `entries` by rank. No allocation.
void rank_priorities(std::span<RankEntry> entries, int low, int high) noexcept;

class Dispatcher;

}  // namespace chimera::muf::detail

namespace chimera::muf {

struct CHIMERA_LOCAL RtpuScheduler::Impl {
    explicit Impl(RtpuOptions o);
    ~Impl();

    RtpuOptions options;
    bool privileged = true;
    bool dispatcher_running = false;
    std::string dispatcher_policy;

    // Set-up calls (never taken by the dispatcher or in a cycle); inherits
    // priority: a task thread takes it to attach and detach itself, when it
    // may already run at its real-time priority.
    mutable ipc::PiMutex mutex;
    std::array<detail::TaskSlot, detail::kMaxTasks> slots;
    std::atomic<int> slot_count_seen{0};  // slots ever used (handles are below it)
    Assignment current_assignment;
    std::vector<int> assignment_handles;   // the handle of each task of current_assignment
    std::atomic<bool> uses_deadline{true};  // false for RM: no dynamic priority
    // The MUF order cannot change between releases (RM, or harmonic periods
    // with implicit deadlines): fixed priorities, tasks release themselves.
    std::atomic<bool> static_ranking{false};
    std::int64_t epoch_ns = 0;              // origin of the release timeline

    // Taken by whoever ranks (the dispatcher; under dynamic ranking each task
    // at its own release): one ranking at a time. Inherits priority.
    ipc::PiMutex rank_mutex;

    // Dispatcher wake-up word: bumped on criticality, deadline and set changes.
    std::atomic<std::uint32_t> event_word{0};
    std::atomic<bool> stopping{false};
    std::atomic<std::uint64_t> reschedules{0};
    std::atomic<std::uint64_t> priority_changes{0};
    std::atomic<std::uint64_t> watchdog_signals{0};  // DEADLINE signals sent by the watchdog
    std::atomic<int> dispatcher_tid{0};
    std::thread dispatcher;

    detail::TaskSlot* slot(TaskHandle h) noexcept;
    const detail::TaskSlot* slot(TaskHandle h) const noexcept;
    detail::TaskSlot& checked_slot(TaskHandle h, const char* what);  // throws SchedError
    /// Recomputes the MUF assignment of the tasks added; under `mutex`.
    void reassign();
    /// The data flows among the tasks of `handles` (indices into it), §6.2.4.
    std::vector<Flow> data_flows(const std::vector<int>& handles) const;
    /// Wakes the dispatcher (async-signal-safe).
    void notify() noexcept;
    void dispatcher_main() noexcept;
    /// Signals the jobs found past their deadlines; returns when to look again.
    std::int64_t watch_deadlines(std::int64_t now) noexcept;
    /// The ranking entries of the attached dispatched tasks (unsorted): under
    /// static ranking by their fixed urgency, otherwise by the job each has
    /// or, waiting, the job its next release begins (pending: released by `now`).
    std::size_t collect_ranking(std::int64_t now,
                                std::span<detail::RankEntry, detail::kMaxTasks> entries) noexcept;
    /// The dispatcher's ranking (events): applies the priorities, changing only
    /// those that move; under dynamic ranking only where the order does not
    /// hold (ranking_holds). Takes rank_mutex.
    void rank_and_apply(std::int64_t now) noexcept;
    /// Dynamic ranking, a task when it first runs after its release (`now`),
    /// before its job begins: nothing when the order holds (no lock, no system
    /// call); otherwise ranks under rank_mutex, its own change (`self`) last.
    void rank_at_release(std::int64_t now, int self) noexcept;
    /// Gives the entries priorities by rank and applies the changes.
    void apply_ranking(std::span<detail::RankEntry> entries, int self) noexcept;
    /// wait_release's body; own_word: `word` is the task's own (the reference form).
    Wake wait_for_release(TaskHandle h, const std::atomic<std::uint32_t>* word, std::uint32_t seen,
                          bool own_word) noexcept;
    /// True when the task ranks at its own release: a dispatched task under
    /// dynamic ranking (static ranking never changes at a release).
    bool ranks_at_release(const detail::TaskSlot& s) const noexcept {
        return s.pacing.load(std::memory_order_relaxed) == detail::Pacing::dispatched &&
               !static_ranking.load(std::memory_order_acquire);
    }
    /// The first release of a task attached now: the next instant of the
    /// timeline epoch + k·period.
    std::int64_t aligned_release(std::int64_t period_ns) const noexcept;
};

}  // namespace chimera::muf

namespace chimera::muf::detail {

// --- policy.cpp: pinning and scheduling classes --------------------------------

/// Pins the calling thread to `cpu`; 0 or the errno.
int pin_to_cpu(int cpu) noexcept;
/// "this process may run on CPUs 0-1": the process's cpuset, for a refusal
/// that needs a CPU of its own.
std::string process_cpus_text();
/// SCHED_FIFO at `prio` for thread `tid` (0: the caller); 0 or the errno.
int set_fifo(pid_t tid, int prio) noexcept;
/// SCHED_OTHER for thread `tid` (0: the caller); 0 or the errno.
int set_other(pid_t tid) noexcept;
/// SCHED_DEADLINE with SCHED_FLAG_DL_OVERRUN (SIGXCPU on overrun); 0 or the errno.
int set_deadline_policy(pid_t tid, std::int64_t runtime_ns, std::int64_t deadline_ns,
                        std::int64_t period_ns) noexcept;
/// Text of what the thread really runs under, from the kernel.
std::string describe_policy(pid_t tid);
/// Locks the process's memory (mlockall MCL_CURRENT | MCL_FUTURE) once per
/// process, unless CHIMERA_NO_MLOCK is set or the build has a sanitizer.
/// Returns "" when locked, else one line saying why not (said once by the caller).
std::string lock_memory();
/// Asks the kernel (PM QoS, /dev/cpu_dma_latency = 0, held open for the
/// process's life) to keep the CPUs out of slow idle states, as cyclictest
/// does; unless CHIMERA_NO_CPU_LATENCY is set. "" when held, else why not.
std::string hold_cpu_wakeup_latency();
/// The kernel's SCHED_DEADLINE bandwidth limit per CPU (sched_rt_runtime/period), or 0.95.
double deadline_bandwidth_per_cpu() noexcept;

// --- failure.cpp: per-thread failure state and signals --------------------------

/// Installs the process-wide handlers of the timer signal and SIGXCPU (once).
void install_failure_signals();
/// The real-time signal the timers send.
int timer_signal() noexcept;
/// Binds the calling thread to a task (nullptr unbinds); touches the
/// thread-local state so it is allocated before any signal can arrive.
void bind_thread(RtpuScheduler::Impl* impl, TaskSlot* slot, TaskHandle h) noexcept;
/// Creates the MAXEXEC timer (the thread's CPU clock), signalling this thread.
/// Throws SchedError.
void create_budget_timer(TaskSlot& s);
void delete_budget_timer(TaskSlot& s) noexcept;
/// At a release: arms MAXEXEC with `budget` (<= 0 or infinity: not armed; a
/// task without a budget makes no system call here). Async-signal-safe.
void arm_budget(TaskSlot& s, std::int64_t budget_ns) noexcept;
/// The job of the calling thread has ended (its phase already left `job`): if
/// it ended after its deadline and that failure was not reported yet, DEADLINE
/// is raised here, in the task (the handler runs; there is no cycle to abort).
/// Returns whether the job ended after its own deadline (a miss for the caller
/// to count). One clock read, no system call where the vDSO serves the clock.
bool job_ended(TaskSlot& s) noexcept;
/// `count` releases from `first_release` on were skipped (the task was still
/// busy): each deadline among them not reported yet is a DEADLINE failure
/// (the handler runs once), so a task's misses and failures agree.
void releases_skipped(TaskSlot& s, std::int64_t first_release, std::int64_t count) noexcept;
/// Dynamic ranking, at a release: a job whose deadline passed before it began
/// (it waited for the CPU behind more urgent jobs) is a DEADLINE failure, as
/// the watchdog signals a job begun; the handler runs, and abort_cycle drops
/// the job before it begins. Nothing when the deadline is ahead of `now`.
void deadline_passed_unstarted(TaskSlot& s, std::int64_t now) noexcept;
/// The watchdog's signal to task thread `tid`: its job is past its deadline.
/// 0 or the errno.
int signal_deadline(pid_t tid) noexcept;
/// Raises a failure in the calling thread outside a signal handler (MINEXEC at a
/// release); returns the handler's action. Counts it.
FailureAction raise_failure_here(Failure kind) noexcept;
/// Takes (and clears) the "skip the next cycle" request of the calling thread.
bool take_skip_next() noexcept;
/// Called by cycle_complete: a late abort turns into resume.
void clear_abort() noexcept;
void set_abort_armed() noexcept;
/// At a release: the job is pending and not begun (see set_abort_armed()).
void mark_job_unstarted() noexcept;
/// True (once) when the cycle that just ended was aborted by a handler.
bool take_cycle_aborted() noexcept;

}  // namespace chimera::muf::detail
