// chimera/ipc/fault.hpp — what a reader found wrong in shared memory that
// another process writes.
//
// Every offset, length, index and link that a process reads from a segment
// another process may write is bounded before it is used (issue #15.3): a
// process that may write a segment must not be able to crash, or make read
// outside the segment, any process that reads it. The checks are pure
// functions over the bytes of a segment (each service's validate_*()), so a
// fuzzer can call them on arbitrary images; a hot path that finds a bad value
// refuses the operation with a Status (corrupt) and keeps the Fault, which
// describe() turns into a message naming the segment, off the hot path.
#pragma once

#include "chimera/export.hpp"

#include <cstdint>
#include <string>
#include <string_view>

namespace chimera::ipc {

/// One broken bound. `field` is static text ("ring record length"), so
/// recording a fault allocates nothing; `index` says which element of an
/// array (ring, waiter, header), -1 for none.
struct [[nodiscard]] Fault {
    const char* field = nullptr;  ///< nullptr: no fault
    std::int64_t index = -1;
    std::uint64_t value = 0;      ///< what was found
    std::uint64_t limit = 0;      ///< the bound it broke
    const char* rule = "at most"; ///< how value relates to limit when sound

    explicit operator bool() const noexcept { return field != nullptr; }
};

/// A fault, or none, as one expression: `return fault_if(x > n, "x", x, n);`.
constexpr Fault fault_if(bool broken, const char* field, std::uint64_t value, std::uint64_t limit,
                         const char* rule = "at most", std::int64_t index = -1) noexcept {
    return broken ? Fault{field, index, value, limit, rule} : Fault{};
}

/// "segment /chimera.arm.xm.b: ring 3 record length 99999 (must be at most 4088)";
/// "" for no fault.
CHIMERA_API std::string describe(std::string_view segment, const Fault& fault);

}  // namespace chimera::ipc
