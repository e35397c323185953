// chimera/ipc/lock.hpp — the table lock (the thesis's xmLock, §5.3, §6.6).
//
// A spin-lock in shared memory whose word holds the owner, (pid << 32 | tid),
// 0 when free. Acquiring it uncontended is one compare-and-swap, releasing it
// one store: no system call, no allocation (the caller's pid/tid are cached per thread). Under
// contention the caller spins a bounded number of times with the CPU's polling
// pause, then polls with short sleeps until its timeout.
//
// What the thesis's xmLock did on timeout — reset the lock blindly — can tear
// data that was consistent. Here, while polling, the waiter checks whether the
// holder still exists (tgkill(pid, tid, 0), then /proc/<pid>/task/<tid>/stat to
// tell a zombie); a holder that died is detected and the lock taken over, and
// the caller is TOLD (LockStatus::recovered) so it can repair what the holder
// was writing (the SVAR table rolls back an undo record). A timeout is
// reported (LockStatus::timed_out) and the lock is left alone; only a caller
// that asks for it (LockOptions::reset_on_timeout) gets the thesis's blind
// reset, reported as LockStatus::forced. Every recovery, timeout and reset
// also bumps a counter in the lock and calls the process-wide handler, if one
// is set: never silent.
//
// Limits: the owner is identified by the pid/tid of the caller's PID
// namespace; all users of one lock must share it (one machine, one container).
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
    std::uint32_t reserved0 = 0;
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
    /// Spins with the CPU's pause instruction before the first sleep.
    std::uint32_t spin_count = 200;
    /// First sleep between polls; doubles up to max_sleep_ns.
    std::int64_t min_sleep_ns = 2'000;
    std::int64_t max_sleep_ns = 200'000;
    /// How often, while polling, to check that the holder is alive.
    std::int64_t liveness_check_ns = 1'000'000;
    /// The thesis's blind reset when the timeout passes (reported as forced).
    bool reset_on_timeout = false;
};

/// Reported to the process-wide handler.
struct LockEvent {
    enum class Kind { recovered, timed_out, forced } kind;
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
constexpr std::int32_t owner_tid(std::uint64_t word) noexcept {
    return static_cast<std::int32_t>(word & 0xffffffffu);
}

/// True when the thread named by an owner word still exists (and is not a
/// zombie). A system call: for slow paths only.
CHIMERA_API bool owner_alive(std::uint64_t word) noexcept;

/// One attempt; no waiting, no liveness check.
inline LockStatus try_lock(LockWord& lock) noexcept {
    std::uint64_t expected = 0;
    const std::uint64_t me = self_owner_id();
    if (lock.owner.compare_exchange_strong(expected, me, std::memory_order_acquire,
                                           std::memory_order_relaxed))
        return LockStatus::acquired;
    return expected == me ? LockStatus::already_held : LockStatus::busy;
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

/// Acquires the lock: one CAS when free, else spin, poll, recover or time out.
inline LockStatus lock(LockWord& lock, const LockOptions& options = {}) noexcept {
    if (lock_if_free(lock, self_owner_id())) [[likely]]
        return LockStatus::acquired;
    return lock_slow(lock, options);
}

/// Releases the lock held by `self` (the caller's owner word, as given to
/// lock_if_free): true; false (and nothing changed) when the caller does not
/// hold it, e.g. because a waiter reset it after a timeout.
///
/// A check and a plain release store, not a compare-and-swap: a locked
/// instruction here would double the cost of an uncontended transfer. Only a
/// holder can be displaced while it runs, and only by the opt-in blind reset
/// (reset_on_timeout, after the full timeout): if that reset lands between the
/// check and the store, the store frees the new holder's lock, and that holder
/// learns it when its own unlock() returns false. The reset is reported as
/// forced in any case, and forced already means "data may be torn".
[[nodiscard]] inline bool unlock(LockWord& lock, std::uint64_t self) noexcept {
    if (lock.owner.load(std::memory_order_relaxed) != self) return false;
    lock.owner.store(0, std::memory_order_release);
    return true;
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
