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
// Which slot each side holds, and whether the middle one is unread, is ONE
// atomic word (the state), changed by one compare-and-swap per publish and per
// fresh read (as the Rust triple_buffer crate keeps its indices in one word).
// So a writer or reader killed at any instruction leaves a consistent buffer:
// before its swap nothing the other side sees has changed, after it the swap is
// complete; the next process to take the role goes on from the state word
// (issue #15.2: with the indices in two words, a writer killed between them
// left both sides sharing a slot for good). The counter-stamp of the next item
// is derived from the newest published item, not kept apart, so a writer that
// dies between stamping and publishing leaves no gap in the counters either.
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
// (the state word is an atomic of this machine; item contents are the
// application's business, as in the thesis).
//
// Untrusted memory (issue #15.3): the geometry (item size, slot places) is
// checked once on attach (validate()) and then kept in the handle, so nothing
// another process writes later can move a copy outside the buffer; the state
// word is checked on every operation (three distinct slot numbers), and a bad
// one is refused: write() returns kCorrupt, read() ReadStatus::corrupt, and
// fault_message() names the segment.
//
// Roles: one thread writes, one thread reads (each may be in any process, and
// a side may detach, or be killed, and another process take its role over).
// A handle that has written keeps the writer's slot number: hand the role
// over by detaching (or dying), never by writing through two live handles in
// turn; a handle that finds another one has published since refuses
// (kCorrupt, "another writer") instead of going on.
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
#include "chimera/ipc/segment.hpp"

