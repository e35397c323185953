// chimera/prof.hpp — automatic task profiling and the status segment
// (thesis §4.4.1 status fields, §6.7 automatic profiling, §6.4 execution
// profiles; docs/architecture.md §11).
//
// One shared-memory segment per subsystem, `/chimera.<subsystem>.status`,
// holds one slot per task. Each slot has three parts:
//
//   identity   rmod, rtpu, cpu, task type, SVAR names read/written. Written by
//              claim() under the header lock before the slot is marked in use.
//   info       tid, state, crit, scheduling policy in force, refF, the warning
//              count and first warning, the error message. Written by the task
//              thread (or by whoever claimed the slot before the thread starts /
//              after it ended) — one writer at a time, no lock.
//   profile    §6.7's n_c, n_m, q_t, q_min, q_max, the per-cycle histogram.
//              Written ONLY by the task's TaskProfiler, at cycle boundaries.
//
// Both writer-side groups are published with a sequence counter (seqlock): a
// reader in any process copies the group and retries if the counter moved, so
// readers get consistent snapshots and never block or slow the task beyond
// the cache lines they touch. The writers never wait for anything.
//
// Profiling epochs ("since last status", §4.4.1 / §6.7): each RTPU has an
// epoch number and the CLOCK_MONOTONIC time it started. reset_all() /
// reset_rtpu() bump it; a task notices at its next cycle boundary and zeroes
// its counters there (the reset is honoured by the writer, so it is lock-free
// for the task). Until then readers already show the task as reset (zeros).
// Warnings (count and first message) are reset by status resets only.
//
// Profiling windows per reader (issue 16.4): within an epoch every counter
// and histogram of a slot only grows, so a reader never needs to reset what
// the others see. A StatusWindow keeps, in the reader's own memory, a copy of
// each slot's counters at the moment it (re)started, and shows the difference:
// `status` at the sbs prompt, a network peer's `status` and each chimtop have
// their own window. An epoch change (the explicit `status reset`, which is the
// thesis's reset-on-status for everyone, a task turned on, an accounting
// change) ends every window of that RTPU: readers then show the counts since
// that reset. The minimum and maximum of a sum cannot be subtracted, so minC,
// maxC, minU and maxU are always since the RTPU's last reset, for every
// reader; the per-window tails are the window's own percentiles (below).
// The first cycle completed after a reset is counted in `cycle` but its CPU
// time is dropped from totC/minC/maxC/avgC, exactly as §6.7 does. A task
// turned on calls TaskProfiler::start(), which restarts profiling on its RTPU
// ("profiling is restarted on an RTPU whenever a new task begins execution").
//
// CPU time per cycle comes from the kernel's own per-thread run-time
// accounting, read without a system call in the steady state: a
// perf_event task-clock counter on the task thread, whose mmap'ed page the
// kernel rewrites at every context switch of the thread (with the thread's
// exact run time at that switch) under a sequence lock. cycle_begin() and
// cycle_end() read the page and CLOCK_MONOTONIC (vDSO). If the page's sequence
// did not move, the thread ran without being switched out, and its CPU time
// is the wall-clock difference — no system call. If it moved, the thread was
// preempted or blocked during the cycle: cycle_end() then reads the thread's
// CPU clock once (clock_gettime(CLOCK_THREAD_CPUTIME_ID), a system call only
// in cycles that already paid for a context switch) and takes the start from
// the page's count at the thread's last switch before cycle_begin(), i.e. the
// cycle is charged from its switch-in, as Chimera's context-switch
// accounting did; the preemption itself is never charged. The page's
// cap_user_time interpolation is not needed (and is not offered on
// paravirtualised machines, e.g. this project's VMs). Where perf_event_open
// is refused (seccomp, perf_event_paranoid 3, no CONFIG_PERF_EVENTS) the
// fallback reads CLOCK_THREAD_CPUTIME_ID at both ends (two system calls per
// cycle); the status says which source is in force (TaskStatus::cpu_clock).
//
// Release lateness and cycle time (issue 14.11): next to the CPU time, each
// cycle adds one count to two log-linear histograms of its slot (a few
// increments on the task thread, no system call): `lateness`, the wake-up
// time minus the release instant the job serves (periodic tasks; skipped
// releases are counted in `miss`), and `cycle_time`, the wall-clock time from
// the wake-up to the end of the cycle (out-vars written) — what LinuxCNC HAL
// reports as a thread's time. Buckets are exact below 16 ns and 1/16 of an
// octave wide above (a percentile is at most 6.25 % above the true value,
// never below), up to 2^32 ns; TimeHistogram::percentile_ns() gives p50, p99.
//
// Half-tick accounting (§6.7): with Accounting::half_tick and a tick T, each
// cycle's CPU time c is quantised as Chimera's kernel did for a cycle that
// starts on a clock tick: every whole tick counts 2 half-ticks, a final
// partial tick counts 1 (half_ticks(c) = 2*floor(c/T) + (c mod T != 0)), and
// ptime counts whole ticks. The default is Accounting::nanoseconds.
//
// Real-time contract: cycle_begin(), cycle_end(), missed() and all TaskSlot
// setters are noexcept, allocate nothing, take no lock and (steady state)
// make no system call. create/attach/claim/release/reset and TaskProfiler's
// constructor are set-up calls: they may allocate, lock and throw.
#pragma once

