// chimera/tbuf.hpp — the triple buffer (TBUF, thesis §5.6).
//
// A one-way, non-blocking channel for periodic data between two tasks that run
// at unrelated rates (typically in different subsystems): one writer, one
// reader. Three slots: the writer fills its private "back" slot and swaps it
// with the shared "middle" slot; the reader, when the middle slot holds
// something new, swaps its private "front" slot with it. Neither side ever
// waits for the other (lock-free: the writer's swap succeeds at the latest at
// its second try, the reader's whenever the writer is not publishing at that
// very instant), the reader always gets the newest complete item, and an item
// is never written while it is being read.
//
// The slots' roles, and what survives a kill (issue #15.2). The one word both
// sides change is the middle word: the middle slot's number and a "fresh" bit
// (an item the reader has not taken). Each side swaps its slot into it with
// one exchange — the writer sets the fresh bit, the reader clears it — and
// keeps the slot it gets back, as the Rust triple_buffer crate does. An
// exchange cannot fail, so neither side ever loops (a compare-and-swap cost
// 1.4 ns more a write+read; bench/results/svar.md).
//
// So that a side's successor can take its role over after a kill -9, each side
// keeps a record of its slot in a line of its own, stored after each exchange,
// and says when it is between its exchange and that record:
// - the writer by its stamp: its record also holds the counter-stamp of the
//   item it published last, and the stamp it writes into its slot before the
//   exchange is newer than that (nothing added to the publish);
// - the reader by a bit in its record, set by one store before its exchange.
// Taking a role over (serialised by a robust lock in the header; the hot
// paths never touch it):
// - The writer's successor takes the recorded slot when the stamp does not
//   say otherwise: right also when the dead writer's item there is half-
//   written (only the writer role ever holds a slot being written).
// - Otherwise (the writer died inside its publish: every item is then
//   complete), and always for the reader's successor: the slot that is
//   neither the middle one nor the one the other side's record names. The
//   dead side's slot no longer moves, and the middle and the other side's
//   slot are the two others at any instant — read while the other side is
//   not inside an exchange. While it is, and lives, the successor waits for
//   it (100 ms at most, then refuses); when it died there too, every slot is
//   complete, nobody holds one, and the successor takes the lowest (writer) or
//   highest (reader) slot that is not the middle one.
// The writer's successor goes on counting from the newest counter-stamp in
// any slot, so counters never repeat; a writer killed in the few instructions
// between stamping an item and publishing it leaves a gap of one (the reader
// counts that item missed).
//
// Every item carries a time-stamp (CLOCK_MONOTONIC ns, read in write() through
// the vDSO, or supplied by the caller, e.g. the cycle's release time, which
// saves the clock read) and a counter-stamp (0 for the first item, +1 per
// publish). The reader learns whether an item is new or the one it already had,
// and how many it missed.
//
// The buffer lives either in its own shared-memory segment, found by name
// (create/attach), or in a block of memory the caller supplies (create_in/
// attach_in: another segment, a device's memory window). Both start with the
// common segment header, whose byte-order code is checked on attach: a buffer
// written by a machine of the other byte order is refused with a clear error
// (the middle word and the records are atomics of this machine; item contents
// are the application's business, as in the thesis).
//
// Untrusted memory (issue #15.3): the geometry (item size, slot places) is
// checked once on attach (validate()) and then kept in the handle, so nothing
// another process writes later can move a copy outside the buffer. The middle
// word is checked on every operation (a slot number below 3, not the caller's
// own slot, no stray bit) and the records when a role is taken over; a bad one
// is refused: write() returns kCorrupt, read() ReadStatus::corrupt, and
// fault_message() names the segment. A damaged middle word met by an exchange
// is put back when nothing moved since, so the item is not published.
//
// Roles: one thread writes, one thread reads (each may be in any process, and
// a side may detach, or be killed, and another process take its role over).
// A handle that has written keeps the writer's slot number: hand the role
// over by detaching (or dying), never by writing through two live handles in
// turn; a handle that finds another one has published since refuses
// (kCorrupt, "another writer") instead of going on. The same holds for
// reading: one live reading handle at a time.
#pragma once

#include "chimera/export.hpp"

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <string>

