// chimera/ipc/lock.hpp — the table lock (the thesis's xmLock, §5.3, §6.6).
//
// A lock in shared memory whose 64-bit word holds the owner, (pid << 32 | tid),
// 0 when free. Its low 32 bits are a Linux PI futex word (the owner's TID plus
// the kernel's FUTEX_WAITERS bit), so a waiter that has to block does so in the
// kernel with FUTEX_LOCK_PI: the kernel boosts the holder to the waiter's
// priority until it lets go, and a low-priority holder is never kept off the
// CPU by a medium-priority thread while a high-priority one waits.
//
// Cost. Acquiring it uncontended is one compare-and-swap (0 -> owner), releasing
// it one compare-and-swap (owner -> 0): no system call, no allocation (the
// caller's pid/tid are cached per thread). Releasing was a plain store before
// priority inheritance; it must be atomic now, as the kernel may set
// FUTEX_WAITERS at any moment and a store would lose that waiter (bench/svar's
// TableLockUnlock measures the transfer; bench/results/svar.md has the ratio).
// Under contention the caller spins a bounded number of times with the CPU's
// polling pause, then blocks in FUTEX_LOCK_PI until the lock is handed to it,
// the holder is found dead, or its timeout passes; a holder that finds
// FUTEX_WAITERS set releases through FUTEX_UNLOCK_PI, which hands the lock to
// the highest-priority waiter.
//
// Dead holders. What the thesis's xmLock did on timeout — reset the lock
// blindly — can tear data that was consistent. Here a holder that died is
// detected by the kernel: FUTEX_LOCK_PI answers ESRCH when the word names a
// thread that no longer exists (or has exited: a killed process's zombie
// counts as dead), and the waiter takes the lock over; a holder that dies while
// others are blocked on it has the lock handed by the kernel to the top waiter
// (its exit releases the PI state). Either way the caller is TOLD
// (LockStatus::recovered) so it can repair what the holder was writing (the
// SVAR table rolls back an undo record). How a waiter tells a kernel hand-over
// at exit from a clean FUTEX_UNLOCK_PI: the releasing holder clears the word's
// pid half before it calls FUTEX_UNLOCK_PI, the kernel only writes the TID half;
// so a waiter handed the lock with the previous pid still in the word knows
// that holder never released it. No robust list is used (glibc owns the
// thread's robust list head).
//
// A holder that dies while waiters are queued leaves the kernel's PI state
// without an owner, and until the waiter its exit woke has run, the kernel
// refuses (EINVAL) the word naming the dead thread; that waiter may never run
// (killed too). The kernel's remedy is the robust list's mark (TID 0 plus
// FUTEX_OWNER_DIED): a waiter refused a word whose TID is gone writes that
// mark (keeping the pid half) and tries again, and the kernel gives it the
// lock; FUTEX_OWNER_DIED or a pid half left in the word makes it a recovery.
//
// Corruption. Another process may overwrite the word. A word naming no thread
// is a dead holder (taken over, recovered, reported). A word the kernel keeps
// refusing (EINVAL: inconsistent with its PI state, EPERM: a kernel thread,
// EFAULT) for 50 ms (or until the timeout), or whose pid half names no process
// that has the thread of its TID half, seen so twice one liveness period
// apart, is reported as LockStatus::corrupt: the caller gets an error (the
// SVAR table's "the SVAR table's lock word is corrupt"), the word is left
// alone, and no waiter blocks on it past that bound — even with an infinite
// timeout. A word copied from a live holder elsewhere cannot be told from a
// holder and waits for the timeout (finite on every task path).
//
// A timeout is reported (LockStatus::timed_out) and the lock is left alone;
// only a caller that asks for it (LockOptions::reset_on_timeout) gets the
// thesis's blind reset, reported as LockStatus::forced (with PI waiters
// blocked on the old holder, the kernel then finds its state inconsistent and
// they report corrupt: forced already means "data may be torn"). Every
// recovery, timeout, corruption and reset also bumps a counter in the lock and
// calls the process-wide handler, if one is set: never silent.
//
// Limits: the owner is identified by the pid/tid of the caller's PID
// namespace; all users of one lock must share it (one machine, one container).
// A recycled TID (a dead holder's TID given to a new thread before a waiter
// looks) is taken for a live holder until the timeout. The kernel's 32-bit
// compare-and-swap on the low half and ours on the whole word are both atomic
// on the same aligned cache line (x86-64, AArch64).
#pragma once

#include "chimera/export.hpp"

