// The per-RTPU dispatcher of the fifo backend (and of the non-critical tasks of
// the deadline backend), and the DEADLINE watchdog of every backend. It is not
// on the release path: every task sleeps to its own release and the kernel
// wakes that task itself. The dispatcher re-ranks when the set, a criticality
// or a deadline changes, computing every ready task's urgency (Figure 6.2) and
// giving the task threads SCHED_FIFO priorities in urgency order, changing only
// those that move (thesis §6.2.3, ARCHITECTURE §5). Under dynamic ranking a
// task also ranks at its own release (stand_by_for_release(), rt.cpp).
//
// It runs pinned to the RTPU's CPU at options.fifo_high, above every task of
// the band, so while it re-ranks no task of its CPU runs: the priorities change
// as one step (a task ranking at its release runs at that same priority). It
// sleeps on a futex with an absolute CLOCK_MONOTONIC timeout (FUTEX_WAIT_BITSET:
// the same hrtimer as clock_nanosleep(TIMER_ABSTIME)), so that a criticality
// change from a failure handler can wake it at once.
#include <algorithm>

#include "chimera/ipc/futex.hpp"
#include "rt_internal.hpp"

namespace chimera::muf {
namespace detail {

void rank_priorities(std::span<RankEntry> entries, int low, int high) noexcept {
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
            if (ahead && s.period_ns.load(std::memory_order_relaxed) > 0)
                next = std::min(next, s.next_release_ns.load(std::memory_order_relaxed) +
                                          s.rel_deadline_ns.load(std::memory_order_relaxed));
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

void RtpuScheduler::Impl::rank_and_apply(std::int64_t now, int self) noexcept {
    std::lock_guard<ipc::PiMutex> lock(rank_mutex);
    std::array<detail::RankEntry, detail::kMaxTasks> entries;
    std::size_t n = 0;
    const bool dynamic = uses_deadline.load(std::memory_order_relaxed);
    const bool fixed = static_ranking.load(std::memory_order_acquire);
    const int count = std::min(slot_count_seen.load(std::memory_order_acquire), detail::kMaxTasks);
    for (int h = 0; h < count; ++h) {
        TaskSlot& s = slots[static_cast<std::size_t>(h)];
        if (s.state.load(std::memory_order_acquire) != SlotState::attached) continue;
        if (s.pacing.load(std::memory_order_relaxed) != Pacing::dispatched) continue;
        std::optional<std::int64_t> ticks;
        std::int64_t since = 0;
        if (fixed) {
            // Every task, waiting or not, its fixed place: the relative
            // deadline stands for the time to the deadline (with harmonic
            // periods and implicit deadlines their order is the order of the
            // absolute deadlines of any jobs pending together).
            if (dynamic) ticks = s.rel_deadline_ns.load(std::memory_order_relaxed) / options.tick_ns;
        } else {
            // Only tasks with a pending job compete; a waiting task keeps its
            // priority (it is blocked) until its release ranks it again.
            if (s.phase.load(std::memory_order_acquire) != Phase::job) continue;
            const std::int64_t deadline = s.job_deadline_ns.load(std::memory_order_acquire);
            if (dynamic && deadline != infinity) ticks = (deadline - now) / options.tick_ns;
            since = s.job_release_ns.load(std::memory_order_relaxed);
        }
        detail::RankEntry& e = entries[n++];
        e.urgency = urgency(options.encoding, s.crit.load(std::memory_order_acquire), ticks,
                            s.uprio.load(std::memory_order_relaxed));
        e.since_ns = since;
        e.handle = h;
        e.current_prio = s.fifo_prio.load(std::memory_order_relaxed);
        e.new_prio = e.current_prio;
    }
    apply_ranking(std::span(entries.data(), n), self);
}

void RtpuScheduler::Impl::apply_ranking(std::span<detail::RankEntry> entries, int self) noexcept {
    detail::rank_priorities(entries, options.fifo_low, options.fifo_high);
    const auto apply = [this](const detail::RankEntry& e) {
        if (e.new_prio == e.current_prio) return;
        TaskSlot& s = slots[static_cast<std::size_t>(e.handle)];
        if (detail::set_fifo(s.tid.load(std::memory_order_relaxed), e.new_prio) == 0) {
            s.fifo_prio.store(e.new_prio, std::memory_order_relaxed);
            priority_changes.fetch_add(1, std::memory_order_relaxed);
        }
    };
    // The caller's own change last: lowering itself may hand its CPU over.
    const detail::RankEntry* mine = nullptr;
    for (const detail::RankEntry& e : entries) {
        if (e.handle == self) mine = &e;
        else apply(e);
    }
    if (mine) apply(*mine);
    reschedules.fetch_add(1, std::memory_order_relaxed);
}

void RtpuScheduler::Impl::stand_by_for_release(TaskSlot& s) noexcept {
    if (s.fifo_prio.load(std::memory_order_relaxed) == options.fifo_high) return;
    if (detail::set_fifo(0, options.fifo_high) == 0) {
        s.fifo_prio.store(options.fifo_high, std::memory_order_relaxed);
        priority_changes.fetch_add(1, std::memory_order_relaxed);
    }
}

}  // namespace chimera::muf