#include "chimera/ipc/clock.hpp"
#include "chimera/ipc/copy.hpp"
#include "chimera/ipc/fault.hpp"
#include "chimera/ipc/lock.hpp"
#include "chimera/ipc/segment.hpp"

namespace chimera::tbuf {

inline constexpr std::uint32_t kLayoutVersion = 3;

/// What a read found.
enum class ReadStatus : std::uint8_t {
    fresh,    ///< an item the reader had not seen
    reused,   ///< no new item since the last read: the same item again
    empty,    ///< nothing has been written yet
    corrupt,  ///< the middle word or a record is damaged: nothing read (see fault_message())
};

struct [[nodiscard]] ReadResult {
    ReadStatus status = ReadStatus::empty;
    std::uint64_t counter = 0;  ///< counter-stamp of the item
    std::int64_t time_ns = 0;   ///< time-stamp of the item
    std::uint64_t missed = 0;   ///< items written but never read since the last fresh read
};

/// What write() and publish() return when the buffer is damaged.
inline constexpr std::uint64_t kCorrupt = ~std::uint64_t{0};

namespace detail {

// The middle word: bits 0-1 the middle slot, bit 2 set while its item is
// unread. Nothing else may be set.
inline constexpr std::uint32_t kFresh = 1u << 2;
inline constexpr std::uint32_t kSlotMask = 3u;
/// No slot: a handle that has not taken its role yet.
inline constexpr std::uint32_t kNoSlot = 3u;
/// A role's record: its slot in bits 0-1; the writer's also the counter-stamp
/// (Stamp::seq) of the item it published last, from bit 2; the reader's
/// kExchanging while it is inside an exchange.
constexpr std::uint64_t make_record(std::uint32_t slot, std::uint64_t published) noexcept {
    return slot | published << 2;
}
constexpr std::uint32_t record_slot(std::uint64_t r) noexcept { return static_cast<std::uint32_t>(r & kSlotMask); }
constexpr std::uint64_t record_published(std::uint64_t r) noexcept { return r >> 2; }
inline constexpr std::uint64_t kExchanging = 1u << 2;
/// A middle word a side holding slot `own` can accept: a slot number, not its
/// own, no stray bit (a few ALU operations: every operation checks it).
constexpr bool middle_valid(std::uint32_t m, std::uint32_t own) noexcept {
    return (m & ~(kSlotMask | kFresh)) == 0 && (m & kSlotMask) < 3 && (m & kSlotMask) != own;
}
/// The slot that is neither a nor b (a != b, both below 3).
constexpr std::uint32_t third_slot(std::uint32_t a, std::uint32_t b) noexcept { return 3u - a - b; }
static_assert(middle_valid(1, 0) && middle_valid(2 | kFresh, 0) && !middle_valid(0, 0));
static_assert(!middle_valid(3, 0) && !middle_valid(1 | 1u << 3, 0) && third_slot(2, 0) == 1);

/// After each slot's item: its stamps.
struct Stamp {
    std::int64_t time_ns;
    std::uint64_t seq;  // counter-stamp + 1; 0 while the slot never held an item
};
static_assert(sizeof(Stamp) == 16);
/// Stamps from 2^63 on cannot come from counting: a writer refuses to go on from one.
inline constexpr std::uint64_t kMaxSeq = std::uint64_t{1} << 63;

/// One role's line, written only by the handle that holds the role.
struct alignas(64) Role {
    std::atomic<std::uint64_t> record;  // make_record(), stored after each exchange
    std::atomic<std::uint64_t> owner;   // the thread that took the role last (pid << 32 | tid)
    std::uint8_t reserved[48];
};
static_assert(std::atomic<std::uint64_t>::is_always_lock_free);
static_assert(sizeof(Role) == 64);

struct alignas(64) Header {
    ipc::SegmentHeader segment;  // offset 0: magic, version, byte order
    // offset 64: fixed at creation
    std::uint64_t item_size;
    std::uint64_t slot_stride;   // item + Stamp, rounded to 64
    std::uint64_t slots_offset;  // from the start of the block
    std::uint64_t stamp_offset;  // of a slot's Stamp, from the slot's start
    std::uint8_t reserved0[32];
    // offset 128: the only word both sides write
    std::atomic<std::uint32_t> middle;
    std::uint8_t reserved1[60];
    Role writer;                 // offset 192
    Role reader;                 // offset 256
    ipc::LockWord roles;         // offset 320: held while a handle takes a role over
};
static_assert(sizeof(Header) == 384);
static_assert(offsetof(Header, middle) == 128 && offsetof(Header, writer) == 192 &&
              offsetof(Header, reader) == 256 && offsetof(Header, roles) == 320);
static_assert(std::atomic<std::uint32_t>::is_always_lock_free);

}  // namespace detail

/// Bytes of memory a buffer for items of `item_size` bytes needs.
CHIMERA_API std::size_t required_size(std::size_t item_size) noexcept;

/// Checks a buffer's image of `size` bytes (header, geometry, middle word,
/// records) as attach() does, without throwing: the first bound broken, or
/// none. A pure function over the bytes, for tests and fuzzers.
CHIMERA_API ipc::Fault validate(const void* image, std::size_t size) noexcept;

/// A triple buffer. Move-only; destruction detaches.
class CHIMERA_API Tbuf {
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
    /// tbufDestroy: unmaps and removes the segment if no other live process
    /// maps it (users killed without detaching are not counted).
    bool destroy() noexcept;

