// Waitlists of SEM and MSG objects (thesis §5.4.2, §5.4.3.1: "the policy for
// inserting tasks into the waitlist ... highest-priority-first").
#include <sys/syscall.h>
#include <unistd.h>

#include <cerrno>

#include "detail.hpp"

namespace chimera::xm::detail {

bool thread_exists(std::int32_t pid, std::int32_t tid) noexcept {
    if (pid <= 0 || tid <= 0) return false;
    return syscall(SYS_tgkill, pid, tid, 0) == 0 || errno != ESRCH;
}

bool thread_alive(std::int32_t pid, std::int32_t tid) noexcept {
    return ipc::owner_alive(static_cast<std::uint64_t>(static_cast<std::uint32_t>(pid)) << 32 |
                            static_cast<std::uint32_t>(tid));
}

Waiter* waiter_add(Waiter* slots, std::uint32_t n, std::uint32_t& next_ticket,
                   std::int32_t priority) noexcept {
    for (std::uint32_t i = 0; i < n; ++i) {
        Waiter& w = slots[i];
        if (w.state != kFree) continue;
        const std::uint64_t me = ipc::self_owner_id();
        w.word.store(0, std::memory_order_relaxed);
        w.pid = ipc::owner_pid(me);
        w.tid = ipc::owner_tid(me);
        w.priority = priority;
        w.ticket = next_ticket++;
        w.handed = 0;
        w.state = kWaiting;
        return &w;
    }
    // Full: free the slots of threads that were killed while waiting (a slot
    // holding a handed message is left to the object's own reclaim).
    bool freed = false;
    for (std::uint32_t i = 0; i < n; ++i) {
        Waiter& w = slots[i];
        if (w.state != kFree && w.handed == 0 && !thread_alive(w.pid, w.tid)) {
            waiter_free(w);
            freed = true;
        }
    }
    return freed ? waiter_add(slots, n, next_ticket, priority) : nullptr;
}

Waiter* waiter_pick(Waiter* slots, std::uint32_t n, std::uint32_t* reclaimed) noexcept {
    for (;;) {
        Waiter* best = nullptr;
        for (std::uint32_t i = 0; i < n; ++i) {
            Waiter& w = slots[i];
            if (w.state != kWaiting) continue;
            // Tickets wrap: compare their difference, not their values.
            if (!best || w.priority > best->priority ||
                (w.priority == best->priority &&
                 static_cast<std::int32_t>(w.ticket - best->ticket) < 0))
                best = &w;
        }
        if (!best || thread_exists(best->pid, best->tid)) return best;
        waiter_free(*best);  // killed while waiting: never signal it
        if (reclaimed) ++*reclaimed;
    }
}

bool waiter_sleep(Waiter& w, std::int64_t deadline) noexcept {
    for (;;) {
        if (w.word.load(std::memory_order_acquire) != 0) return true;
        std::int64_t slice = kWaitSlice;
        if (deadline >= 0) {
            const std::int64_t left = deadline - ipc::now_ns();
            if (left <= 0) return false;
            if (left < slice) slice = left;
        }
        ipc::futex_wait(w.word, 0, slice);
    }
}

std::uint32_t waiter_count(const Waiter* slots, std::uint32_t n) noexcept {
    std::uint32_t c = 0;
    for (std::uint32_t i = 0; i < n; ++i)
        if (slots[i].state == kWaiting) ++c;
    return c;
}

}  // namespace chimera::xm::detail
