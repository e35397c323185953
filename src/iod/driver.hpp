// Internal to src/iod: the driver factories open() dispatches to.
#pragma once

#include "chimera/iod.hpp"

namespace chimera::iod::detail {

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
