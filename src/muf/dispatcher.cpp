// The per-RTPU dispatcher of the fifo backend (and of the non-critical tasks of
// the deadline backend), and the DEADLINE watchdog of every backend. It is not
// on the release path: every task sleeps to its own release and the kernel
// wakes that task itself. The dispatcher re-ranks when the set, a criticality
// or a deadline changes, computing every task's urgency (Figure 6.2) and
// giving the task threads SCHED_FIFO priorities in urgency order, changing only
// those that move (thesis §6.2.3, docs/architecture.md §9). Under dynamic
// ranking a task also looks at the ranking when it first runs after its release
// (rank_at_release()), and changes priorities only where the order is wrong.
//
// It runs pinned to the RTPU's CPU at options.fifo_high, above every task of
// the band, so while it re-ranks no task of its CPU runs: the priorities change
// as one step. A task ranking at its release runs at its own priority; the
// order it applies the changes in (apply_ranking) keeps that safe. It sleeps on
// a futex with an absolute CLOCK_MONOTONIC timeout (FUTEX_WAIT_BITSET: the same
// hrtimer as clock_nanosleep(TIMER_ABSTIME)), so that a criticality change
// from a failure handler can wake it at once.
#include <algorithm>

#include "chimera/ipc/futex.hpp"
#include "rt_internal.hpp"

