// Internal helpers shared by SEM and MSG: waitlists of Waiter slots, the
// object lock with repair-on-recovery, and the per-type segment factories the
// XM server calls. Not installed.
#pragma once

#include <string>

#include "chimera/ipc/clock.hpp"
#include "chimera/ipc/futex.hpp"
#include "chimera/ipc/lock.hpp"
#include "chimera/ipc/segment.hpp"
#include "chimera/xmail.hpp"

namespace chimera::xm::detail {

using layout::Waiter;

enum WaiterState : std::uint32_t { kFree = 0, kWaiting = 1, kSignaled = 2 };

/// Longest single sleep of a waiter: it then re-checks its word, so a
/// signaller that died between signalling and waking delays it by at most this.
inline constexpr std::int64_t kWaitSlice = 20'000'000;

/// How long object operations wait for the object's lock before lock_timeout.
inline constexpr std::int64_t kObjectLockTimeout = 2'000'000'000;

/// True unless the thread certainly no longer exists (cheap: one tgkill). A
/// zombie (killed, not yet reaped) passes: the hand-off paths use this, and a
/// grant to a zombie is taken back by the paths that find nothing available.
bool thread_exists(std::int32_t pid, std::int32_t tid) noexcept;
/// True when the thread runs: gone and zombie threads are not alive
/// (ipc::owner_alive: tgkill, then /proc). For the reclaim paths.
bool thread_alive(std::int32_t pid, std::int32_t tid) noexcept;

/// Takes a free slot for the calling thread (under the object's lock).
Waiter* waiter_add(Waiter* slots, std::uint32_t n, std::uint32_t& next_ticket,
                   std::int32_t priority) noexcept;
/// The waiting slot with the highest priority (earliest ticket among equals)
/// whose thread exists; slots of vanished threads are freed on the way (and
/// reported through `reclaimed`).
Waiter* waiter_pick(Waiter* slots, std::uint32_t n, std::uint32_t* reclaimed = nullptr) noexcept;
inline void waiter_signal(Waiter& w) noexcept {
    w.state = kSignaled;
    w.word.store(1, std::memory_order_release);
}
inline void waiter_free(Waiter& w) noexcept {
    w.state = kFree;
    w.handed = 0;
    w.pid = w.tid = 0;
    w.word.store(0, std::memory_order_relaxed);
}
inline void waiter_wake(Waiter& w) noexcept { ipc::futex_wake_all(w.word); }
/// Sleeps (outside the lock) until the slot is signalled or the absolute
/// deadline (negative: none) passes. True when signalled.
bool waiter_sleep(Waiter& w, std::int64_t deadline) noexcept;
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

inline std::int64_t deadline_for(std::int64_t timeout_ns) noexcept {
    return timeout_ns < 0 ? -1 : ipc::now_ns() + timeout_ns;
}

/// Factories run by the owning RTPU's XM server: create, initialise and
/// publish the segment `segment` for object `full_name`.
ipc::Segment create_shm_segment(const std::string& segment, const std::string& full_name,
                                const ObjectParams& params);
ipc::Segment create_sem_segment(const std::string& segment, const std::string& full_name,
                                const ObjectParams& params);
ipc::Segment create_msg_segment(const std::string& segment, const std::string& full_name,
                                const ObjectParams& params);

}  // namespace chimera::xm::detail
