// Internal helpers shared by SEM and MSG: waitlists of Waiter slots, the
// object lock with repair-on-recovery, and the per-type segment factories the
// XM server calls. Not installed.
#pragma once

#include <algorithm>
#include <string>
#include <type_traits>

#include "chimera/ipc/clock.hpp"
#include "chimera/ipc/futex.hpp"
#include "chimera/ipc/lock.hpp"
#include "chimera/ipc/segment.hpp"
#include "chimera/xmail.hpp"

namespace chimera::xm::detail {

using layout::Waiter;

enum WaiterState : std::uint32_t { kFree = 0, kWaiting = 1, kSignaled = 2 };

/// Bits of a Waiter's word, the one its thread sleeps on.
enum WaiterWord : std::uint32_t {
    kWordSignalled = 1,  ///< what it waited for is there (a repair's re-arm)
    kWordKicked = 2,     ///< another waiter joined the list: sleep in slices from now on
    kWordUntimed = 4,    ///< asleep without a timer: the only waiter of its list
    /// waiter_signal()'s mark: the signaller's thread id with this bit (and
    /// bit 30 once the kernel found that thread dead), the shape of a robust
    /// futex held by it (see waiter_signal()). The small bits above are not
    /// flags of such a word.
    kWordHandedOver = 1u << 31,
};
/// True when the word says the waiter was given what it waited for.
constexpr bool word_signalled(std::uint32_t word) noexcept {
    return (word & (kWordSignalled | kWordHandedOver)) != 0;
}

/// Longest single sleep of a waiter: it then re-checks its word, and passes
/// on what a waiter that died after being signalled was given (a unit, a
/// message, the turn to send), so a death delays the others by at most this.
inline constexpr std::int64_t kWaitSlice = 20'000'000;

/// How long object operations wait for the object's lock before lock_timeout.
inline constexpr std::int64_t kObjectLockTimeout = 2'000'000'000;

/// True when the thread runs: false for a thread that is gone and for one
/// that was killed and not yet reaped (a zombie), whose process can never
/// take what it is given. tgkill (the thread of that process exists) and
/// get_robust_list (the kernel empties it when the thread exits; glibc
/// registers one for every thread), /proc only when those cannot tell.
bool thread_alive(std::int32_t pid, std::int32_t tid) noexcept;

/// A read of a field that other threads and processes write under the
/// object's lock, without the lock: the look of a sleeper at the waiters, of
/// a poller at the counts (a hint, re-checked under the lock). Every write of
/// such a field is a poke(): both sides atomic, so the look is no data race
/// (relaxed: it orders nothing; ThreadSanitizer holds the tests to it).
inline std::uint32_t peek(const std::uint32_t& field) noexcept {
    return __atomic_load_n(&field, __ATOMIC_RELAXED);
}
inline std::int32_t peek(const std::int32_t& field) noexcept {
    return __atomic_load_n(&field, __ATOMIC_RELAXED);
}
template <typename T>
inline void poke(T& field, std::type_identity_t<T> value) noexcept {
    __atomic_store_n(&field, value, __ATOMIC_RELAXED);
}

/// Asks for a cache line this thread is about to write, without waiting for
/// it: prefetchw brings the line exclusive, so the write needs no second
/// trip (a CPU without it takes it as a no-op). Never faults.
inline void prefetch_for_write(const void* p) noexcept {
#if defined(__x86_64__)
    asm volatile("prefetchw %0" : : "m"(*static_cast<const char*>(p)));
#else
    __builtin_prefetch(p, 1, 3);
#endif
}

/// Takes a free slot for the calling thread (under the object's lock), and
/// kicks the list's untimed sleeper, if any, into slices (sleep_untimed()):
/// with two waiters, one may be given something and die with it.
Waiter* waiter_add(Waiter* slots, std::uint32_t n, std::uint32_t& next_ticket,
                   std::int32_t priority) noexcept;
/// The waiting slot with the highest priority (earliest ticket among
/// equals). No system call: a slot of a thread that died is found dead when
/// the wake-up reaches nobody (waiter_wake_checked()).
Waiter* waiter_pick(Waiter* slots, std::uint32_t n) noexcept;
/// Gives `w` what it waits for (its word, then its state), under the
/// object's lock; waiter_wake() or waiter_wake_checked() follows, after the
/// lock is let go. A signaller killed in between would leave a waiter that
/// sleeps without a timer asleep for good, so the word is written as a robust
/// futex held by the calling thread (its id, kWordHandedOver) and the thread's
/// robust list (set_robust_list(2), the one glibc registers for every
/// thread) names it as the operation in progress until the wake: if the
/// thread dies first, the kernel, as it exits, marks the word and wakes its
/// sleeper. No system call (but the first call in a thread reads where its
/// robust list is).
void waiter_signal(Waiter& w) noexcept;
/// waiter_signal() in two steps, for a hand-off that has a commit point of
/// its own (MSG's send): the word and the robust mark first, before the
/// commit, so that a signaller killed anywhere after it has the kernel wake
/// the waiter (which then finds the committed item under the lock, put back
/// by the repair); the state after it (waiter_signal_armed()).
void waiter_arm(Waiter& w) noexcept;
inline void waiter_signal_armed(Waiter& w) noexcept { poke(w.state, kSignaled); }
inline void waiter_free(Waiter& w) noexcept {
    poke(w.state, kFree);
    w.handed = 0;
    poke(w.pid, 0);
    poke(w.tid, 0);
    w.word.store(0, std::memory_order_relaxed);
}
/// Wakes a signalled waiter; the end of waiter_signal()'s hand-off.
void waiter_wake(Waiter& w) noexcept;
/// A repair's look at a live waiter found signalled: its signaller (the lock
/// holder that died) may have died before setting the word or waking it, so
/// the word is set again and the waiter woken (lock held; a rare path).
inline void waiter_rearm(Waiter& w) noexcept {
    w.word.store(kWordSignalled, std::memory_order_release);
    waiter_wake(w);
}

/// Who holds a slot: after the object's lock was let go, tells whether the
/// slot is still the one signalled (its thread cannot free it if it died,
/// but a reclaim by another user may have, and the slot been taken again).
struct WaiterId {
    std::int32_t pid = 0, tid = 0;
    std::uint32_t ticket = 0;
};
inline WaiterId id_of(const Waiter& w) noexcept { return {w.pid, w.tid, w.ticket}; }
inline bool still_signalled(const Waiter& w, const WaiterId& id) noexcept {
    return w.state == kSignaled && w.pid == id.pid && w.tid == id.tid && w.ticket == id.ticket;
}

/// Wakes a signalled waiter, after the lock is let go. True when it will
/// take what it was given: a thread slept on the word and was woken (one
/// system call, the common case), or, when nobody slept there, its thread
/// still runs (it had not gone to sleep yet). False: it died; the caller takes
/// back what it gave (under the lock, if still_signalled()) and passes it on.
bool waiter_wake_checked(Waiter& w, const WaiterId& id) noexcept;

/// True when some slot other than `self` is signalled and its thread died
/// (the look a sleeper takes every slice, without the lock).
bool signalled_dead(const Waiter* slots, std::uint32_t n, const Waiter* self) noexcept;

/// The timeout of one blocking call. The clock is read only when the call has
/// to wait (a send or receive that finds room or a message reads none; a round
/// trip's calls used to read it eight times), and the timeout counts from that
/// first wait. Afterwards the deadline is absolute, so sleeps need no read.
class WaitDeadline {
public:
    /// `timeout_ns` < 0: no limit; 0 is the caller's non-blocking case.
    explicit WaitDeadline(std::int64_t timeout_ns) noexcept : timeout_(timeout_ns) {}