    bool valid() const noexcept { return h_ != nullptr; }
    std::size_t item_size() const noexcept { return item_size_; }
    /// Total items this handle's reads found missed (written, never read).
    std::uint64_t missed_total() const noexcept { return missed_total_; }
    /// What the last refused operation found damaged, naming the segment ("" if none).
    std::string fault_message() const;

    // --- writer ----------------------------------------------------------------
    /// tbufWrite: copies `item` (item_size() bytes), stamps it with now_ns()
    /// (read after the copy, when the item is complete: measured 1 ns of 51
    /// faster at 24 bytes than reading it first) and the next counter, and
    /// makes it the newest. Returns its counter (kCorrupt, nothing published,
    /// when the middle word or a record is damaged, another handle has written
    /// since, or the newest item's counter-stamp is one no writer could have
    /// made, >= kMaxSeq).
    [[nodiscard]] std::uint64_t write(const void* item) noexcept {
        if (back_ == detail::kNoSlot && !become_writer()) [[unlikely]]
            return kCorrupt;
        ipc::copy_var(slot_at(back_), static_cast<const std::byte*>(item), item_size_);
        // The stamps' place is taken before the clock read (a call, after
        // which the handle's fields would be loaded again).
        detail::Stamp& st = stamp(back_);
        return swap_in(st, ipc::now_ns());
    }
    /// As write(), with a caller-supplied time-stamp (saves reading the clock).
    /// Always inlined, as read() is: the call cost 0.5-0.7 ns of a 24-byte
    /// write+read's 27 (bench/results/svar.md).
    [[nodiscard, gnu::always_inline]] std::uint64_t write(const void* item, std::int64_t time_ns) noexcept {
        if (back_ == detail::kNoSlot && !become_writer()) [[unlikely]]
            return kCorrupt;
        ipc::copy_var(slot_at(back_), static_cast<const std::byte*>(item), item_size_);
        return swap_in(stamp(back_), time_ns);
    }
    /// Zero-copy writing: the writer's private slot, to fill in place
    /// (nullptr when the buffer is damaged)...
    [[nodiscard]] void* write_slot() noexcept {
        if (back_ == detail::kNoSlot && !become_writer()) [[unlikely]]
            return nullptr;
        return slot_at(back_);
    }
    /// The counter-stamp the next publish of this handle will carry (the
    /// newest item's + 1, also when a killed writer's successor goes on);
    /// kCorrupt when the buffer is damaged.
    [[nodiscard]] std::uint64_t next_counter() noexcept {
        if (back_ == detail::kNoSlot && !become_writer()) [[unlikely]]
            return kCorrupt;
        return seq_;
    }
    /// ...then publish it (stamps, one exchange). Returns its counter.
    [[nodiscard]] std::uint64_t publish(std::int64_t time_ns) noexcept {
        if (back_ == detail::kNoSlot && !become_writer()) [[unlikely]]
            return kCorrupt;
        return swap_in(stamp(back_), time_ns);
    }