#include "chimera/export.hpp"

#include <array>
#include <bit>
#include <atomic>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

#include "chimera/ipc/lock.hpp"
#include "chimera/ipc/segment.hpp"

namespace chimera::prof {

// ---------------------------------------------------------------------------
// Vocabulary
// ---------------------------------------------------------------------------

/// Task type, the status field `S`.
enum class TaskType : char {
    periodic = 'P',
    synchronous = 'Y',
    sporadic = 'S',    ///< sporadic server
    deferrable = 'D',  ///< deferrable server
    background = 'B',  ///< background server
};

/// Task state, the status field `state` (docs/architecture.md §7).
enum class TaskState : std::uint32_t {
    not_created = 0,
    off = 1,
    on = 2,
    error = 3,
    spawning = 4,  ///< in init (reading in-consts, init, writing out-consts)
    killing = 5,   ///< in kill
};
/// "NOT-CREATED", "OFF", "ON", "ERROR", "SPAWNING", "KILLING".
CHIMERA_API const char* to_string(TaskState state) noexcept;

/// How per-cycle CPU time is quantised.
enum class Accounting : std::uint32_t {
    nanoseconds = 0,  ///< exact, the default
    half_tick = 1,    ///< the thesis's half-tick quantisation (§6.7)
};
CHIMERA_API const char* to_string(Accounting accounting) noexcept;

/// Where a task's CPU time comes from (shown in the status; never silent).
enum class CpuClock : std::uint32_t {
    none = 0,             ///< no TaskProfiler attached yet
    perf_switch = 1,      ///< perf task-clock page + vDSO clock: 0 syscalls unless switched out
    thread_cputime = 2,   ///< fallback: CLOCK_THREAD_CPUTIME_ID at both ends (2 syscalls/cycle)
};
/// "none", "perf-page", "thread-cputime".
CHIMERA_API const char* to_string(CpuClock clock) noexcept;

/// Half-ticks for `cpu_ns` of CPU time with a tick of `tick_ns` (> 0): whole
/// ticks count 2, a trailing partial tick counts 1 (§6.7).
constexpr std::uint64_t half_ticks(std::uint64_t cpu_ns, std::uint64_t tick_ns) noexcept {
    return 2 * (cpu_ns / tick_ns) + (cpu_ns % tick_ns != 0 ? 1 : 0);
}

// ---------------------------------------------------------------------------
// Shared-memory layout (version kStatusLayoutVersion). Plain structs, offsets
// only; sizes checked below. Strings are NUL-terminated, truncated to fit.
// ---------------------------------------------------------------------------

inline constexpr std::uint32_t kStatusLayoutVersion = 2;
inline constexpr std::size_t kNameMax = 32;      ///< rmod name (incl. NUL)
inline constexpr std::size_t kPolicyMax = 48;    ///< policy text (incl. NUL)
inline constexpr std::size_t kMessageMax = 160;  ///< WARNING>/ERROR> text (incl. NUL)
inline constexpr std::size_t kVarListMax = 256;  ///< "a,b,c" SVAR names (incl. NUL)
inline constexpr std::size_t kSubsystemMax = 64;
inline constexpr std::size_t kHistogramBuckets = 64;  ///< last bucket collects overflow
inline constexpr std::uint32_t kMaxRtpus = 64;

/// Log-linear time buckets: values below 2^kTimeSubBits ns have a bucket each;
/// above, every octave [2^e, 2^(e+1)) is cut into 2^kTimeSubBits equal buckets;
/// from 2^kTimeMaxBits ns on, one overflow bucket.
inline constexpr unsigned kTimeSubBits = 4;
inline constexpr unsigned kTimeMaxBits = 32;  ///< 2^32 ns = 4.29 s
inline constexpr std::size_t kTimeSub = std::size_t{1} << kTimeSubBits;
inline constexpr std::size_t kTimeOverflowBucket = kTimeSub + (kTimeMaxBits - kTimeSubBits) * kTimeSub;
inline constexpr std::size_t kTimeBuckets = kTimeOverflowBucket + 1;

/// The bucket of a duration of `ns` nanoseconds.
constexpr std::size_t time_bucket(std::uint64_t ns) noexcept {
    if (ns < kTimeSub) return static_cast<std::size_t>(ns);
    const auto e = static_cast<unsigned>(std::bit_width(ns)) - 1;  // floor(log2(ns)): one instruction
    if (e >= kTimeMaxBits) return kTimeOverflowBucket;
    const unsigned shift = e - kTimeSubBits;
    return kTimeSub + (e - kTimeSubBits) * kTimeSub + static_cast<std::size_t>((ns >> shift) - kTimeSub);
}
/// Smallest and largest duration (ns, inclusive) of bucket `b`; the overflow
/// bucket's largest is UINT64_MAX.
constexpr std::uint64_t time_bucket_low(std::size_t b) noexcept {
    if (b < kTimeSub) return b;
    if (b >= kTimeOverflowBucket) return std::uint64_t{1} << kTimeMaxBits;
    const std::size_t k = b - kTimeSub;
    const unsigned shift = static_cast<unsigned>(k / kTimeSub);
    return static_cast<std::uint64_t>(kTimeSub + k % kTimeSub) << shift;
}
constexpr std::uint64_t time_bucket_high(std::size_t b) noexcept {
    if (b >= kTimeOverflowBucket) return UINT64_MAX;
    return b + 1 < kTimeSub ? b : time_bucket_low(b + 1) - 1;
}

/// Per-RTPU profiling epoch. Written under the header lock (seq odd while
/// writing); read lock-free by tasks and readers. `name` and `cpu` are set
/// at creation (the .sbs's RTPU name and CPU) and never change.
struct alignas(64) RtpuBlock {
    std::atomic<std::uint32_t> seq;
    std::atomic<std::uint32_t> epoch;       ///< bumped by every reset
    std::atomic<std::int64_t> start_ns;     ///< CLOCK_MONOTONIC at the reset (Q_start)
    std::atomic<std::int64_t> tick_ns;      ///< the RTPU's accounting tick
    std::atomic<std::uint32_t> accounting;  ///< Accounting, applied from the next reset
    /// Bumped by status resets only (reset_all/reset_rtpu), not by a task
    /// starting: warnings are "since the last status command" (§4.4.1).
    std::atomic<std::uint32_t> status_epoch;
    std::int32_t cpu;                       ///< -1: not given
    char name[kNameMax];                    ///< "" when not given (shown as its number)
    std::uint8_t reserved[28];
};
static_assert(sizeof(RtpuBlock) == 128);

/// The profile group of a slot: written only by the task's TaskProfiler.
struct ProfileData {
    std::atomic<std::uint32_t> seq;
    std::atomic<std::uint32_t> epoch_seen;   ///< the RTPU epoch these counters belong to
    std::atomic<std::uint32_t> cpu_clock;    ///< CpuClock
    std::atomic<std::uint32_t> accounting;   ///< Accounting in force for these counters
    std::atomic<std::int64_t> unit_num;      ///< one count unit = unit_num/unit_den ns
    std::atomic<std::int64_t> unit_den;
    std::atomic<std::uint64_t> cycles;       ///< n_c
    std::atomic<std::uint64_t> misses;       ///< n_m
    std::atomic<std::uint64_t> accounted;    ///< cycles whose time is in q_t (n_c minus the dropped first)
    std::atomic<std::uint64_t> q_total;      ///< q_t, in units
    std::atomic<std::uint64_t> q_min;        ///< in units; UINT64_MAX when none
    std::atomic<std::uint64_t> q_max;        ///< in units
    std::atomic<std::uint64_t> q_last;       ///< last cycle, in units (also the dropped one)
    std::atomic<std::uint64_t> switched;     ///< cycles during which the thread was switched out
    std::atomic<std::int64_t> last_end_ns;   ///< CLOCK_MONOTONIC of the last cycle_end
    std::atomic<std::uint64_t> hist_width_ns;///< 0: histogram off
    std::atomic<std::uint32_t> hist[kHistogramBuckets];  ///< per-cycle CPU time, ns buckets
    std::atomic<std::uint64_t> lateness[kTimeBuckets];    ///< wake-up minus release, per cycle
    std::atomic<std::uint64_t> cycle_time[kTimeBuckets];  ///< wake-up to end of cycle, wall clock
};

/// The info group of a slot.
struct InfoData {
    std::atomic<std::uint32_t> seq;
    std::atomic<std::int32_t> tid;
    std::atomic<std::uint32_t> state;         ///< TaskState
    std::atomic<std::int32_t> crit;
    std::atomic<std::uint64_t> ref_freq_bits; ///< refF (double) as bits
    std::atomic<std::uint32_t> warn_epoch;    ///< RTPU status_epoch the warning count belongs to
    std::atomic<std::uint32_t> warnings;
    std::atomic<std::uint32_t> has_error;
    std::atomic<std::int32_t> depth;          ///< writer-private nesting count (signal handlers)
    char policy[kPolicyMax];
    char warning[kMessageMax];                ///< first warning since the last reset
    char error[kMessageMax];
};

/// One task's slot.
struct alignas(64) TaskSlotData {
    std::atomic<std::uint32_t> in_use;      ///< 0 free, 1 claimed (identity valid)
    std::atomic<std::uint32_t> generation;  ///< bumped by every claim and release
    std::int32_t rtpu;
    std::int32_t cpu;
    std::uint32_t type;                     ///< TaskType character
    std::uint32_t reserved0;
    char rmod[kNameMax];
    char inputs[kVarListMax];               ///< SVAR names the task reads, comma-separated
    char outputs[kVarListMax];              ///< SVAR names the task writes
    alignas(64) InfoData info;
    alignas(64) ProfileData profile;
};

/// The segment body after the common ipc::SegmentHeader.
struct StatusHeader {
    ipc::SegmentHeader segment;
    ipc::LockWord lock;                     ///< claim/release/reset
    std::uint32_t max_tasks;
    std::uint32_t rtpus;                    ///< number of RtpuBlocks
    std::atomic<std::uint32_t> generation;  ///< bumped by every claim/release
    std::uint32_t reserved0;
    ipc::Offset<RtpuBlock> rtpu_blocks;
    ipc::Offset<TaskSlotData> slots;
    char subsystem[kSubsystemMax];
    std::uint8_t reserved[32];
};
static_assert(sizeof(StatusHeader) == 256);
static_assert(std::atomic<std::int64_t>::is_always_lock_free);

// ---------------------------------------------------------------------------
// Derived status (§4.4.1), as readers see it
// ---------------------------------------------------------------------------

/// Counts of durations in the time buckets above (release lateness, cycle time).
struct CHIMERA_API TimeHistogram {
    std::array<std::uint64_t, kTimeBuckets> counts{};