namespace chimera::muf {
namespace detail {

std::uint64_t standing_urgency(const UrgencyEncoding& enc, int crit, std::int64_t deadline_ticks,
                               int uprio) noexcept {
    const auto max_of = [](unsigned bits) { return (std::uint64_t{1} << bits) - 1; };
    const unsigned dyn_bits = 64 - enc.crit_bits - enc.user_bits;  // >= enc.dyn_bits >= 1
    const std::uint64_t c = std::min<std::uint64_t>(static_cast<std::uint64_t>(std::max(crit, 0)), max_of(enc.crit_bits));
    const std::uint64_t u = std::min<std::uint64_t>(static_cast<std::uint64_t>(std::max(uprio, 0)), max_of(enc.user_bits));
    std::uint64_t d = 0;  // no deadline: the least urgent of its criticality
    if (deadline_ticks >= 0)
        d = max_of(dyn_bits) - std::min<std::uint64_t>(static_cast<std::uint64_t>(deadline_ticks), max_of(dyn_bits) - 1);
    return (c << (dyn_bits + enc.user_bits)) | (d << enc.user_bits) | u;
}

void sort_by_urgency(std::span<RankEntry> entries) noexcept {
    // Insertion sort: at most kMaxTasks entries, no allocation, stable.
    const auto before = [](const RankEntry& a, const RankEntry& b) {
        if (a.urgency != b.urgency) return a.urgency > b.urgency;
        if (a.since_ns != b.since_ns) return a.since_ns < b.since_ns;  // first come, first served
        return a.handle < b.handle;
    };
    for (std::size_t i = 1; i < entries.size(); ++i) {
        const RankEntry x = entries[i];
        std::size_t j = i;
        for (; j > 0 && before(x, entries[j - 1]); --j) entries[j] = entries[j - 1];
        entries[j] = x;
    }
}

bool ranking_holds(std::span<const RankEntry> sorted, int low, int high) noexcept {
    // From the least urgent up: each entry stands above the nearest less
    // urgent pending job (and so above all of them, by induction).
    int pending_floor = low - 1;
    for (std::size_t k = sorted.size(); k-- > 0;) {
        const RankEntry& e = sorted[k];
        if (e.current_prio < low || e.current_prio >= high || e.current_prio <= pending_floor) return false;
        if (e.pending) pending_floor = e.current_prio;
    }
    return true;
}

void rank_priorities(std::span<RankEntry> entries, int low, int high) noexcept {
    sort_by_urgency(entries);
    // Keep the largest set of current priorities that can stay: kept tasks i < j
    // need cur_i - cur_j >= j - i (room for the tasks ranked between them), and
    // room above and below in the band. With key = cur + rank that is a longest
    // non-increasing run of keys within [low + n - 1, high - 1]: O(n^2), n <= 64.
    const int n = static_cast<int>(entries.size());
    std::array<int, kMaxTasks> run{}, prev{};
    int best = -1;
    for (int i = 0; i < n; ++i) {
        const int cur = entries[static_cast<std::size_t>(i)].current_prio;
        const int key = cur + i;
        run[static_cast<std::size_t>(i)] = 0;
        prev[static_cast<std::size_t>(i)] = -1;
        if (cur <= 0 || key < low + n - 1 || key > high - 1) continue;
        run[static_cast<std::size_t>(i)] = 1;
        for (int j = 0; j < i; ++j) {
            const auto uj = static_cast<std::size_t>(j);
            if (run[uj] > 0 && entries[uj].current_prio + j >= key &&
                run[uj] + 1 >= run[static_cast<std::size_t>(i)]) {
                run[static_cast<std::size_t>(i)] = run[uj] + 1;
                prev[static_cast<std::size_t>(i)] = j;
            }
        }
        if (best < 0 || run[static_cast<std::size_t>(i)] >= run[static_cast<std::size_t>(best)]) best = i;
    }
    std::array<bool, kMaxTasks> kept{};
    for (int i = best; i >= 0; i = prev[static_cast<std::size_t>(i)]) kept[static_cast<std::size_t>(i)] = true;
    // Ties go to the later task, which keeps the kept priorities spread over
    // the band. The others take the next priorities down from the one above.
    int above = high;
    for (int k = 0; k < n; ++k) {
        RankEntry& e = entries[static_cast<std::size_t>(k)];
        e.new_prio = kept[static_cast<std::size_t>(k)] ? e.current_prio : above - 1;
        above = e.new_prio;
    }
}

}  // namespace detail

using detail::Pacing;
using detail::Phase;
using detail::SlotState;
using detail::TaskSlot;

void RtpuScheduler::Impl::notify() noexcept {
    event_word.fetch_add(1, std::memory_order_acq_rel);
    ipc::futex_wake(event_word, 1);
}

void RtpuScheduler::Impl::dispatcher_main() noexcept {
    std::uint32_t ranked = event_word.load() - 1;  // the event last ranked for
    for (;;) {
        const std::uint32_t seen = event_word.load(std::memory_order_acquire);
        if (stopping.load(std::memory_order_acquire)) return;
        const std::int64_t now = clock_ns();
        std::int64_t next = infinity;
        // Only an event (set, period, criticality, a task's own deadline)
        // re-ranks; a watchdog wake-up does not.
        if (seen != ranked) {
            rank_and_apply(now);
            ranked = seen;
        }
        next = std::min(next, watch_deadlines(now));
        ipc::futex_wait_until(event_word, seen, next);
    }
}

// The DEADLINE watchdog: tasks make no system call to arm a deadline, so a job
// that never returns is found here. A job seen running with its deadline ahead
// is watched to that deadline exactly; otherwise the watchdog looks again
// within options.watchdog_ns. A job found past its deadline is signalled once
// (per deadline: the handler moves a continuing job's deadline a period on);
// the handler runs in the task's own thread (failure.cpp).
std::int64_t RtpuScheduler::Impl::watch_deadlines(std::int64_t now) noexcept {
    std::int64_t next = now + options.watchdog_ns;
    // Under dynamic ranking the watch is exact also for jobs not yet released
    // (a task's next job is due at its next release plus its deadline), as when
    // the dispatcher released them: EDF's overload drops a job exactly at its
    // deadline (Figure 6.1). Under static ranking one look per watchdog_ns is
    // the documented bound, and keeps the dispatcher asleep at high rates.
    const bool ahead = !static_ranking.load(std::memory_order_acquire);
    const int count = std::min(slot_count_seen.load(std::memory_order_acquire), detail::kMaxTasks);
    for (int h = 0; h < count; ++h) {
        TaskSlot& s = slots[static_cast<std::size_t>(h)];
        if (s.state.load(std::memory_order_acquire) != SlotState::attached) continue;
        if (s.phase.load(std::memory_order_acquire) != Phase::job) {
            // A job released and not begun by its deadline (it waits for the
            // CPU) is the task's own to find when it runs (wait_release).
            const std::int64_t due = s.next_release_ns.load(std::memory_order_relaxed) +
                                     s.rel_deadline_ns.load(std::memory_order_relaxed);
            if (ahead && s.period_ns.load(std::memory_order_relaxed) > 0 && due > now) next = std::min(next, due);
            continue;
        }
        const std::int64_t deadline = s.job_deadline_ns.load(std::memory_order_acquire);
        if (deadline == infinity) continue;
        if (deadline > now) {
            next = std::min(next, deadline);
        } else if (s.watchdog_signalled.exchange(deadline, std::memory_order_acq_rel) != deadline) {
            if (detail::signal_deadline(s.tid.load(std::memory_order_relaxed)) == 0)
                watchdog_signals.fetch_add(1, std::memory_order_relaxed);
        }
    }
    return next;
}

std::size_t RtpuScheduler::Impl::collect_ranking(std::int64_t now,
                                                 std::span<detail::RankEntry, detail::kMaxTasks> entries) noexcept {
    std::size_t n = 0;
    const bool dynamic = uses_deadline.load(std::memory_order_relaxed);
    const bool fixed = static_ranking.load(std::memory_order_acquire);
    const int count = std::min(slot_count_seen.load(std::memory_order_acquire), detail::kMaxTasks);
    for (int h = 0; h < count; ++h) {
        TaskSlot& s = slots[static_cast<std::size_t>(h)];
        if (s.state.load(std::memory_order_acquire) != SlotState::attached) continue;
        if (s.pacing.load(std::memory_order_relaxed) != Pacing::dispatched) continue;
        detail::RankEntry& e = entries[n++];
        const int crit = s.crit.load(std::memory_order_acquire);
        const int uprio = s.uprio.load(std::memory_order_relaxed);
        e.since_ns = 0;
        e.pending = false;
        if (fixed) {
            // Every task its fixed place: the relative deadline stands for the
            // time to the deadline (with harmonic periods and implicit
            // deadlines their order is the order of the absolute deadlines of
            // any jobs pending together).
            std::optional<std::int64_t> ticks;
            if (dynamic) ticks = s.rel_deadline_ns.load(std::memory_order_relaxed) / options.tick_ns;
            e.urgency = urgency(options.encoding, crit, ticks, uprio);
        } else {
            // Every task by the job it has, or else by the job its next release
            // begins (the kernel will release it at the priority it has now).
            // A job stays pending from its release, begun or not. A task that
            // times itself (pause) has no next job until it sets one.
            const bool job = s.phase.load(std::memory_order_acquire) == Phase::job;
            const bool self_timed = s.self_timed.load(std::memory_order_relaxed);
            const std::int64_t release = job ? s.job_release_ns.load(std::memory_order_relaxed)
                                             : s.next_release_ns.load(std::memory_order_relaxed);
            std::int64_t deadline = job ? s.job_deadline_ns.load(std::memory_order_acquire)
                                        : release + s.rel_deadline_ns.load(std::memory_order_relaxed);
            if (!job && self_timed) deadline = infinity;
            e.pending = job || (!self_timed && release <= now);
            e.since_ns = !job && self_timed ? infinity : release;
            const std::int64_t ticks =
                !dynamic || deadline == infinity ? -1 : std::max<std::int64_t>(deadline - epoch_ns, 0) / options.tick_ns;
            e.urgency = detail::standing_urgency(options.encoding, crit, ticks, uprio);
        }
        e.handle = h;
        e.current_prio = s.fifo_prio.load(std::memory_order_relaxed);
        e.new_prio = e.current_prio;
    }
    return n;
}

void RtpuScheduler::Impl::rank_and_apply(std::int64_t now) noexcept {
    std::lock_guard<ipc::PiMutex> lock(rank_mutex);
    std::array<detail::RankEntry, detail::kMaxTasks> entries;
    const auto ranked = std::span(entries.data(), collect_ranking(now, entries));
    if (!static_ranking.load(std::memory_order_acquire)) {
        detail::sort_by_urgency(ranked);
        if (detail::ranking_holds(ranked, options.fifo_low, options.fifo_high)) {
            reschedules.fetch_add(1, std::memory_order_relaxed);
            return;
        }
    }
    apply_ranking(ranked, -1);
}

void RtpuScheduler::Impl::rank_at_release(std::int64_t now, int self) noexcept {
    std::array<detail::RankEntry, detail::kMaxTasks> entries;
    // A look without the lock first: in steady state the order holds, and
    // the release costs no system call. A ranking under way elsewhere (its
    // holder preempted by this task) may show a half-applied order: then the
    // lock waits for it (boosting its holder) and the order is looked at again.
    auto ranked = std::span(entries.data(), collect_ranking(now, entries));
    detail::sort_by_urgency(ranked);
    if (detail::ranking_holds(ranked, options.fifo_low, options.fifo_high)) return;
    std::lock_guard<ipc::PiMutex> lock(rank_mutex);
    ranked = std::span(entries.data(), collect_ranking(now, entries));
    detail::sort_by_urgency(ranked);
    if (detail::ranking_holds(ranked, options.fifo_low, options.fifo_high)) return;
    apply_ranking(ranked, self);
}

void RtpuScheduler::Impl::apply_ranking(std::span<detail::RankEntry> entries, int self) noexcept {
    detail::rank_priorities(entries, options.fifo_low, options.fifo_high);
    const auto apply = [this](const detail::RankEntry& e) {
        TaskSlot& s = slots[static_cast<std::size_t>(e.handle)];
        // Recorded before the call: a thread raised above the caller runs at
        // once, inside the call, and looks at the ranking with its new place.
        s.fifo_prio.store(e.new_prio, std::memory_order_relaxed);
        if (detail::set_fifo(s.tid.load(std::memory_order_relaxed), e.new_prio) == 0)
            priority_changes.fetch_add(1, std::memory_order_relaxed);
        else
            s.fifo_prio.store(e.current_prio, std::memory_order_relaxed);
    };
    // A task ranking at its release runs at its own priority, above every
    // runnable task of the band. Those it lowers go first, least urgent first
    // (no thread lowered passes its caller); then those it raises, most urgent
    // first: the first one raised above the caller takes the CPU, and it is
    // the most urgent then, as everything above its new place is final and
    // everything below it still lower. The caller's own change last: lowering
    // itself may hand its CPU over.
    const detail::RankEntry* mine = nullptr;
    for (std::size_t k = entries.size(); k-- > 0;) {
        const detail::RankEntry& e = entries[k];
        if (e.handle == self) mine = &e;
        else if (e.new_prio < e.current_prio) apply(e);
    }
    for (const detail::RankEntry& e : entries)
        if (e.handle != self && e.new_prio > e.current_prio) apply(e);
    if (mine && mine->new_prio != mine->current_prio) apply(*mine);
    reschedules.fetch_add(1, std::memory_order_relaxed);
}

}  // namespace chimera::muf