    // --- reader ----------------------------------------------------------------
    /// tbufRead: the newest complete item, copied to `item` (unless empty or corrupt).
    [[gnu::always_inline]] ReadResult read(void* item) noexcept {
        const void* p = nullptr;
        const ReadResult r = take(p);
        if (r.status <= ReadStatus::reused)
            ipc::copy_var(static_cast<std::byte*>(item), static_cast<const std::byte*>(p), item_size_);
        return r;
    }
    /// True when an item this reader has not read is waiting: one load, no
    /// change to the buffer (a reader polling for a new item looks with it,
    /// then reads).
    bool fresh_pending() const noexcept {
        return (h_->middle.load(std::memory_order_relaxed) & detail::kFresh) != 0;
    }
    /// Zero-copy reading: the newest item in place, valid until the next read
    /// (nullptr when the buffer is damaged).
    [[gnu::always_inline]] const void* read_view(ReadResult& r) noexcept {
        const void* p = nullptr;
        r = take(p);
        return p;
    }

private:
    // The reader's step: takes the middle slot if it holds a new item, and
    // points `item` at the front slot (left alone when corrupt). The result is
    // made at the end, not filled in before the exchange: stores pending at a
    // locked instruction make it wait.
    [[gnu::always_inline]] ReadResult take(const void*& item) noexcept {
        if (front_ == detail::kNoSlot && !become_reader()) [[unlikely]]
            return ReadResult{ReadStatus::corrupt, 0, 0, 0};
        const std::uint32_t m = h_->middle.load(std::memory_order_relaxed);
        if (!detail::middle_valid(m, front_)) [[unlikely]]
            return refuse_read(m);
        if (!(m & detail::kFresh))
            return view(front_, ReadStatus::reused, item);
        // Before the exchange: the old front slot is the writer's after it.
        const std::uint64_t had = front_seq_ != kUnknownSeq ? front_seq_ : stamp(front_).seq;
        h_->reader.record.store(front_ | detail::kExchanging, std::memory_order_relaxed);
        // Release: we are done with our old slot before the writer gets it
        // (and the mark is visible before the exchange); acquire: the item we
        // take is complete. What comes back is the newest item (the writer
        // may have published again since the load).
        const std::uint32_t got = h_->middle.exchange(front_, std::memory_order_acq_rel);
        if (!detail::middle_valid(got, front_) || !(got & detail::kFresh)) [[unlikely]]
            return refuse_taken(got);
        front_ = got & detail::kSlotMask;
        h_->reader.record.store(front_, std::memory_order_relaxed);
        ReadResult r = view(front_, ReadStatus::fresh, item);
        if (r.status == ReadStatus::fresh) {
            r.missed = front_seq_ - had - 1;  // had == 0: every item before this one
            if (r.missed != 0)  // no store when none was missed, the usual case
                missed_total_ += r.missed;
        }
        return r;
    }
    // The item in `slot`, now the reader's: `item` points at it; its stamps
    // (empty when the slot never held an item; missed 0).
    [[gnu::always_inline]] ReadResult view(std::uint32_t slot, ReadStatus status, const void*& item) noexcept {
        const detail::Stamp& st = stamp(slot);
        front_seq_ = st.seq;
        item = slot_at(slot);
        return st.seq == 0 ? ReadResult{ReadStatus::empty, 0, st.time_ns, 0}
                           : ReadResult{status, st.seq - 1, st.time_ns, 0};
    }

