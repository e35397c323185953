// Waitlists of SEM and MSG objects (thesis §5.4.2, §5.4.3.1: "the policy for
// inserting tasks into the waitlist ... highest-priority-first").
#include <linux/futex.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <cerrno>

#include "detail.hpp"

namespace chimera::xm::detail {

bool thread_alive(std::int32_t pid, std::int32_t tid) noexcept {
    if (pid <= 0 || tid <= 0) return false;
    if (syscall(SYS_tgkill, pid, tid, 0) != 0 && errno == ESRCH) return false;
    // tgkill succeeds on a zombie. The kernel empties a thread's robust-futex
    // list when it exits, and glibc gives every thread one: a list means the
    // thread runs. No list, or not allowed to look: ask /proc.
    void* head = nullptr;
    std::size_t len = 0;
    if (syscall(SYS_get_robust_list, tid, &head, &len) == 0) {
        if (head != nullptr) return true;
    } else if (errno == ESRCH) {
        return false;
    }
    return ipc::owner_alive(static_cast<std::uint64_t>(static_cast<std::uint32_t>(pid)) << 32 |
                            static_cast<std::uint32_t>(tid));
}

namespace {

void kick_untimed(Waiter* slots, std::uint32_t n, const Waiter* self) noexcept {
    for (std::uint32_t i = 0; i < n; ++i) {
        Waiter& w = slots[i];
        if (&w == self || peek(w.state) == kFree) continue;
        const std::uint32_t word = w.word.load(std::memory_order_seq_cst);
        if ((word & kWordUntimed) && !word_signalled(word)) {
            w.word.fetch_or(kWordKicked, std::memory_order_relaxed);
            ipc::futex_wake_all(w.word);
        }
    }
}

}  // namespace

bool others_in(const Waiter* slots, std::uint32_t n, const Waiter* self) noexcept {
    for (std::uint32_t i = 0; i < n; ++i)
        if (&slots[i] != self && __atomic_load_n(&slots[i].state, __ATOMIC_SEQ_CST) != kFree) return true;
    return false;
}

Waiter* waiter_add(Waiter* slots, std::uint32_t n, std::uint32_t& next_ticket,
                   std::int32_t priority) noexcept {
    for (std::uint32_t i = 0; i < n; ++i) {
        Waiter& w = slots[i];
        if (w.state != kFree) continue;
        const std::uint64_t me = ipc::self_owner_id();
        w.word.store(0, std::memory_order_relaxed);
        poke(w.pid, ipc::owner_pid(me));
        poke(w.tid, ipc::owner_tid(me));
        w.priority = priority;
        w.ticket = next_ticket++;
        w.handed = 0;
        // seq_cst, then the look at the others' words (see sleep_untimed()).
        __atomic_store_n(&w.state, kWaiting, __ATOMIC_SEQ_CST);
        kick_untimed(slots, n, &w);
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

Waiter* waiter_pick(Waiter* slots, std::uint32_t n) noexcept {
    Waiter* best = nullptr;
    for (std::uint32_t i = 0; i < n; ++i) {
        Waiter& w = slots[i];
        if (w.state != kWaiting) continue;
        // Tickets wrap: compare their difference, not their values.
        if (!best || w.priority > best->priority ||
            (w.priority == best->priority && static_cast<std::int32_t>(w.ticket - best->ticket) < 0))
            best = &w;
    }
    return best;
}

static_assert(kWordHandedOver == FUTEX_WAITERS);

namespace {

// The calling thread's robust list, as the kernel knows it (nullptr when it
// has none: then a hand-off is not covered).
robust_list_head* robust_head() noexcept {
    thread_local robust_list_head* head = nullptr;
    thread_local bool looked = false;
    if (!looked) {
        std::size_t len = 0;
        if (syscall(SYS_get_robust_list, 0, &head, &len) != 0) head = nullptr;
        looked = true;
    }
    return head;
}

// The kernel finds the futex of list_op_pending at that pointer plus the
// list's futex_offset (glibc's, for its mutexes).
void hand_off_begins(std::atomic<std::uint32_t>& word) noexcept {
    if (robust_list_head* head = robust_head())
        head->list_op_pending = reinterpret_cast<robust_list*>(reinterpret_cast<char*>(&word) - head->futex_offset);
}
void hand_off_ends() noexcept {
    if (robust_list_head* head = robust_head()) head->list_op_pending = nullptr;
}

}  // namespace

void waiter_arm(Waiter& w) noexcept {
    hand_off_begins(w.word);
    // Release: what was handed over so far is visible with the word (and
    // the pending mark before it, for the kernel: the same thread).
    const auto tid = static_cast<std::uint32_t>(ipc::owner_tid(ipc::self_owner_id()));
    w.word.store((tid & FUTEX_TID_MASK) | kWordHandedOver, std::memory_order_release);
}

void waiter_signal(Waiter& w) noexcept {
    // The word before the state: a signaller that dies between them has
    // marked the word already, so the kernel wakes the waiter, which finds
    // under the lock whether the state made it (nothing was given if not).
    waiter_arm(w);
    waiter_signal_armed(w);
}

void waiter_wake(Waiter& w) noexcept {
    ipc::futex_wake_all(w.word);
    hand_off_ends();
}

bool waiter_wake_checked(Waiter& w, const WaiterId& id) noexcept {
    const bool woke = ipc::futex_wake_all(w.word) > 0;
    hand_off_ends();
    return woke || thread_alive(id.pid, id.tid);
}

bool signalled_dead(const Waiter* slots, std::uint32_t n, const Waiter* self) noexcept {
    for (std::uint32_t i = 0; i < n; ++i) {
        const Waiter& w = slots[i];
        if (&w == self || peek(w.state) != kSignaled) continue;
        if (!thread_alive(peek(w.pid), peek(w.tid))) return true;
    }
    return false;
}

std::uint32_t waiter_count(const Waiter* slots, std::uint32_t n) noexcept {
    std::uint32_t c = 0;
    for (std::uint32_t i = 0; i < n; ++i)
        if (slots[i].state == kWaiting) ++c;
    return c;
}

}  // namespace chimera::xm::detail
