// Internal to src/iod: the driver factories open() dispatches to.
#pragma once

#include "chimera/iod.hpp"

#include <ctime>

namespace chimera::iod::detail {

/// The WAIT_TIMEOUT bound of one blocking read (Control::WAIT_TIMEOUT, in
/// microseconds; -1: none). The deadline is read from CLOCK_MONOTONIC through
/// the vDSO: no system call for it.
class WaitBound {
public:
    explicit WaitBound(long timeout_us) noexcept : bounded_(timeout_us >= 0) {
        if (!bounded_) return;
        clock_gettime(CLOCK_MONOTONIC, &deadline_);
        deadline_.tv_sec += timeout_us / 1000000;
        deadline_.tv_nsec += (timeout_us % 1000000) * 1000;
        if (deadline_.tv_nsec >= 1000000000) {
            deadline_.tv_nsec -= 1000000000;
            ++deadline_.tv_sec;
        }
    }
    /// False when the time has run out; else `wait` is what to give ppoll()
    /// (nullptr: no bound).
    bool left(const timespec*& wait) noexcept {
        if (!bounded_) {
            wait = nullptr;
            return true;
        }
        timespec now{};
        clock_gettime(CLOCK_MONOTONIC, &now);
        const long long ns = (static_cast<long long>(deadline_.tv_sec) - now.tv_sec) * 1000000000LL +
                             (deadline_.tv_nsec - now.tv_nsec);
        if (ns <= 0) return false;
        left_.tv_sec = static_cast<time_t>(ns / 1000000000LL);
        left_.tv_nsec = static_cast<long>(ns % 1000000000LL);
        wait = &left_;
        return true;
    }

private:
    bool bounded_;
    timespec deadline_{}, left_{};
};

// Each factory validates what only the driver knows (direction against the
// hardware, flags it cannot honour), acquires the kernel interface, and
// throws iod::Error naming the device when it cannot.
// `initial` (PIO outputs only, checked by open()): the elements the lines
// are requested with.
std::unique_ptr<Device> make_pio(const DeviceSpec& spec, int start, int end, unsigned flags,
                                 const void* initial);
std::unique_ptr<Device> make_can(const DeviceSpec& spec, int start, int end, unsigned flags);
std::unique_ptr<Device> make_sio(const DeviceSpec& spec, int start, int end, unsigned flags);
std::unique_ptr<Device> make_mem(const DeviceSpec& spec, int start, int end, unsigned flags);

/// "device NAME (FILE:LINE)" for messages.
std::string describe(const DeviceSpec& spec);

}  // namespace chimera::iod::detail