    std::uint64_t total() const noexcept;
    /// The nearest-rank percentile: the largest value of the bucket that holds
    /// the ceil(ppm/1e6 * n)-th smallest sample (ppm in parts per million:
    /// 500000 is p50, 990000 p99; 0 counts as the first sample). nullopt when
    /// empty; UINT64_MAX when that sample is in the overflow bucket.
    [[nodiscard]] std::optional<std::uint64_t> percentile_ns(std::uint32_t ppm) const noexcept;
    /// Largest value of the highest non-empty bucket (nullopt when empty).
    [[nodiscard]] std::optional<std::uint64_t> max_ns() const noexcept;
    /// Counts of `now` that are not in `base` (bucket by bucket).
    static TimeHistogram since(const TimeHistogram& now, const TimeHistogram& base) noexcept;
};

/// Per-cycle CPU-time histogram: bucket i counts cycles with
/// i*width <= c < (i+1)*width; the last bucket also holds everything above.
struct CHIMERA_API Histogram {
    std::uint64_t bucket_width_ns = 0;  ///< 0: off
    std::array<std::uint32_t, kHistogramBuckets> counts{};

    std::uint64_t total() const noexcept;
    /// The execution profile Ψ(t) of §6.4 at the bucket edges: the fraction
    /// of cycles that finished within (i+1)*width.
    double psi(std::size_t bucket) const noexcept;
    /// Effective execution time E for a hardness H in (0, 1] (§6.4): the
    /// smallest bucket upper edge t with Ψ(t) >= H, in ns. nullopt when
    /// the histogram is empty or H is reached only in the overflow bucket
    /// (the profile does not bound E).
    [[nodiscard]] std::optional<std::uint64_t> effective_ns(double hardness) const noexcept;
};

/// One task's status: the §4.4.1 fields plus what the Linux port adds.
/// Times in seconds, utilisations in percent.
struct TaskStatus {
    std::uint32_t slot = 0;
    std::string rmod;
    int rtpu = 0;
    int cpu = -1;
    int tid = 0;
    char type = 'P';           ///< S
    int crit = 0;
    TaskState state = TaskState::not_created;
    std::uint64_t cycle = 0;   ///< since the last reset
    std::uint64_t miss = 0;
    double ref_f = 0;          ///< refF, Hz (0: aperiodic)
    double ref_t = 0;          ///< refT = 1/refF
    double mez_f = 0;          ///< cycles / ptime
    double mez_t = 0;          ///< ptime / (cycle + miss), rounded to the nearest tick
    double ptime = 0;          ///< profiling time since the RTPU's last reset
    double tot_c = 0;          ///< CPU time of the accounted cycles
    double tick = 0;           ///< resolution: the tick (half-tick mode) or 1 ns
    double min_u = 0, max_u = 0, avg_u = 0;
    double min_c = 0, max_c = 0, avg_c = 0;
    std::uint32_t warn = 0;
    std::string warning;       ///< first warning since the last reset ("" if none)
    std::string error;         ///< set while state is ERROR
    std::string policy;        ///< scheduling policy actually in force
    std::string inputs, outputs;
    CpuClock cpu_clock = CpuClock::none;
    Accounting accounting = Accounting::nanoseconds;
    bool reset_pending = false;  ///< the task has not yet seen the RTPU's reset
    std::uint64_t accounted = 0; ///< cycles whose CPU time is in totC
    std::uint64_t switched = 0;  ///< cycles preempted or blocked part-way
    double last_c = 0;           ///< CPU time of the last cycle
    Histogram histogram;
    TimeHistogram lateness;      ///< release lateness per cycle (periodic tasks)
    TimeHistogram cycle_time;    ///< wake-up to end of cycle per cycle (wall clock)
    std::string rtpu_name;       ///< the RTPU's name in the .sbs ("" when not given)
    bool consistent = true;      ///< see RawSlot::consistent
    /// Set by StatusWindow: the counts are since this reader's window began
    /// (false: since the RTPU's last reset).
    bool windowed = false;
};

/// Raw, consistent copies of one slot (what the seqlocks protect).
struct RawSlot {
    std::uint32_t index = 0;
    std::uint32_t generation = 0;
    std::string rmod, inputs, outputs;
    int rtpu = 0, cpu = -1;
    char type = 'P';
    // info
    int tid = 0;
    TaskState state = TaskState::not_created;
    int crit = 0;
    double ref_f = 0;
    std::uint32_t warn_epoch = 0, warnings = 0;
    bool has_error = false;
    std::string policy, warning, error;
    // profile
    std::uint32_t epoch_seen = 0;
    CpuClock cpu_clock = CpuClock::none;
    Accounting accounting = Accounting::nanoseconds;
    std::int64_t unit_num = 1, unit_den = 1;
    std::uint64_t cycles = 0, misses = 0, accounted = 0, q_total = 0, q_min = UINT64_MAX,
                  q_max = 0, q_last = 0, switched = 0;
    std::int64_t last_end_ns = 0;
    Histogram histogram;
    TimeHistogram lateness, cycle_time;
    /// False when a group could not be read consistently within the reader's
    /// timeout (its writer died, or stayed preempted, inside its window).
    bool consistent = true;
};

/// One RTPU's profiling epoch as read consistently.
struct RtpuEpoch {
    std::uint32_t epoch = 0;
    std::uint32_t status_epoch = 0;
    std::int64_t start_ns = 0;
    std::int64_t tick_ns = 1;
    Accounting accounting = Accounting::nanoseconds;
    std::string name;  ///< as in the .sbs ("" when not given)
    int cpu = -1;
};

/// The §4.4.1 / §6.7 derivation, a pure function (exact tests use it with a
/// chosen `now_ns`). ptime = now − start (whole ticks in half-tick mode).
CHIMERA_API TaskStatus derive(const RawSlot& raw, const RtpuEpoch& rtpu, std::int64_t now_ns);

/// One reader's window, a pure function: the status of `now` counted since
/// `base` (the same slot's copy taken at `base_ns`). When `base` is null, is
/// another task (generation) or another profiling epoch, or the task has not
/// yet seen the RTPU's current epoch, the window is the RTPU's epoch: the
/// result is derive(now, rtpu, now_ns). Otherwise every counter, the warning
/// count and the histograms are differences, ptime runs from base_ns, and
/// minC/maxC stay the epoch's (see the top of this file).
CHIMERA_API TaskStatus derive_window(const RawSlot& now, const RawSlot* base, std::int64_t base_ns,
                                     const RtpuEpoch& rtpu, std::int64_t now_ns);

// ---------------------------------------------------------------------------
// Errors
// ---------------------------------------------------------------------------

/// A set-up failure (segment full, bad RTPU, ...); what() names the segment
/// and object.
class CHIMERA_API StatusError : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

// ---------------------------------------------------------------------------
// Writer side
// ---------------------------------------------------------------------------

/// What claim() needs to know about a task.
struct TaskIdentity {
    std::string_view rmod;
    int rtpu = 0;                   ///< 0 .. rtpus-1
    int cpu = -1;                   ///< CPU the thread is pinned to (-1: unknown)
    TaskType type = TaskType::periodic;
    double ref_freq = 0;            ///< refF in Hz (0 for aperiodic tasks)
    int crit = 0;
    std::string_view inputs;        ///< "a,b,c": SVARs read (shown by chimtop)
    std::string_view outputs;       ///< SVARs written
};

/// A claimed slot, as a small non-owning handle (valid while the
/// StatusSegment that claimed it is alive and until release()). Copyable:
/// the runtime keeps one and gives one to the task's TaskProfiler.
/// Setters: one writer at a time — the task's thread, or the claimer before
/// the thread starts / after it has ended. All are noexcept, lock-free and
/// allocation-free; strings are truncated to fit.
class CHIMERA_API TaskSlot {
public:
    TaskSlot() noexcept = default;
    bool valid() const noexcept { return slot_ != nullptr; }
    std::uint32_t index() const noexcept;
    int rtpu() const noexcept;

