// Futex wait/wake: shared variants (the word is mapped by several processes)
// unless a FutexScope says the word is this process's own.
#include "chimera/ipc/futex.hpp"

#include <linux/futex.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <cerrno>
#include <climits>
#include <ctime>

#include "chimera/ipc/clock.hpp"

namespace chimera::ipc {
namespace {

long sys_futex(std::atomic<std::uint32_t>& word, int op, std::uint32_t val,
               const timespec* timeout, std::uint32_t val3) noexcept {
    return syscall(SYS_futex, reinterpret_cast<std::uint32_t*>(&word), op, val, timeout,
                   nullptr, val3);
}

FutexResult result_of(long rc) noexcept {
    if (rc == 0) return FutexResult::woken;
    switch (errno) {
        case EAGAIN: return FutexResult::value_changed;
        case ETIMEDOUT: return FutexResult::timed_out;
        case EINTR: return FutexResult::interrupted;
        default: return FutexResult::woken;  // caller re-checks the word
    }
}

int with_scope(int op, FutexScope scope) noexcept {
    return scope == FutexScope::process ? op | FUTEX_PRIVATE_FLAG : op;
}

}  // namespace

FutexResult futex_wait(std::atomic<std::uint32_t>& word, std::uint32_t expected, std::int64_t timeout_ns,
                       FutexScope scope) noexcept {
    const int op = with_scope(FUTEX_WAIT, scope);
    if (timeout_ns < 0) return result_of(sys_futex(word, op, expected, nullptr, 0));
    const timespec ts = to_timespec(timeout_ns);
    return result_of(sys_futex(word, op, expected, &ts, 0));
}

FutexResult futex_wait_until(std::atomic<std::uint32_t>& word, std::uint32_t expected, std::int64_t deadline_ns,
                             FutexScope scope) noexcept {
    // FUTEX_WAIT_BITSET takes an absolute CLOCK_MONOTONIC time.
    const timespec ts = to_timespec(deadline_ns < 0 ? 0 : deadline_ns);
    return result_of(
        sys_futex(word, with_scope(FUTEX_WAIT_BITSET, scope), expected, &ts, FUTEX_BITSET_MATCH_ANY));
}

int futex_wake_all(std::atomic<std::uint32_t>& word, FutexScope scope) noexcept {
    const long rc = sys_futex(word, with_scope(FUTEX_WAKE, scope), static_cast<std::uint32_t>(INT_MAX), nullptr, 0);
    return rc < 0 ? 0 : static_cast<int>(rc);
}

FutexResult futex_wait(std::atomic<std::uint32_t>& word, std::uint32_t expected,
                       std::int64_t timeout_ns) noexcept {
    return futex_wait(word, expected, timeout_ns, FutexScope::shared);
}

FutexResult futex_wait_until(std::atomic<std::uint32_t>& word, std::uint32_t expected,
                             std::int64_t deadline_ns) noexcept {
    return futex_wait_until(word, expected, deadline_ns, FutexScope::shared);
}

int futex_wake(std::atomic<std::uint32_t>& word, int count) noexcept {
    const long rc = sys_futex(word, FUTEX_WAKE, static_cast<std::uint32_t>(count), nullptr, 0);
    return rc < 0 ? 0 : static_cast<int>(rc);
}

int futex_wake_all(std::atomic<std::uint32_t>& word) noexcept {
    return futex_wake_all(word, FutexScope::shared);
}

}  // namespace chimera::ipc
