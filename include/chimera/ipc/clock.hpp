// chimera/ipc/clock.hpp — monotonic time in nanoseconds.
//
// clock_gettime(CLOCK_MONOTONIC) is served by the vDSO on Linux: no real
// system call, so it may be used on real-time paths (time-stamps, lock
// deadlines).
#pragma once

#include <cstdint>
#include <ctime>

namespace chimera::ipc {

/// Nanoseconds on CLOCK_MONOTONIC (shared by every process on the machine).
inline std::int64_t now_ns() noexcept {
    timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return static_cast<std::int64_t>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec;
}

/// A relative time in nanoseconds as a timespec.
inline timespec to_timespec(std::int64_t ns) noexcept {
    timespec ts;
    ts.tv_sec = static_cast<time_t>(ns / 1'000'000'000);
    ts.tv_nsec = static_cast<long>(ns % 1'000'000'000);
    return ts;
}

}  // namespace chimera::ipc
