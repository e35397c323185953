// chimera/tbuf.hpp — the triple buffer (TBUF, thesis §5.6).
//
// A one-way, non-blocking channel for periodic data between two tasks that run
// at unrelated rates (typically in different subsystems): one writer, one
// reader. Three slots: the writer fills its private slot and swaps it with the
// shared "middle" slot in one atomic exchange; the reader, when the middle
// slot holds something new, swaps its private slot with it in one atomic
// exchange. Neither side ever waits for the other, the reader always gets the
// newest complete item, and an item is never written while it is being read.
//
// Every item carries a time-stamp (CLOCK_MONOTONIC ns, taken in write() or
// supplied by the caller, e.g. the cycle's release time, which is cheaper)
// and a counter-stamp (0 for the first item, +1 per write). The reader learns
// whether an item is new or the one it already had, and how many it missed.
//
// The buffer lives either in its own shared-memory segment, found by name
// (create/attach), or in a block of memory the caller supplies (create_in/
// attach_in: another segment, a device's memory window). Both start with the
// common segment header, whose byte-order code is checked on attach: a buffer
// written by a machine of the other byte order is refused with a clear error
// (the synchronisation word is an atomic of this machine; item contents are
// the application's business, as in the thesis).
//
// Roles: one thread writes, one thread reads (each may be in any process, and
// a side may detach and another process take its role over later).
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <string>

#include "chimera/ipc/clock.hpp"
#include "chimera/ipc/segment.hpp"

namespace chimera::tbuf {

inline constexpr std::uint32_t kLayoutVersion = 1;

/// What a read found.
enum class ReadStatus : std::uint8_t {
    fresh,   ///< an item the reader had not seen
    reused,  ///< no new item since the last read: the same item again
    empty,   ///< nothing has been written yet
};

struct ReadResult {
    ReadStatus status = ReadStatus::empty;
    std::uint64_t counter = 0;  ///< counter-stamp of the item
    std::int64_t time_ns = 0;   ///< time-stamp of the item
    std::uint64_t missed = 0;   ///< items written but never read since the last fresh read
};

namespace detail {

inline constexpr std::uint32_t kFresh = 4;  // set in `middle` when it holds an unread item
inline constexpr std::uint32_t kIndex = 3;

struct alignas(64) SlotHeader {
    std::int64_t time_ns;
    std::uint64_t counter;
    std::uint64_t written;  // 1 once the slot holds an item
    std::uint8_t reserved[40];
};
static_assert(sizeof(SlotHeader) == 64);

struct alignas(64) Header {
    ipc::SegmentHeader segment;  // offset 0: magic, version, byte order
    // offset 64: fixed
    std::uint64_t item_size;
    std::uint64_t slot_stride;   // SlotHeader + item, rounded to 64
    std::uint64_t slots_offset;  // from the start of the block
    std::uint8_t reserved0[40];
    // offset 128: the only word both sides touch
    std::atomic<std::uint32_t> middle;
    std::uint8_t reserved1[60];
    // offset 192: writer's own line
    std::uint32_t back;
    std::uint32_t reserved2;
    std::uint64_t next_counter;
    std::uint8_t reserved3[48];
    // offset 256: reader's own line
    std::uint32_t front;
    std::uint32_t has_read;
    std::uint64_t last_counter;
    std::uint64_t missed_total;
    std::uint8_t reserved4[40];
};
static_assert(sizeof(Header) == 320);
static_assert(offsetof(Header, middle) == 128);
static_assert(offsetof(Header, back) == 192);
static_assert(offsetof(Header, front) == 256);

}  // namespace detail

/// Bytes of memory a buffer for items of `item_size` bytes needs.
std::size_t required_size(std::size_t item_size) noexcept;

/// A triple buffer. Move-only; destruction detaches.
class Tbuf {
public:
    Tbuf() noexcept = default;
    Tbuf(Tbuf&&) noexcept;
    Tbuf& operator=(Tbuf&&) noexcept;
    ~Tbuf() = default;