    // Stamps the back slot with the next counter and swaps it into the middle.
    [[gnu::always_inline]] std::uint64_t swap_in(detail::Stamp& st, std::int64_t time_ns) noexcept {
        st.time_ns = time_ns;
        // Atomic (a plain store on x86-64 and AArch64): a reader taking its
        // role over may look at this stamp meanwhile (Tbuf::exchanging()).
        std::atomic_ref<std::uint64_t>(st.seq).store(seq_ + 1, std::memory_order_relaxed);
        // Our record still names our slot, or another handle has written
        // since (it is not on the way to the exchange: a predicted branch).
        if (detail::record_slot(h_->writer.record.load(std::memory_order_relaxed)) != back_) [[unlikely]]
            return lost_writer_slot();
        // Release: the item and its stamps are complete before the reader can
        // take them; acquire: the reader is done with the slot we get back.
        const std::uint32_t got = h_->middle.exchange(back_ | detail::kFresh, std::memory_order_acq_rel);
        if (!detail::middle_valid(got, back_)) [[unlikely]]
            return refuse_published(got);
        back_ = got & detail::kSlotMask;
        h_->writer.record.store(detail::make_record(back_, seq_ + 1), std::memory_order_relaxed);
        return seq_++;
    }

    explicit Tbuf(ipc::Segment seg);
    static detail::Header& init(void* memory, std::size_t size, std::size_t item_size);
    static void check(const std::string& where, const void* memory, std::size_t size);
    void bind(std::byte* base) noexcept;

    // A handle's first write or read takes the role over (under the header's
    // role lock; see the top of this file): its slot, and for the writer the
    // counter to go on from. False (fault recorded) when the buffer is
    // damaged or the other side stays inside its exchange past a bound.
    bool become_writer() noexcept;
    bool become_reader() noexcept;
    // The slot the role's successor takes.
    bool find_writer_slot(std::uint32_t& slot) noexcept;
    bool find_reader_slot(std::uint32_t& slot) noexcept;
    // The slot that is neither the middle one nor the one `other` records,
    // read while `other` is not inside an exchange: waits while it is and
    // lives; kNoSlot when it died there (`middle` then says which slot not to
    // take). False when damaged or timed out.
    bool third_of_middle_and(const detail::Role& other, std::uint32_t& slot, std::uint32_t& middle) noexcept;
    // The other side is inside an exchange (by its record, or the stamp in
    // the slot the writer's record names).
    bool exchanging(const detail::Role& other, std::uint64_t record) noexcept;

    // Another handle moved the writer's slot: nothing published. Records the
    // fault; kCorrupt.
    std::uint64_t lost_writer_slot() noexcept;
    // An exchange brought back a damaged middle word: put it back if nothing
    // moved since (nothing published / taken; the slot stays ours), else take
    // the role over again at the next operation; record the fault.
    std::uint64_t refuse_published(std::uint32_t got) noexcept;
    ReadResult refuse_taken(std::uint32_t got) noexcept;
    // Record a damaged middle word; kCorrupt / a corrupt result.
    std::uint64_t refuse(std::uint32_t m) noexcept;
    ReadResult refuse_read(std::uint32_t m) noexcept {
        refuse(m);
        return ReadResult{ReadStatus::corrupt, 0, 0, 0};
    }
    // Computed, not looked up in a table: after the reader's exchange the
    // slot number is known only then, and a multiply is quicker than a load.
    std::byte* slot_at(std::uint32_t slot) const noexcept { return slots_ + slot * slot_stride_; }
    detail::Stamp& stamp(std::uint32_t slot) noexcept {
        return *reinterpret_cast<detail::Stamp*>(slot_at(slot) + stamp_offset_);
    }

    ipc::Segment seg_;             // empty for caller-supplied memory
    detail::Header* h_ = nullptr;
    // Kept from the header checked on attach: later writes to the shared
    // header cannot move a copy outside the buffer.
    std::byte* slots_ = nullptr;
    std::size_t slot_stride_ = 0;
    std::size_t item_size_ = 0;
    std::size_t stamp_offset_ = 0;
    std::uint64_t missed_total_ = 0;
    // The reader's: the seq of the item in its front slot, kept so that a read
    // touches only the slot it takes (unknown until this handle first reads).
    static constexpr std::uint64_t kUnknownSeq = ~std::uint64_t{0};
    std::uint64_t front_seq_ = kUnknownSeq;
    // The reader's slot and the writer's (kNoSlot until the role is taken),
    // and the seq of the writer's last item.
    std::uint32_t front_ = detail::kNoSlot;
    std::uint32_t back_ = detail::kNoSlot;
    std::uint64_t seq_ = 0;
    ipc::Fault fault_;
    std::string where_;            // the segment's name, for fault_message()
};

}  // namespace chimera::tbuf
