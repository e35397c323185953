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

#include "chimera/ipc/copy.hpp"
#include "chimera/ipc/lock.hpp"
#include "chimera/ipc/segment.hpp"
#include "chimera/ipc/seqlock.hpp"
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
    // Odd while a write-set is being written (undo_mark .. undo_clear, or a
    // roll-back): watchers, who take no lock, copy by it (ipc/seqlock.hpp).
    std::atomic<std::uint32_t> write_seq;
    std::uint8_t reserved1[36];
};
static_assert(sizeof(TableHeader) == 256);
static_assert(offsetof(TableHeader, lock) == 64);
static_assert(offsetof(TableHeader, nvars) == 128);
static_assert(offsetof(TableHeader, illegal_config) == 192);
static_assert(offsetof(TableHeader, write_seq) == 216);

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

// The copies of a variable's bytes (inline for 8 to 64 bytes): ipc/copy.hpp.
using ipc::copy_small;
using ipc::copy_var;
using ipc::is_small;

// The undo record around a write into the global table (see svar.hpp). The
// writer saves the old contents of its write-set into the undo area and their
// indices into the undo list, then marks the record active; writes; clears
// the mark.
inline void undo_mark(TableHeader& h, std::uint32_t count, std::uint64_t writer) noexcept {
    ipc::seqlock::write_begin(h.write_seq);
    h.undo_count = count;
    h.undo_writer = writer;
    // Release: the saved copy is complete before the record is marked active.
    h.undo_active.store(1, std::memory_order_release);
    // And no store of the write-set moves above the mark: a holder that dies
    // stops at an instruction boundary, so the order the waiter must be able
    // to rely on is program order, which the compiler must not change.
    std::atomic_signal_fence(std::memory_order_seq_cst);
}

inline void undo_clear(TableHeader& h) noexcept {
    // Release: the new data is complete before the record is dropped.
    h.undo_active.store(0, std::memory_order_release);
    ipc::seqlock::write_end(h.write_seq);
}

}  // namespace detail

// The table lock on the cycle path: one CAS to take it, one to give it back.
inline Status Table::acquire() noexcept {
    switch (ipc::lock(hdr_->lock, lock_options_)) {
        case ipc::LockStatus::acquired: return Status::ok;
        case ipc::LockStatus::recovered:
            roll_back();
            return Status::recovered;
        case ipc::LockStatus::forced: return Status::forced;
        case ipc::LockStatus::already_held: return Status::reentered;
        case ipc::LockStatus::corrupt: return Status::lock_corrupt;
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
