// The SVAR table segment's layout (internal). One segment:
//
//   TableHeader   segment header, table lock, counts, offsets, undo record
//   Descriptor[n] name, type, sizes, offsets of data/init/min/max/strings
//   u32[n]        undo index list (variables of the interrupted write-set)
//   data          the variables, each 16-byte aligned
//   undo data     a mirror of the data area: old contents of the write-set
//   values        INIT / MIN / MAX per variable, in the variable's own type
//   strings       DESC and UNITS texts, the source file name
//
// Every reference is an offset from the segment's start. Sizes are checked
// below so that a change of layout must bump kLayoutVersion.
//
// Also here: the table lock's cycle path (Table::acquire/release), inline in
// every file of the service that transfers data.
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <cstring>

#include "chimera/ipc/lock.hpp"
#include "chimera/ipc/segment.hpp"
#include "chimera/svar.hpp"

namespace chimera::svar::detail {

inline constexpr std::size_t kVarAlign = 16;

enum DescriptorFlags : std::uint32_t {
    kHasInit = 1u << 0,
    kHasRange = 1u << 1,
};

struct alignas(64) TableHeader {
    ipc::SegmentHeader segment;          // offset 0
    ipc::LockWord lock;                  // offset 64, its own cache line
    // --- offset 128: fixed after creation
    std::uint32_t nvars;
    std::uint32_t source_len;
    std::uint64_t desc_offset;
    std::uint64_t undo_index_offset;
    std::uint64_t data_offset;
    std::uint64_t data_bytes;
    std::uint64_t undo_offset;
    std::uint64_t source_offset;
    std::uint64_t reserved0;
    // --- offset 192: changes at run time
    std::atomic<std::uint32_t> illegal_config;
    std::atomic<std::uint32_t> rollbacks;
    std::atomic<std::uint32_t> undo_active;  // 1 while a write-set is being written
    std::uint32_t undo_count;                // variables in the undo index list
    std::uint64_t undo_writer;               // owner word of the writer (diagnostics)
    std::uint8_t reserved1[40];
};
static_assert(sizeof(TableHeader) == 256);
static_assert(offsetof(TableHeader, lock) == 64);
static_assert(offsetof(TableHeader, nvars) == 128);
static_assert(offsetof(TableHeader, illegal_config) == 192);

struct Descriptor {
    char name[16];              // NUL-terminated, at most kMaxNameLength characters
    std::uint32_t type;         // svar::Type
    std::uint32_t elem_size;
    std::uint32_t nelem;
    std::uint32_t flags;        // DescriptorFlags
    std::uint64_t data_offset;  // from the start of the data area (same in undo area)
    std::uint64_t bytes;        // elem_size * nelem
    std::uint64_t init_offset;  // from the segment start; 0 when absent
    std::uint64_t min_offset;
    std::uint64_t max_offset;
    std::uint64_t desc_offset;  // strings, from the segment start
    std::uint32_t desc_len;
    std::uint32_t units_len;
    std::uint64_t units_offset;
};
static_assert(sizeof(Descriptor) == 96);

}  // namespace chimera::svar::detail

namespace chimera::svar {

namespace detail {

// Copies one variable. Small ones (float[6], double[6]: the usual joint
// vectors) are moved with two to four unaligned 8- or 16-byte loads and stores
// inline: a call to memcpy, its size dispatch included, costs as much as the
// copy itself, and a multi-variable transfer makes one per variable.
[[gnu::always_inline]] inline void copy_var(std::byte* dst, const std::byte* src,
                                            std::size_t n) noexcept {
    if (n >= 16 && n <= 64) {
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
    } else if (n >= 8 && n < 16) {
        std::byte a[8], b[8];
        std::memcpy(a, src, 8);
        std::memcpy(b, src + n - 8, 8);
        std::memcpy(dst, a, 8);
        std::memcpy(dst + n - 8, b, 8);
    } else {
        std::memcpy(dst, src, n);
    }
}

}  // namespace detail

// The table lock on the cycle path: one CAS to take it, a store to give it back.
inline Status Table::acquire() noexcept {
    switch (ipc::lock(hdr_->lock, lock_options_)) {
        case ipc::LockStatus::acquired: return Status::ok;
        case ipc::LockStatus::recovered:
            roll_back();
            return Status::recovered;
        case ipc::LockStatus::forced: return Status::forced;
        case ipc::LockStatus::already_held: return Status::reentered;
        case ipc::LockStatus::busy:
        case ipc::LockStatus::timed_out: break;
    }
    return Status::timed_out;
}

inline Status Table::release(Status acquired) noexcept {
    if (!ipc::unlock(hdr_->lock)) return Status::lock_lost;
    return acquired;
}

}  // namespace chimera::svar
