// chimera/ipc/futex.hpp — futex wait/wake on a 32-bit word in shared memory.
//
// The Linux form of the thesis's mailbox interrupt / xmWakeup (§5.3). The
// operations without a FutexScope are the shared (not FUTEX_PRIVATE) variants,
// because the word lives in a segment that several processes map, each at its
// own address.
#pragma once

#include "chimera/export.hpp"

#include <atomic>
#include <cstdint>

namespace chimera::ipc {

static_assert(sizeof(std::atomic<std::uint32_t>) == sizeof(std::uint32_t));
static_assert(std::atomic<std::uint32_t>::is_always_lock_free);

/// Result of a wait.
enum class FutexResult {
    woken,        ///< woken by futex_wake (or spuriously): re-check the word
    value_changed,///< the word did not hold `expected` when the kernel looked
    timed_out,    ///< the timeout passed
    interrupted,  ///< a signal handler ran
};

/// Sleeps while `word` holds `expected`, at most `timeout_ns` (negative: no
/// limit). A system call, by nature: for the blocking path only.
CHIMERA_API FutexResult futex_wait(std::atomic<std::uint32_t>& word, std::uint32_t expected,
                                   std::int64_t timeout_ns = -1) noexcept;

/// As futex_wait, but until an absolute CLOCK_MONOTONIC time (see now_ns()).
CHIMERA_API FutexResult futex_wait_until(std::atomic<std::uint32_t>& word, std::uint32_t expected,
                                         std::int64_t deadline_ns) noexcept;

/// Wakes up to `count` waiters on `word`; returns how many were woken.
CHIMERA_API int futex_wake(std::atomic<std::uint32_t>& word, int count = 1) noexcept;

/// Wakes every waiter on `word`.
CHIMERA_API int futex_wake_all(std::atomic<std::uint32_t>& word) noexcept;

/// Who may wait on and wake a word. `process`: only threads of this process
/// (FUTEX_PRIVATE_FLAG): the kernel finds the word without looking up its
/// page, a cheaper call on a real-time path. A waiter and its wakers must use
/// the same scope: a private wake does not reach a shared waiter.
enum class FutexScope : std::uint8_t { shared, process };

/// The same operations in a given scope.
CHIMERA_API FutexResult futex_wait(std::atomic<std::uint32_t>& word, std::uint32_t expected,
                                   std::int64_t timeout_ns, FutexScope scope) noexcept;
CHIMERA_API FutexResult futex_wait_until(std::atomic<std::uint32_t>& word, std::uint32_t expected,
                                         std::int64_t deadline_ns, FutexScope scope) noexcept;
CHIMERA_API int futex_wake_all(std::atomic<std::uint32_t>& word, FutexScope scope) noexcept;

}  // namespace chimera::ipc