    void set_tid(int tid) noexcept;
    void set_state(TaskState state) noexcept;
    void set_crit(int crit) noexcept;
    void set_ref_freq(double hz) noexcept;
    /// The scheduling policy actually in force, e.g. "SCHED_FIFO 80",
    /// "SCHED_DEADLINE 1000/5000 us", "SCHED_OTHER (no RT privilege)".
    void set_policy(std::string_view policy) noexcept;
    /// Counts a warning; keeps the first message since the last reset.
    void warning(std::string_view message) noexcept;
    /// Sets the ERROR> line (does not change `state`: the runtime does).
    void error(std::string_view message) noexcept;
    void clear_error() noexcept;

    TaskSlotData* data() const noexcept { return slot_; }
    StatusHeader* header() const noexcept { return header_; }

private:
    friend class StatusSegment;
    friend class TaskProfiler;
    TaskSlot(StatusHeader* header, TaskSlotData* slot) noexcept : header_(header), slot_(slot) {}
    void info_begin() noexcept;
    void info_end() noexcept;

    StatusHeader* header_ = nullptr;
    TaskSlotData* slot_ = nullptr;
};

/// Options for StatusSegment::create().
struct StatusOptions {
    std::uint32_t rtpus = 0;        ///< 0: one per online CPU
    Accounting accounting = Accounting::nanoseconds;
    std::int64_t tick_ns = 1'000'000;  ///< used in half-tick mode
    /// Unlink a segment of the same name left by a process that died.
    bool replace_stale = true;
    /// Owner read-write, the watch group read-only (chimtop as a member of
    /// group chimera: docs/permissions.md); 0600 for the owner alone.
    mode_t mode = 0640;
    /// The RTPUs' names and CPUs as in the .sbs (index = RTPU number); shorter
    /// lists leave the rest unnamed. A name is cut to kNameMax - 1 characters.
    std::vector<std::string> rtpu_names;
    std::vector<int> rtpu_cpus;
};

/// The status segment of one subsystem (owned by the master). Move-only.
/// Destruction destroys the segment if this is its last user.
class CHIMERA_API StatusSegment {
public:
    StatusSegment() = default;
    StatusSegment(StatusSegment&&) noexcept = default;
    /// Closes the segment held before (as the destructor does), then moves.
    StatusSegment& operator=(StatusSegment&& other) noexcept;
    ~StatusSegment();
    /// The destructor's work, early: the creator removes the segment (readers
    /// keep their mapping and see it destroyed); another user detaches.
    void close() noexcept;