#include <atomic>
#include <cstdint>

namespace chimera::ipc {

/// The lock as laid out in shared memory: one cache line.
struct alignas(64) LockWord {
    std::atomic<std::uint64_t> owner{0};       ///< pid << 32 | tid; 0 = free
    std::atomic<std::uint32_t> recoveries{0};  ///< dead holders taken over
    std::atomic<std::uint32_t> timeouts{0};    ///< acquisitions that timed out
    std::atomic<std::uint32_t> forced{0};      ///< blind resets after a timeout
    std::atomic<std::uint32_t> corruptions{0}; ///< acquisitions refused: the word was corrupt
    std::atomic<std::uint64_t> acquisitions{0};///< slow-path acquisitions (after contention)
    std::uint8_t reserved[32] = {};
};
static_assert(sizeof(LockWord) == 64);
static_assert(std::atomic<std::uint64_t>::is_always_lock_free);

enum class [[nodiscard]] LockStatus : int {
    acquired = 0,  ///< the caller holds the lock
    recovered,     ///< the caller holds the lock, taken over from a dead holder
    forced,        ///< the caller holds the lock, reset blindly after a timeout
    busy,          ///< try_lock only: held by someone else
    timed_out,     ///< not acquired within the timeout
    already_held,  ///< the calling thread holds it already (not recursive)
    corrupt,       ///< not acquired: the word names no possible holder (see above)
};

/// True for the statuses in which the caller now holds the lock.
constexpr bool holds(LockStatus s) noexcept {
    return s == LockStatus::acquired || s == LockStatus::recovered || s == LockStatus::forced;
}
CHIMERA_API const char* to_string(LockStatus s) noexcept;

struct LockOptions {
    /// Total time to wait; negative waits forever (still recovering dead
    /// holders). 100 ms is far beyond any transfer, but survives a holder
    /// preempted for a few time slices on a busy machine without SCHED_FIFO.
    std::int64_t timeout_ns = 100'000'000;
    /// Spins with the CPU's pause instruction before blocking in the kernel.
    std::uint32_t spin_count = 200;
    /// How long one wait in the kernel lasts before the waiter checks the
    /// word is still consistent (a corrupt word is reported within two).
    std::int64_t liveness_check_ns = 1'000'000;
    /// The thesis's blind reset when the timeout passes (reported as forced).
    bool reset_on_timeout = false;
};

/// Reported to the process-wide handler.
struct LockEvent {
    enum class Kind { recovered, timed_out, forced, corrupt } kind;
    const LockWord* lock;
    std::int32_t previous_pid;   ///< the holder at the time
    std::int32_t previous_tid;
    std::int64_t waited_ns;
};
using LockEventHandler = void (*)(const LockEvent& event, void* context) noexcept;

/// Installs a handler for every recovery/timeout/reset in this process (nullptr
/// removes it). The handler runs in the thread that saw the event.
CHIMERA_API void set_lock_event_handler(LockEventHandler handler, void* context = nullptr) noexcept;

namespace detail {
/// This thread's owner word once known, else 0. Initial-exec TLS: reading it is
/// one load relative to the thread pointer, also from inside the shared library
/// (the general-dynamic model would call __tls_get_addr on every lock).
[[gnu::tls_model("initial-exec")]] extern CHIMERA_API constinit thread_local std::uint64_t t_self_owner_id;
/// Computes the owner word (getpid, gettid) and caches it.
CHIMERA_API std::uint64_t self_owner_id_slow() noexcept;
}  // namespace detail

/// This thread's owner word (pid << 32 | tid), cached per thread and reset in a
/// child after fork(). No system call once cached.
inline std::uint64_t self_owner_id() noexcept {
    const std::uint64_t id = detail::t_self_owner_id;
    if (id != 0) [[likely]] return id;
    return detail::self_owner_id_slow();
}
constexpr std::int32_t owner_pid(std::uint64_t word) noexcept {
    return static_cast<std::int32_t>(word >> 32);
}
/// The kernel's bits in the futex half of the word (linux/futex.h).
inline constexpr std::uint64_t kFutexWaiters = 0x80000000u;    ///< FUTEX_WAITERS
inline constexpr std::uint64_t kFutexOwnerDied = 0x40000000u;  ///< FUTEX_OWNER_DIED
inline constexpr std::uint64_t kFutexTidMask = 0x3fffffffu;    ///< FUTEX_TID_MASK
constexpr std::int32_t owner_tid(std::uint64_t word) noexcept {
    return static_cast<std::int32_t>(word & kFutexTidMask);
}
/// The owner a word names, without the kernel's flag bits.
constexpr std::uint64_t owner_of(std::uint64_t word) noexcept {
    return word & ~(kFutexWaiters | kFutexOwnerDied);
}

/// True when the thread named by an owner word still exists (and is not a
/// zombie). System calls (tgkill, then a pidfd; /proc/PID/task/TID/stat only
/// where a pidfd cannot tell: a leader of several threads, or any thread of a
/// process of several before Linux 6.9): for slow paths only.
CHIMERA_API bool owner_alive(std::uint64_t word) noexcept;

/// One attempt; no waiting, no liveness check.
inline LockStatus try_lock(LockWord& lock) noexcept {
    std::uint64_t expected = 0;
    const std::uint64_t me = self_owner_id();
    if (lock.owner.compare_exchange_strong(expected, me, std::memory_order_acquire,
                                           std::memory_order_relaxed))
        return LockStatus::acquired;
    return owner_of(expected) == me ? LockStatus::already_held : LockStatus::busy;
}

/// The uncontended acquisition alone, for a caller that has its owner word
/// (self_owner_id(), never 0) at hand: one CAS from free to `self`. False, and
/// nothing changed, when the lock was not free; lock() does the rest then
/// (already held, spin, poll, recover, time out).
[[nodiscard]] inline bool lock_if_free(LockWord& lock, std::uint64_t self) noexcept {
    std::uint64_t expected = 0;
    return lock.owner.compare_exchange_strong(expected, self, std::memory_order_acquire,
                                              std::memory_order_relaxed);
}

/// The contended path of lock(); out of line.
CHIMERA_API LockStatus lock_slow(LockWord& lock, const LockOptions& options) noexcept;

/// Acquires the lock: one CAS when free, else spin, block in FUTEX_LOCK_PI
/// (boosting the holder), recover, report corruption or time out.
inline LockStatus lock(LockWord& lock, const LockOptions& options = {}) noexcept {
    if (lock_if_free(lock, self_owner_id())) [[likely]]
        return LockStatus::acquired;
    return lock_slow(lock, options);
}

/// The release when the kernel has waiters queued (FUTEX_WAITERS): clears the
/// pid half (a clean hand-over) and calls FUTEX_UNLOCK_PI; out of line.
CHIMERA_API bool unlock_slow(LockWord& lock, std::uint64_t self, std::uint64_t seen) noexcept;

/// Releases the lock held by `self` (the caller's owner word, as given to
/// lock_if_free): true; false (and nothing changed) when the caller does not
/// hold it, e.g. because a waiter reset it after a timeout.
///
/// One compare-and-swap from `self` to free: it fails when the kernel set
/// FUTEX_WAITERS (a waiter blocked; unlock_slow hands the lock over) or when
/// the word no longer names the caller.
[[nodiscard]] inline bool unlock(LockWord& lock, std::uint64_t self) noexcept {
    std::uint64_t expected = self;
    if (lock.owner.compare_exchange_strong(expected, 0, std::memory_order_release,
                                           std::memory_order_relaxed)) [[likely]]
        return true;
    return unlock_slow(lock, self, expected);
}
/// The same, `self` being the caller's owner word (self_owner_id()).
[[nodiscard]] inline bool unlock(LockWord& lock) noexcept { return unlock(lock, self_owner_id()); }

/// Takes the lock over from a holder known to be dead (CAS from its word);
/// counts and reports the recovery. Exposed for services that find a dead
/// owner by other means.
CHIMERA_API LockStatus take_over(LockWord& lock, std::uint64_t dead_owner, std::int64_t waited_ns) noexcept;

/// RAII holder for set-up code (not for cycle code that must look at the status).
class LockGuard {
public:
    explicit LockGuard(LockWord& lock, const LockOptions& options = {}) noexcept
        : lock_(lock), status_(ipc::lock(lock, options)) {}
    ~LockGuard() {
        // A destructor cannot report a lock reset under its holder (possible only
        // with reset_on_timeout): code that must know calls unlock() itself.
        if (holds(status_)) (void)unlock(lock_);
    }
    LockGuard(const LockGuard&) = delete;
    LockGuard& operator=(const LockGuard&) = delete;
    LockStatus status() const noexcept { return status_; }
    bool owns() const noexcept { return holds(status_); }

private:
    LockWord& lock_;
    LockStatus status_;
};

}  // namespace chimera::ipc