    /// Before each wait: true once the deadline has passed. Reads the clock.
    bool passed() noexcept {
        if (timeout_ < 0) return false;
        now_ = ipc::now_ns();
        if (at_ < 0) at_ = now_ + timeout_;
        return now_ >= at_;
    }
    /// The absolute CLOCK_MONOTONIC deadline; -1 for none.
    std::int64_t at() const noexcept { return timeout_ < 0 ? -1 : at_; }
    /// The time read by the last passed(): where the next sleep's slices start.
    std::int64_t last_read() const noexcept { return now_; }

private:
    std::int64_t timeout_;
    std::int64_t at_ = -1;
    std::int64_t now_ = 0;
};

/// Another slot of the list in use (waiting or signalled), seen after the
/// caller's own seq_cst mark (see sleep_untimed()).
bool others_in(const Waiter* slots, std::uint32_t n, const Waiter* self) noexcept;

/// The sleep of a waiter with no time limit, when it is the only one of its
/// list: nobody else could be given something and die with it, so no slice
/// (and no kernel timer: one cost fewer than a timed sleep, as an mqueue's
/// or a pipe's blocking read) is needed. A waiter that joins the list later
/// kicks it (waiter_add()) and it goes on in slices. True when it slept or
/// its word changed (look again); false when others wait: sleep in slices.
inline bool sleep_untimed(Waiter& w, const Waiter* slots, std::uint32_t n) noexcept {
    std::uint32_t word = 0;
    // seq_cst, then the look at the others: a waiter_add() that the look
    // misses finds the mark and kicks (Dekker's pattern on both sides).
    if (!w.word.compare_exchange_strong(word, kWordUntimed, std::memory_order_seq_cst)) return true;
    if (others_in(slots, n, &w)) {
        word = kWordUntimed;
        // Fails only when signalled or kicked meanwhile: the caller looks again.
        return !w.word.compare_exchange_strong(word, 0, std::memory_order_relaxed);
    }
    (void)ipc::futex_wait(w.word, kWordUntimed, -1);
    return true;
}

/// Sleeps (outside the lock) until the slot is signalled or the deadline (see
/// WaitDeadline::passed(), called just before) passes. Without a deadline,
/// the only waiter of its list sleeps untimed (sleep_untimed()); otherwise
/// at every slice that passes in vain it calls `on_slice()`, which passes on
/// what dead waiters were given. True when signalled. Slices end at absolute
/// times, so a sleep reads no clock. `slots`: the list `w` is in.
/// `on_wake()` runs as each sleep ends, before the look at the word (a miss
/// across CPUs: the signaller wrote it): what it asks of memory comes in
/// parallel with that look (MSG prefetches the lines it will write).
template <typename OnSlice, typename OnWake>
bool waiter_sleep(Waiter& w, const Waiter* slots, std::uint32_t n, const WaitDeadline& deadline,
                  OnSlice&& on_slice, OnWake&& on_wake) noexcept {
    const std::int64_t at = deadline.at();
    std::int64_t slice_end = at < 0 ? -1 : std::min(deadline.last_read() + kWaitSlice, at);
    for (;;) {
        std::uint32_t word = w.word.load(std::memory_order_acquire);
        if (word_signalled(word)) return true;
        if (word != 0) {  // kicked, or the mark of an untimed sleep: start again from 0
            w.word.compare_exchange_strong(word, 0, std::memory_order_relaxed);
            continue;
        }
        if (at < 0 && sleep_untimed(w, slots, n)) {
            on_wake();
            continue;
        }
        const ipc::FutexResult r = at < 0 ? ipc::futex_wait(w.word, 0, kWaitSlice)
                                          : ipc::futex_wait_until(w.word, 0, slice_end);
        on_wake();
        if (r != ipc::FutexResult::timed_out || word_signalled(w.word.load(std::memory_order_acquire)))
            continue;
        if (at >= 0) {
            if (slice_end == at) return false;
            slice_end = std::min(slice_end + kWaitSlice, at);
        }
        on_slice();
    }
}
template <typename OnSlice>
bool waiter_sleep(Waiter& w, const Waiter* slots, std::uint32_t n, const WaitDeadline& deadline,
                  OnSlice&& on_slice) noexcept {
    return waiter_sleep(w, slots, n, deadline, on_slice, [] {});
}
std::uint32_t waiter_count(const Waiter* slots, std::uint32_t n) noexcept;

/// Takes an object's lock; when the previous holder died, runs `repair`
/// (with the lock held) and counts it in `recoveries`.
template <typename Repair>
Status lock_object(ipc::LockWord& lock, std::uint32_t& recoveries, Repair&& repair) noexcept {
    ipc::LockOptions options;
    options.timeout_ns = kObjectLockTimeout;
    options.liveness_check_ns = 500'000;
    const ipc::LockStatus s = ipc::lock(lock, options);
    if (!ipc::holds(s)) return Status::lock_timeout;
    if (s != ipc::LockStatus::acquired) {
        ++recoveries;
        repair();
    }
    return Status::ok;
}

/// Lets an XM object's lock go. ipc::unlock() is false only when the word no
/// longer names this thread; XM locks are never reset blindly (no
/// reset_on_timeout) and a live holder is never taken over, so that means
/// another process overwrote the word: nothing this thread could undo, and
/// the next locker takes a lock named after a dead or unknown thread over and
/// repairs the object.
inline void unlock_object(ipc::LockWord& lock) noexcept { (void)ipc::unlock(lock); }

/// Factories run by the owning RTPU's XM server: create, initialise and
/// publish the segment `segment` for object `full_name`.
ipc::Segment create_shm_segment(const std::string& segment, const std::string& full_name,
                                const ObjectParams& params);
ipc::Segment create_sem_segment(const std::string& segment, const std::string& full_name,
                                const ObjectParams& params);
ipc::Segment create_msg_segment(const std::string& segment, const std::string& full_name,
                                const ObjectParams& params);

}  // namespace chimera::xm::detail
