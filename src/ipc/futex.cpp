// Futex wait/wake (shared variants: the word is mapped by several processes).
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

}  // namespace

FutexResult futex_wait(std::atomic<std::uint32_t>& word, std::uint32_t expected,
                       std::int64_t timeout_ns) noexcept {
    if (timeout_ns < 0) return result_of(sys_futex(word, FUTEX_WAIT, expected, nullptr, 0));
    const timespec ts = to_timespec(timeout_ns);
    return result_of(sys_futex(word, FUTEX_WAIT, expected, &ts, 0));
}

FutexResult futex_wait_until(std::atomic<std::uint32_t>& word, std::uint32_t expected,
                             std::int64_t deadline_ns) noexcept {
    // FUTEX_WAIT_BITSET takes an absolute CLOCK_MONOTONIC time.
    const timespec ts = to_timespec(deadline_ns < 0 ? 0 : deadline_ns);
    return result_of(
        sys_futex(word, FUTEX_WAIT_BITSET, expected, &ts, FUTEX_BITSET_MATCH_ANY));
}

int futex_wake(std::atomic<std::uint32_t>& word, int count) noexcept {
    const long rc = sys_futex(word, FUTEX_WAKE, static_cast<std::uint32_t>(count), nullptr, 0);
    return rc < 0 ? 0 : static_cast<int>(rc);
}

int futex_wake_all(std::atomic<std::uint32_t>& word) noexcept {
    return futex_wake(word, INT_MAX);
}

}  // namespace chimera::ipc