    /// Creates `/chimera.<subsystem>.status` with room for `max_tasks` tasks.
    static StatusSegment create(std::string_view subsystem, std::uint32_t max_tasks,
                                const StatusOptions& options = {});
    /// Attaches to an existing one (e.g. a second writer process).
    static StatusSegment attach(std::string_view subsystem);

    /// Takes a free slot for a task (set-up path; throws StatusError when full
    /// or the RTPU is out of range). The slot starts at state NOT-CREATED,
    /// zero counters, in the RTPU's current epoch.
    TaskSlot claim(const TaskIdentity& identity);
    /// Frees a slot (the task has been killed). The handle becomes invalid.
    void release(TaskSlot& slot);

    /// "Since last status": restarts profiling on every RTPU / on one.
    void reset_all();
    void reset_rtpu(int rtpu);
    /// Accounting mode and tick of an RTPU, in force from its next reset
    /// (this call also resets it).
    void set_accounting(int rtpu, Accounting accounting, std::int64_t tick_ns);

    /// Consistent snapshot of every task (now: CLOCK_MONOTONIC unless given).
    std::vector<TaskStatus> snapshot() const;
    std::vector<TaskStatus> snapshot(std::int64_t now_ns) const;

    std::uint32_t max_tasks() const noexcept;
    std::uint32_t rtpus() const noexcept;
    const std::string& name() const noexcept { return segment_.name(); }
    StatusHeader* header() const noexcept;
    bool valid() const noexcept { return segment_.valid(); }

private:
    explicit StatusSegment(ipc::Segment segment) noexcept : segment_(std::move(segment)) {}
    ipc::Segment segment_;
};

/// A read-only view from any process (chimtop, the sbs CLI). Never writes the
/// task groups; reset requests only bump RTPU epochs.
class CHIMERA_API StatusReader {
public:
    StatusReader() = default;
    /// Attaches by subsystem name; throws ipc::SegmentError if absent.
    static StatusReader attach(std::string_view subsystem);
    /// Like attach(), nullopt if the segment does not exist (yet).
    [[nodiscard]] static std::optional<StatusReader> try_attach(std::string_view subsystem);
    /// Like try_attach(), and says why not: `error_number` gets the errno of
    /// the failure (ENOENT: no such subsystem; EACCES: this user may not open
    /// its segment; 0: another reason, e.g. another layout) and `why` the message.
    [[nodiscard]] static std::optional<StatusReader> try_attach(std::string_view subsystem, int& error_number,
                                                                std::string& why);
    /// Maps the segment read-only, as a watcher (chimtop; docs/permissions.md):
    /// a member of the watch group may, and the reads are the same seqlocked
    /// copies; it is not a user of the segment (keeps nothing alive) and its
    /// resets and set_accounting() throw StatusError "permission denied".
    static StatusReader watch(std::string_view subsystem);
    /// Like watch(), nullopt with the reason as try_attach() says it (EACCES:
    /// the message says what to do, ipc::permission_advice()).
    [[nodiscard]] static std::optional<StatusReader> try_watch(std::string_view subsystem, int& error_number,
                                                               std::string& why);
    /// True for a watcher's reader.
    bool read_only() const noexcept { return segment_.read_only(); }

