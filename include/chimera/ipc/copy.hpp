// chimera/ipc/copy.hpp — the copy of a run-time-sized item on the hot paths
// (SVAR variables, TBUF items).
//
// A call to memcpy, its size dispatch included, costs as much as copying a
// small item itself; the usual items (float[6], double[6] joint vectors) are
// 8 to 64 bytes, so those are copied inline with two to four unaligned 8- or
// 16-byte loads and stores.
#pragma once

#include <cstddef>
#include <cstring>

namespace chimera::ipc {

// GCC, inlining these into a caller whose object it knows the size of (an
// 8-byte item), warns about the branch for larger sizes that the run-time
// size never takes (out of bounds, or reading bytes never set): not a real
// access.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Warray-bounds"
#pragma GCC diagnostic ignored "-Wstringop-overread"
#pragma GCC diagnostic ignored "-Wstringop-overflow"
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"

/// Copies 8 to 64 bytes (is_small(n)) inline.
[[gnu::always_inline]] inline void copy_small(std::byte* dst, const std::byte* src,
                                              std::size_t n) noexcept {
    if (n >= 16) {
        std::byte a[16], b[16], c[16], d[16];
        std::memcpy(a, src, 16);
        std::memcpy(b, src + n - 16, 16);
        if (n > 32) {
            std::memcpy(c, src + 16, 16);
            std::memcpy(d, src + n - 32, 16);
            std::memcpy(dst + 16, c, 16);
            std::memcpy(dst + n - 32, d, 16);
        }
        std::memcpy(dst, a, 16);
        std::memcpy(dst + n - 16, b, 16);
    } else {
        std::byte a[8], b[8];
        std::memcpy(a, src, 8);
        std::memcpy(b, src + n - 8, 8);
        std::memcpy(dst, a, 8);
        std::memcpy(dst + n - 8, b, 8);
    }
}

/// True for the sizes copy_small() takes.
constexpr bool is_small(std::size_t n) noexcept { return n - 8 <= 56; }

/// Copies `n` bytes: copy_small() or memcpy.
[[gnu::always_inline]] inline void copy_var(std::byte* dst, const std::byte* src,
                                            std::size_t n) noexcept {
    if (is_small(n))
        copy_small(dst, src, n);
    else
        std::memcpy(dst, src, n);
}

#pragma GCC diagnostic pop

}  // namespace chimera::ipc