namespace chimera::tbuf {

inline constexpr std::uint32_t kLayoutVersion = 2;

/// What a read found.
enum class ReadStatus : std::uint8_t {
    fresh,    ///< an item the reader had not seen
    reused,   ///< no new item since the last read: the same item again
    empty,    ///< nothing has been written yet
    corrupt,  ///< the shared state word is damaged: nothing read (see fault_message())
};

struct [[nodiscard]] ReadResult {
    ReadStatus status = ReadStatus::empty;
    std::uint64_t counter = 0;  ///< counter-stamp of the item
    std::int64_t time_ns = 0;   ///< time-stamp of the item
    std::uint64_t missed = 0;   ///< items written but never read since the last fresh read
};

/// What write() and publish() return when the shared state word is damaged.
inline constexpr std::uint64_t kCorrupt = ~std::uint64_t{0};

namespace detail {

// The state word: bits 0-1 the writer's (back) slot, 2-3 the middle slot,
// 4-5 the reader's (front) slot, bit 6 set while the middle slot is unread.
inline constexpr std::uint32_t kFresh = 1u << 6;
constexpr std::uint32_t back_of(std::uint32_t s) noexcept { return s & 3u; }
constexpr std::uint32_t middle_of(std::uint32_t s) noexcept { return (s >> 2) & 3u; }
constexpr std::uint32_t front_of(std::uint32_t s) noexcept { return (s >> 4) & 3u; }
constexpr std::uint32_t make_state(std::uint32_t back, std::uint32_t middle, std::uint32_t front,
                                   bool fresh) noexcept {
    return back | middle << 2 | front << 4 | (fresh ? kFresh : 0u);
}
/// Bit n set when n (fresh bit clear) names three distinct slots.
inline constexpr std::uint64_t kPermutations = [] {
    std::uint64_t bits = 0;
    for (std::uint32_t n = 0; n < 64; ++n)
        if (back_of(n) < 3 && middle_of(n) < 3 && front_of(n) < 3 &&
            ((1u << back_of(n)) | (1u << middle_of(n)) | (1u << front_of(n))) == 7u)
            bits |= std::uint64_t{1} << n;
    return bits;
}();
/// Three distinct slots and no stray bit (a shift and a test: every operation checks it).
constexpr bool state_valid(std::uint32_t s) noexcept {
    return (s & ~kFresh) < 64 && ((kPermutations >> (s & 63u)) & 1u) != 0;
}
static_assert(state_valid(make_state(0, 1, 2, false)) && state_valid(make_state(2, 0, 1, true)));
static_assert(!state_valid(make_state(0, 0, 2, false)) && !state_valid(make_state(3, 1, 2, true)));
static_assert(!state_valid(make_state(0, 1, 2, true) | 1u << 7));
/// After a publish: back and middle swapped, the middle unread.
constexpr std::uint32_t published(std::uint32_t s) noexcept {
    return make_state(middle_of(s), back_of(s), front_of(s), true);
}
/// After a fresh read: front and middle swapped, nothing unread.
constexpr std::uint32_t taken(std::uint32_t s) noexcept {
    return make_state(back_of(s), front_of(s), middle_of(s), false);
}

/// After each slot's item: its stamps.
struct Stamp {
    std::int64_t time_ns;
    std::uint64_t seq;  // counter-stamp + 1; 0 while the slot never held an item
};
static_assert(sizeof(Stamp) == 16);
/// Stamps from 2^63 on cannot come from counting: a writer refuses to go on from one.
inline constexpr std::uint64_t kMaxSeq = std::uint64_t{1} << 63;

struct alignas(64) Header {
    ipc::SegmentHeader segment;  // offset 0: magic, version, byte order
    // offset 64: fixed at creation
    std::uint64_t item_size;
    std::uint64_t slot_stride;   // item + Stamp, rounded to 64
    std::uint64_t slots_offset;  // from the start of the block
    std::uint64_t stamp_offset;  // of a slot's Stamp, from the slot's start
    std::uint8_t reserved0[32];
    // offset 128: the only word both sides write
    std::atomic<std::uint32_t> state;
    std::uint8_t reserved1[60];
};
static_assert(sizeof(Header) == 192);
static_assert(offsetof(Header, state) == 128);
static_assert(std::atomic<std::uint32_t>::is_always_lock_free);

}  // namespace detail

/// Bytes of memory a buffer for items of `item_size` bytes needs.
CHIMERA_API std::size_t required_size(std::size_t item_size) noexcept;

/// Checks a buffer's image of `size` bytes (header, geometry, state word) as
/// attach() does, without throwing: the first bound broken, or none. A pure
/// function over the bytes, for tests and fuzzers.
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
    /// makes it the newest. Returns its counter
    /// (kCorrupt, nothing published, when the state word is damaged or the
    /// newest item's counter-stamp is one no writer could have made, >= kMaxSeq).
    [[nodiscard]] std::uint64_t write(const void* item) noexcept {
        if (back_ > 2 && !become_writer()) [[unlikely]]
            return kCorrupt;
        ipc::copy_var(slot_at(back_), static_cast<const std::byte*>(item), item_size_);
        // What the swap needs is taken before the clock read (a call, after
        // which the handle's fields would be loaded again on the way to the
        // swap).
        detail::Stamp& st = stamp(back_);
        const std::uint32_t expected = guess_;
        return swap_in(st, expected, ipc::now_ns());
    }
    /// As write(), with a caller-supplied time-stamp (saves reading the clock).
    /// Always inlined, as read() is: the call cost 0.5-0.7 ns of a 24-byte
    /// write+read's 27 (bench/results/svar.md).
    [[nodiscard, gnu::always_inline]] std::uint64_t write(const void* item, std::int64_t time_ns) noexcept {
        if (back_ > 2 && !become_writer()) [[unlikely]]
            return kCorrupt;
        ipc::copy_var(slot_at(back_), static_cast<const std::byte*>(item), item_size_);
        return publish_back(time_ns);
    }
    /// Zero-copy writing: the writer's private slot, to fill in place
    /// (nullptr when the state word is damaged)...
    [[nodiscard]] void* write_slot() noexcept {
        if (back_ > 2 && !become_writer()) [[unlikely]]
            return nullptr;
        return slot_at(back_);
    }
    /// The counter-stamp the next publish of this handle will carry (the
    /// newest item's + 1, also when a killed writer's successor goes on);
    /// kCorrupt when the state word is damaged.
    [[nodiscard]] std::uint64_t next_counter() noexcept {
        if (back_ > 2 && !become_writer()) [[unlikely]]
            return kCorrupt;
        return seq_;
    }
    /// ...then publish it (stamps, one compare-and-swap). Returns its counter.
    [[nodiscard]] std::uint64_t publish(std::int64_t time_ns) noexcept {
        if (back_ > 2 && !become_writer()) [[unlikely]]
            return kCorrupt;
        return publish_back(time_ns);
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
        return (h_->state.load(std::memory_order_relaxed) & detail::kFresh) != 0;
    }
    /// Zero-copy reading: the newest item in place, valid until the next read
    /// (nullptr when the state word is damaged).
    [[gnu::always_inline]] const void* read_view(ReadResult& r) noexcept {
        const void* p = nullptr;
        r = take(p);
        return p;
    }

private:
    // The reader's step: takes the middle slot if it holds a new item, and
    // points `item` at the front slot (left alone when corrupt). The result is
    // made at the end, not filled in before the swap: stores pending at a
    // locked instruction make it wait.
    [[gnu::always_inline]] ReadResult take(const void*& item) noexcept {
        std::uint32_t s = h_->state.load(std::memory_order_relaxed);
        // Predicted: the writer has published once since this handle's last
        // take, so the word is take_guess_ (valid and fresh by construction).
        // The swap's operands then come from the handle, not from the load:
        // the predicted branch keeps the load off the swap's critical path.
        std::uint32_t expected = take_guess_;
        if (s != expected) [[unlikely]] {
            if (!detail::state_valid(s))
                return refuse_read(s);
            if (!(s & detail::kFresh))
                return view(detail::front_of(s), ReadStatus::reused, item);
            expected = s;
        }
        // Before the swap: the old front slot is the writer's after it.
        const std::uint64_t had = front_seq_ != kUnknownSeq ? front_seq_ : stamp(detail::front_of(expected)).seq;
        // Release: we are done with our old slot before the writer gets it;
        // acquire: the item we take is complete. A failure means the writer
        // published again meanwhile: take that one.
        while (!h_->state.compare_exchange_weak(expected, detail::taken(expected), std::memory_order_acq_rel,
                                                std::memory_order_relaxed)) {
            if (!detail::state_valid(expected)) [[unlikely]]
                return refuse_read(expected);
        }
        take_guess_ = detail::published(detail::taken(expected));
        ReadResult r = view(detail::middle_of(expected), ReadStatus::fresh, item);
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

    explicit Tbuf(ipc::Segment seg);
    static detail::Header& init(void* memory, std::size_t size, std::size_t item_size);
    static void check(const std::string& where, const void* memory, std::size_t size);
    void bind(std::byte* base) noexcept;

    // The writer's view of the state word, taken when a handle first writes
    // and then kept from its own compare-and-swaps: only the writer moves the
    // back slot, and the newest item is the one it published last. So a
    // publish reads nothing shared before its swap (as the crate's writer).
    // False (fault recorded) when the state word is damaged.
    bool become_writer() noexcept;

    // Stamps the back slot with the next counter and swaps it into the middle.
    std::uint64_t publish_back(std::int64_t time_ns) noexcept { return swap_in(stamp(back_), guess_, time_ns); }
    // publish_back() with the back slot's stamps `st` and the expected word
    // `s` (guess_) already at hand.
    [[gnu::always_inline]] std::uint64_t swap_in(detail::Stamp& st, std::uint32_t s, std::int64_t time_ns) noexcept {
        st.time_ns = time_ns;
        st.seq = seq_ + 1;
        // Release: the item and its stamps are complete before the reader can
        // take them; acquire: the reader is done with the slot we get back.
        // The expected word is a guess (the reader took our last item, or not,
        // as last time); a wrong guess costs a second try with the real word.
        while (!h_->state.compare_exchange_weak(s, detail::published(s), std::memory_order_acq_rel,
                                                std::memory_order_relaxed)) {
            if (!detail::state_valid(s) || detail::back_of(s) != back_) [[unlikely]]
                return lost_writer_slot(s);
        }
        const std::uint32_t now = detail::published(s);
        guess_ = (s & detail::kFresh) ? now : detail::taken(now);
        back_ = detail::back_of(now);
        return seq_++;
    }
    // The state word is damaged, or names another back slot than ours (a
    // second writer): the item went nowhere. Records the fault; kCorrupt.
    std::uint64_t lost_writer_slot(std::uint32_t s) noexcept;
    // Record a damaged state word; kCorrupt / a corrupt result.
    std::uint64_t refuse(std::uint32_t s) noexcept;
    ReadResult refuse_read(std::uint32_t s) noexcept {
        refuse(s);
        return ReadResult{ReadStatus::corrupt, 0, 0, 0};
    }
    // Computed, not looked up in a table: after the reader's swap the slot
    // number is known only then, and a multiply is quicker than a load.
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
    // The state word the reader expects to find: its last take, then one
    // publish (any valid fresh state to begin with).
    std::uint32_t take_guess_ = detail::make_state(0, 1, 2, true);
    // The writer's (see become_writer()): its slot (3: not known yet), the
    // seq of its last item, the expected state word.
    std::uint32_t back_ = 3;
    std::uint32_t guess_ = 0;
    std::uint64_t seq_ = 0;
    ipc::Fault fault_;
    std::string where_;            // the segment's name, for fault_message()
};

}  // namespace chimera::tbuf