    std::vector<TaskStatus> snapshot() const;
    std::vector<TaskStatus> snapshot(std::int64_t now_ns) const;
    /// Raw consistent copy of one slot (nullopt if free).
    [[nodiscard]] std::optional<RawSlot> raw(std::uint32_t index) const;
    RtpuEpoch rtpu_epoch(int rtpu) const;

    /// The explicit reset of the thesis (`status reset`): snapshot, then
    /// reset every RTPU — every reader's counts restart. A reader that only
    /// wants its own "since the last status" uses a StatusWindow.
    std::vector<TaskStatus> status_and_reset();
    void reset_all();
    void reset_rtpu(int rtpu);
    /// As StatusSegment::set_accounting, from any process (e.g. `chimtop
    /// --half-tick`, to compare figures with the thesis's): resets the RTPU.
    void set_accounting(int rtpu, Accounting accounting, std::int64_t tick_ns);

    /// True while the segment is published and its creator process exists.
    bool alive() const noexcept;
    /// Creation time of the attached segment (tells a restarted subsystem apart).
    std::int64_t created_ns() const noexcept;
    /// The process that created the segment (the subsystem's master).
    int creator_pid() const noexcept;
    const std::string& name() const noexcept { return segment_.name(); }
    std::string subsystem() const;
    std::uint32_t max_tasks() const noexcept;
    std::uint32_t rtpus() const noexcept;
    bool valid() const noexcept { return segment_.valid(); }

private:
    explicit StatusReader(ipc::Segment segment) noexcept : segment_(std::move(segment)) {}
    static std::optional<StatusReader> try_map(std::string_view subsystem, bool watcher, int& error_number,
                                               std::string& why);
    void check_writable(const char* what) const;
    ipc::Segment segment_;
};

/// One reader's profiling window (issue 16.4): counts since this window
/// began, without touching what other readers see. Lives in the reader's own
/// memory; restart() takes the current counters of every slot as its
/// baseline. A window never started shows the counts since each RTPU's last
/// reset. Not thread-safe (one per reader).
class CHIMERA_API StatusWindow {
public:
    /// The status of every task counted over this window (now: CLOCK_MONOTONIC
    /// unless given).
    std::vector<TaskStatus> snapshot(const StatusReader& reader) const;
    std::vector<TaskStatus> snapshot(const StatusReader& reader, std::int64_t now_ns) const;
    /// Starts the window again now.
    void restart(const StatusReader& reader);
    void restart(const StatusReader& reader, std::int64_t now_ns);
    /// The thesis's "since the last status command", for this reader only:
    /// the snapshot of the window, which then restarts at the same instant.
    std::vector<TaskStatus> take(const StatusReader& reader);
    /// When the window last restarted (0: never).
    std::int64_t started_ns() const noexcept { return started_ns_; }

private:
    std::vector<std::optional<RawSlot>> base_;  // by slot index
    std::int64_t started_ns_ = 0;
};

/// The task's own profiler. Construct it IN the task thread (it opens the
/// per-thread CPU-time counter and records the tid); the four cycle calls
/// are then made by that thread only. Move-only; destroying it closes the
/// counter (the slot keeps its last values).
class CHIMERA_API TaskProfiler {
public:
    TaskProfiler() noexcept = default;
    /// Opens the CPU-time source for the calling thread; `allow_perf=false`
    /// forces the thread-cputime fallback (tests, comparisons).
    explicit TaskProfiler(TaskSlot slot, bool allow_perf = true);
    TaskProfiler(TaskProfiler&& other) noexcept;
    TaskProfiler& operator=(TaskProfiler&& other) noexcept;
    TaskProfiler(const TaskProfiler&) = delete;
    TaskProfiler& operator=(const TaskProfiler&) = delete;
    ~TaskProfiler();