    /// tbufCreate: a new segment `name` for items of `item_size` bytes.
    static Tbuf create(const std::string& name, std::size_t item_size,
                       const ipc::CreateOptions& options = {});
    /// tbufAttach: the other side, by name.
    static Tbuf attach(const std::string& name, const ipc::AttachOptions& options = {});
    /// Lays a buffer out in caller-supplied memory (at least
    /// required_size(item_size) bytes, 64-byte aligned, zero or not).
    static Tbuf create_in(void* memory, std::size_t size, std::size_t item_size);
    /// Attaches to a buffer laid out by create_in (possibly by another process
    /// mapping the same memory); validates the header.
    static Tbuf attach_in(void* memory, std::size_t size);

    /// tbufDetach: unmaps (segment) or forgets (caller memory).
    void detach() noexcept;
    /// tbufDestroy: unmaps and removes the segment if this was its last user.
    bool destroy() noexcept;

    bool valid() const noexcept { return h_ != nullptr; }
    std::size_t item_size() const noexcept { return h_->item_size; }
    /// Total items the reader has missed (written, never read).
    std::uint64_t missed_total() const noexcept { return h_->missed_total; }

    // --- writer ----------------------------------------------------------------
    /// tbufWrite: copies `item` (item_size() bytes), stamps it with now_ns()
    /// and the next counter, and makes it the newest. Returns its counter.
    std::uint64_t write(const void* item) noexcept { return write(item, ipc::now_ns()); }
    /// As write(), with a caller-supplied time-stamp (saves reading the clock).
    std::uint64_t write(const void* item, std::int64_t time_ns) noexcept {
        std::memcpy(write_slot(), item, h_->item_size);
        return publish(time_ns);
    }
    /// Zero-copy writing: the writer's private slot, to fill in place...
    void* write_slot() noexcept { return data(h_->back); }
    /// ...then publish it (stamps, one atomic exchange). Returns its counter.
    std::uint64_t publish(std::int64_t time_ns) noexcept {
        detail::SlotHeader& s = slot(h_->back);
        const std::uint64_t counter = h_->next_counter++;
        s.time_ns = time_ns;
        s.counter = counter;
        s.written = 1;
        // Release: the item is complete before the reader can take it; acquire:
        // the reader is done with the slot we get back before we overwrite it.
        const std::uint32_t old =
            h_->middle.exchange(h_->back | detail::kFresh, std::memory_order_acq_rel);
        h_->back = old & detail::kIndex;
        return counter;
    }

    // --- reader ----------------------------------------------------------------
    /// tbufRead: the newest complete item, copied to `item` (unless empty).
    ReadResult read(void* item) noexcept {
        ReadResult r;
        const void* p = read_view(r);
        if (r.status != ReadStatus::empty) std::memcpy(item, p, h_->item_size);
        return r;
    }
    /// Zero-copy reading: the newest item in place, valid until the next read.
    const void* read_view(ReadResult& r) noexcept {
        bool fresh = false;
        if (h_->middle.load(std::memory_order_relaxed) & detail::kFresh) {
            const std::uint32_t old = h_->middle.exchange(h_->front, std::memory_order_acq_rel);
            h_->front = old & detail::kIndex;
            fresh = true;
        }
        const detail::SlotHeader& s = slot(h_->front);
        r.counter = s.counter;
        r.time_ns = s.time_ns;
        r.missed = 0;
        if (!s.written) {
            r.status = ReadStatus::empty;
        } else if (fresh) {
            r.status = ReadStatus::fresh;
            r.missed = h_->has_read ? s.counter - h_->last_counter - 1 : s.counter;
            h_->missed_total += r.missed;
            h_->last_counter = s.counter;
            h_->has_read = 1;
        } else {
            r.status = ReadStatus::reused;
        }
        return data(h_->front);
    }

private:
    explicit Tbuf(ipc::Segment seg);
    static detail::Header& init(void* memory, std::size_t size, std::size_t item_size);
    static void check(const std::string& where, void* memory, std::size_t size);

    detail::SlotHeader& slot(std::uint32_t i) noexcept {
        return *reinterpret_cast<detail::SlotHeader*>(base_ + h_->slots_offset + i * h_->slot_stride);
    }
    void* data(std::uint32_t i) noexcept { return &slot(i) + 1; }

    ipc::Segment seg_;             // empty for caller-supplied memory
    std::byte* base_ = nullptr;
    detail::Header* h_ = nullptr;
};

}  // namespace chimera::tbuf