    /// The task is turned on: restarts profiling on its RTPU (§6.7); the
    /// other tasks' warnings stay (they are reset by status commands only).
    /// Set-up path (takes the header lock briefly).
    void start();

    /// Start of a cycle (or event): right after the wake-up.
    void cycle_begin() noexcept;
    /// The same, for a job released at `release_ns` (CLOCK_MONOTONIC): its
    /// lateness (the wake-up minus the release) goes to the lateness
    /// histogram. 0: no release instant (aperiodic, synchronous).
    void cycle_begin(std::int64_t release_ns) noexcept;
    /// End of the cycle: accounts its CPU time and publishes the counters.
    void cycle_end() noexcept;
    /// `n` missed cycles (from the deadline-failure path). Safe to call from
    /// a signal handler running in the task thread.
    void missed(std::uint32_t n = 1) noexcept;
    /// Abandons a cycle without accounting it (aborted by siglongjmp).
    void cycle_abort() noexcept { in_cycle_ = false; }

    /// Turns the per-cycle histogram on (width > 0) or off (0); its counts
    /// restart now and with every reset, like the other counters.
    void set_histogram(std::uint64_t bucket_width_ns) noexcept;

    CpuClock clock() const noexcept { return clock_; }
    TaskSlot slot() const noexcept { return slot_; }
    /// CPU time of the last completed cycle in ns (for the runtime's own use,
    /// e.g. a MAXEXEC check), unquantised.
    std::uint64_t last_cycle_ns() const noexcept { return last_cycle_ns_; }

private:
    void close() noexcept;
    void publish_begin() noexcept;
    void publish_end() noexcept;
    void check_epoch() noexcept;
    std::int64_t thread_cpu_ns() const noexcept;
    void take_anchor() noexcept;

    TaskSlot slot_;
    CpuClock clock_ = CpuClock::none;
    int perf_fd_ = -1;
    void* perf_page_ = nullptr;
    // An exact reading of the thread's counter: `anchor_count_` at
    // `anchor_wall_`, the page at `anchor_seq_`. While the page's sequence
    // has not moved since, the count now is anchor_count_ + (now - anchor_wall_).
    bool anchor_valid_ = false;
    std::uint32_t anchor_seq_ = 0;
    std::uint64_t anchor_count_ = 0;
    std::int64_t anchor_wall_ = 0;
    // cycle_begin() state
    bool in_cycle_ = false;
    std::uint32_t begin_seq_ = 0;
    std::uint64_t begin_count_ = 0;   ///< counter at cycle_begin (or at the switch-in before it)
    std::int64_t begin_wall_ = 0;
    std::int64_t begin_cpu_ = 0;      ///< thread_cputime fallback
    std::int64_t begin_release_ = 0;  ///< the job's release instant (0: none)
    std::uint64_t last_cycle_ns_ = 0;
    // publication nesting: a miss reported by a signal handler that
    // interrupted a publication is folded in when the publication ends
    std::atomic<int> depth_{0};
    std::atomic<std::uint32_t> pending_misses_{0};
    // private copies of the published counters (the task is the only writer)
    std::uint64_t cycles_ = 0, misses_ = 0, accounted_ = 0, q_total_ = 0, q_min_ = UINT64_MAX,
                  q_max_ = 0, q_last_ = 0, switched_ = 0;
    std::uint32_t epoch_ = 0;
    Accounting accounting_ = Accounting::nanoseconds;
    std::int64_t tick_ns_ = 1;
    std::uint64_t hist_width_ns_ = 0;
};

}  // namespace chimera::prof
