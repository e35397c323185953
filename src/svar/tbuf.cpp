// The triple buffer's set-up paths and its validator (the hot paths are
// inline in tbuf.hpp).
#include "chimera/tbuf.hpp"

#include <sched.h>

#include <algorithm>
#include <cstdio>
#include <utility>

namespace chimera::tbuf {

using detail::Header;
using detail::Stamp;

namespace {

constexpr ipc::SegmentKind kKind{ipc::ObjectType::tbuf, kLayoutVersion};

// A slot: the item (64-byte aligned), then its Stamp (16-byte aligned), so a
// small item and its stamps share one cache line.
std::size_t stamp_offset_for(std::size_t item_size) noexcept { return ipc::align_up(item_size, 16); }
std::size_t stride_for(std::size_t item_size) noexcept {
    return ipc::align_up(stamp_offset_for(item_size) + sizeof(Stamp), 64);
}

// A role's record as the kind of side that writes it: a slot number; the
// reader's may also carry its mark, the writer's a counter-stamp above bit 1.
constexpr bool record_valid(std::uint64_t r, bool writer) noexcept {
    return detail::record_slot(r) < 3 && (writer || (r & ~(detail::kSlotMask | detail::kExchanging)) == 0);
}

// Items larger than this are refused: keeps every size computation far from overflow.
constexpr std::uint64_t kMaxItemSize = std::uint64_t{1} << 32;

std::string memory_name(const void* memory) {
    char buf[48];
    std::snprintf(buf, sizeof buf, "<memory %p>", memory);
    return buf;
}

}  // namespace

std::size_t required_size(std::size_t item_size) noexcept {
    return sizeof(Header) + 3 * stride_for(item_size);
}

ipc::Fault validate(const void* image, std::size_t size) noexcept {
    if (ipc::Fault f = ipc::header_fault(image, size, kKind)) return f;
    if (size < sizeof(Header)) return {"size", -1, size, sizeof(Header), "at least"};
    const auto& h = *static_cast<const Header*>(image);
    using ipc::fault_if;
    if (ipc::Fault f = fault_if(h.item_size == 0 || h.item_size > kMaxItemSize, "item size",
                                h.item_size, kMaxItemSize, "1 to"))
        return f;
    if (ipc::Fault f = fault_if(h.slot_stride != stride_for(h.item_size), "slot stride", h.slot_stride,
                                stride_for(h.item_size), "equal to"))
        return f;
    if (ipc::Fault f = fault_if(h.stamp_offset != stamp_offset_for(h.item_size), "stamp offset",
                                h.stamp_offset, stamp_offset_for(h.item_size), "equal to"))
        return f;
    if (ipc::Fault f = fault_if(h.slots_offset != sizeof(Header), "slots offset", h.slots_offset,
                                sizeof(Header), "equal to"))
        return f;
    if (ipc::Fault f = fault_if(required_size(h.item_size) > size, "buffer size for the item size",
                                required_size(h.item_size), size))
        return f;
    // The records may name one slot twice after a kill (a side dead between
    // its exchange and its record): only their range is checked.
    const std::uint32_t m = h.middle.load(std::memory_order_relaxed);
    if (ipc::Fault f = fault_if(!detail::middle_valid(m, detail::kNoSlot),
                                "middle word (a slot number below 3, no stray bit)", m, 6))
        return f;
    const std::uint64_t w = h.writer.record.load(std::memory_order_relaxed);
    if (ipc::Fault f = fault_if(!record_valid(w, true), "writer's slot record", detail::record_slot(w), 2))
        return f;
    const std::uint64_t r = h.reader.record.load(std::memory_order_relaxed);
    return fault_if(!record_valid(r, false), "reader's slot record", r, 6);
}

Tbuf::Tbuf(Tbuf&& o) noexcept { *this = std::move(o); }

Tbuf& Tbuf::operator=(Tbuf&& o) noexcept {
    if (this != &o) {
        seg_ = std::move(o.seg_);
        h_ = std::exchange(o.h_, nullptr);
        slots_ = std::exchange(o.slots_, nullptr);
        slot_stride_ = std::exchange(o.slot_stride_, 0);
        item_size_ = std::exchange(o.item_size_, 0);
        stamp_offset_ = std::exchange(o.stamp_offset_, 0);
        missed_total_ = std::exchange(o.missed_total_, 0);
        front_seq_ = std::exchange(o.front_seq_, kUnknownSeq);
        front_ = std::exchange(o.front_, detail::kNoSlot);
        back_ = std::exchange(o.back_, detail::kNoSlot);
        seq_ = o.seq_;
        fault_ = std::exchange(o.fault_, ipc::Fault{});
        where_ = std::move(o.where_);
    }
    return *this;
}

Tbuf::Tbuf(ipc::Segment seg) : seg_(std::move(seg)) {
    where_ = seg_.name();
    bind(static_cast<std::byte*>(seg_.base()));
}

// Takes the geometry from a header already validated or just initialised.
void Tbuf::bind(std::byte* base) noexcept {
    h_ = reinterpret_cast<Header*>(base);
    item_size_ = h_->item_size;
    stamp_offset_ = h_->stamp_offset;
    slots_ = base + sizeof(Header);
    slot_stride_ = stride_for(item_size_);
}

std::uint64_t Tbuf::refuse(std::uint32_t m) noexcept {
    fault_ = ipc::Fault{"middle word (a slot number below 3, not the caller's own, no stray bit)", -1, m, 6};
    return kCorrupt;
}

namespace {

// How long a role take-over waits for the other side to finish its exchange
// (a few instructions; a live side preempted there is waited for this long).
constexpr std::int64_t kExchangeWaitNs = 100'000'000;

// Holds the header's role lock while a handle takes its role over.
class RoleLock {
public:
    explicit RoleLock(ipc::LockWord& lock) noexcept : lock_(lock), status_(ipc::lock(lock)) {}
    ~RoleLock() {
        if (held()) (void)ipc::unlock(lock_);
    }
    RoleLock(const RoleLock&) = delete;
    RoleLock& operator=(const RoleLock&) = delete;
    bool held() const noexcept { return ipc::holds(status_); }
    // Timed out (a holder stopped for 100 ms) or a corrupt lock word.
    ipc::Fault fault() const noexcept {
        return {"role lock status (not taken)", -1, static_cast<std::uint64_t>(status_),
                static_cast<std::uint64_t>(ipc::LockStatus::forced)};
    }

private:
    ipc::LockWord& lock_;
    ipc::LockStatus status_;
};

}  // namespace

bool Tbuf::exchanging(const detail::Role& other, std::uint64_t record) noexcept {
    if (&other == &h_->reader) return (record & detail::kExchanging) != 0;
    // The live writer may be stamping that slot (an atomic store) meanwhile.
    const std::uint64_t seq =
        std::atomic_ref<std::uint64_t>(stamp(detail::record_slot(record)).seq).load(std::memory_order_relaxed);
    return seq > detail::record_published(record);
}

bool Tbuf::third_of_middle_and(const detail::Role& other, std::uint32_t& slot, std::uint32_t& middle) noexcept {
    const bool writer = &other == &h_->writer;
    const std::int64_t deadline = ipc::now_ns() + kExchangeWaitNs;
    bool dead = false;  // the other side was found dead: what is read next no longer moves
    for (;;) {
        // Acquire: the stamps of items the other side published are visible.
        const std::uint32_t m = h_->middle.load(std::memory_order_acquire);
        if (!detail::middle_valid(m, detail::kNoSlot)) {
            refuse(m);
            return false;
        }
        middle = m & detail::kSlotMask;
        const std::uint64_t r = other.record.load(std::memory_order_acquire);
        const std::uint32_t theirs = detail::record_slot(r);
        if (!record_valid(r, writer)) {
            fault_ = ipc::Fault{writer ? "writer's slot record" : "reader's slot record", -1, r, 2};
            return false;
        }
        if (!exchanging(other, r) && theirs != middle) {
            slot = detail::third_slot(middle, theirs);
            return true;
        }
        // Inside an exchange, or its record names the middle slot (read
        // across an exchange). Read after its death, it stays so: every slot
        // holds a complete item and nobody holds one.
        if (dead) {
            slot = detail::kNoSlot;
            return true;
        }
        // Wait while it lives. Found dead, read again: what was read before
        // may be from before its last exchanges.
        const std::uint64_t owner = other.owner.load(std::memory_order_acquire);
        if (owner == 0 || owner == ipc::self_owner_id() || !ipc::owner_alive(owner)) {
            dead = true;
            continue;
        }
        if (ipc::now_ns() > deadline) {
            fault_ = ipc::Fault{"other side's slot record (its holder stopped inside an exchange for 100 ms)", -1,
                                theirs, middle, "unmarked and different from the middle slot"};
            return false;
        }
        sched_yield();
    }
}

bool Tbuf::find_writer_slot(std::uint32_t& slot) noexcept {
    const std::uint64_t r = h_->writer.record.load(std::memory_order_acquire);
    const std::uint32_t recorded = detail::record_slot(r);
    const std::uint32_t m = h_->middle.load(std::memory_order_acquire);
    if (!detail::middle_valid(m, detail::kNoSlot)) {
        refuse(m);
        return false;
    }
    if (!record_valid(r, true)) {
        fault_ = ipc::Fault{"writer's slot record", -1, recorded, 2};
        return false;
    }
    // No stamp newer than the last item published in the recorded slot: the
    // record is exact (the item there may be half-written: it stays ours).
    if (!exchanging(h_->writer, r)) {
        if (recorded == (m & detail::kSlotMask)) {
            fault_ = ipc::Fault{"writer's slot record", -1, recorded, m & detail::kSlotMask,
                                "a slot other than the middle one, not"};
            return false;
        }
        slot = recorded;
        return true;
    }
    // The last writer died inside its publish: every item is complete.
    std::uint32_t middle = 0;
    if (!third_of_middle_and(h_->reader, slot, middle)) return false;
    if (slot == detail::kNoSlot) slot = middle == 0 ? 1u : 0u;  // the reader died inside its exchange too
    return true;
}

bool Tbuf::find_reader_slot(std::uint32_t& slot) noexcept {
    std::uint32_t middle = 0;
    if (!third_of_middle_and(h_->writer, slot, middle)) return false;
    if (slot == detail::kNoSlot) slot = middle == 2 ? 1u : 2u;  // see find_writer_slot()
    return true;
}

bool Tbuf::become_writer() noexcept {
    if (!h_) return false;
    const RoleLock lock(h_->roles);
    if (!lock.held()) {
        fault_ = lock.fault();
        return false;
    }
    std::uint32_t back = detail::kNoSlot;
    if (!find_writer_slot(back)) return false;
    // The newest item's counter-stamp goes on from there. It may be in any
    // slot, ours too when it was a dead reader's; one that a dead writer
    // stamped but never published (killed between the two) cannot be told
    // from it, so its counter is then skipped: the reader counts it missed.
    // One at 2^63 or more was not written by counting (that takes
    // centuries); going on from it would wrap into kCorrupt and 0 ("never
    // held an item"), so a published item would look refused and the reader
    // would see none.
    const std::uint64_t seq = std::max({stamp(0).seq, stamp(1).seq, stamp(2).seq});
    if (seq >= detail::kMaxSeq) {
        fault_ = ipc::Fault{"counter-stamp of the newest item", -1, seq, detail::kMaxSeq - 1};
        return false;
    }
    // The slot is ours now: a stamp a dead writer left in it must not make
    // our record look inexact to our own successor.
    stamp(back).seq = 0;
    h_->writer.owner.store(ipc::self_owner_id(), std::memory_order_relaxed);
    h_->writer.record.store(detail::make_record(back, seq), std::memory_order_release);
    back_ = back;
    seq_ = seq;
    return true;
}

bool Tbuf::become_reader() noexcept {
    if (!h_) return false;
    const RoleLock lock(h_->roles);
    if (!lock.held()) {
        fault_ = lock.fault();
        return false;
    }
    std::uint32_t front = detail::kNoSlot;
    if (!find_reader_slot(front)) return false;
    h_->reader.owner.store(ipc::self_owner_id(), std::memory_order_relaxed);
    h_->reader.record.store(front, std::memory_order_release);
    front_ = front;
    front_seq_ = kUnknownSeq;
    return true;
}

std::uint64_t Tbuf::lost_writer_slot() noexcept {
    const std::uint32_t recorded = detail::record_slot(h_->writer.record.load(std::memory_order_relaxed));
    fault_ = ipc::Fault{"writer's slot record (another writer has published since this handle wrote)", -1,
                        recorded, back_, "equal to"};
    back_ = detail::kNoSlot;  // the next write takes the role over again
    return kCorrupt;
}

std::uint64_t Tbuf::refuse_published(std::uint32_t got) noexcept {
    std::uint32_t ours = back_ | detail::kFresh;
    // Put back: nothing moved, the slot is still ours (and our record too).
    if (!h_->middle.compare_exchange_strong(ours, got, std::memory_order_acq_rel, std::memory_order_relaxed))
        back_ = detail::kNoSlot;
    return refuse(got);
}

ReadResult Tbuf::refuse_taken(std::uint32_t got) noexcept {
    std::uint32_t ours = front_;
    if (h_->middle.compare_exchange_strong(ours, got, std::memory_order_acq_rel, std::memory_order_relaxed))
        h_->reader.record.store(front_, std::memory_order_relaxed);  // put back: still ours
    else
        front_ = detail::kNoSlot;
    return refuse_read(got);
}

std::string Tbuf::fault_message() const { return ipc::describe(where_, fault_); }

Header& Tbuf::init(void* memory, std::size_t size, std::size_t item_size) {
    auto* base = static_cast<std::byte*>(memory);
    auto& h = *reinterpret_cast<Header*>(base);
    // Everything but the segment header (its owner fills it); every stamp 0: empty.
    std::memset(base + sizeof(ipc::SegmentHeader), 0, size - sizeof(ipc::SegmentHeader));
    h.item_size = item_size;
    h.slot_stride = stride_for(item_size);
    h.slots_offset = sizeof(Header);
    h.stamp_offset = stamp_offset_for(item_size);
    // Writer owns slot 0, the reader slot 2, slot 1 is in the middle (the
    // owners and the role lock are zero: nobody).
    h.writer.record.store(detail::make_record(0, 0), std::memory_order_relaxed);
    h.middle.store(1, std::memory_order_relaxed);
    h.reader.record.store(2, std::memory_order_relaxed);
    return h;
}

void Tbuf::check(const std::string& where, const void* memory, std::size_t size) {
    if (const ipc::Fault f = validate(memory, size))
        throw ipc::SegmentError(where, "corrupt triple buffer: " + ipc::describe(where, f));
}

Tbuf Tbuf::create(const std::string& name, std::size_t item_size,
                  const ipc::CreateOptions& options) {
    if (item_size == 0 || item_size > kMaxItemSize)
        throw ipc::SegmentError(name, "a triple buffer needs an item size of 1 to " +
                                          std::to_string(kMaxItemSize) + " bytes");
    const std::size_t size = required_size(item_size);
    ipc::Segment seg = ipc::Segment::create(name, size, kKind, options);
    init(seg.base(), size, item_size);
    seg.publish();
    return Tbuf(std::move(seg));
}

Tbuf Tbuf::attach(const std::string& name, const ipc::AttachOptions& options) {
    ipc::Segment seg = ipc::Segment::attach(name, kKind, options);
    check(name, seg.base(), seg.size());
    return Tbuf(std::move(seg));
}

Tbuf Tbuf::create_in(void* memory, std::size_t size, std::size_t item_size) {
    const std::string where = memory_name(memory);
    if (reinterpret_cast<std::uintptr_t>(memory) % 64 != 0)
        throw ipc::SegmentError(where, "a triple buffer needs 64-byte aligned memory");
    if (item_size == 0 || item_size > kMaxItemSize)
        throw ipc::SegmentError(where, "a triple buffer needs an item size of 1 to " +
                                           std::to_string(kMaxItemSize) + " bytes");
    if (size < required_size(item_size))
        throw ipc::SegmentError(where, std::to_string(size) + " bytes, a triple buffer of " +
                                           std::to_string(item_size) + "-byte items needs " +
                                           std::to_string(required_size(item_size)));
    auto* hdr = static_cast<ipc::SegmentHeader*>(memory);
    // The header says the buffer's own size: attach_in() checks it against the block's.
    ipc::init_header(*hdr, kKind, required_size(item_size));
    init(memory, required_size(item_size), item_size);
    hdr->state.store(static_cast<std::uint32_t>(ipc::SegmentState::ready), std::memory_order_release);
    Tbuf t;
    t.where_ = where;
    t.bind(static_cast<std::byte*>(memory));
    return t;
}

Tbuf Tbuf::attach_in(void* memory, std::size_t size) {
    const std::string where = memory_name(memory);
    if (reinterpret_cast<std::uintptr_t>(memory) % 64 != 0)
        throw ipc::SegmentError(where, "a triple buffer needs 64-byte aligned memory");
    const auto& hdr = *static_cast<const ipc::SegmentHeader*>(memory);
    if (size < sizeof(ipc::SegmentHeader))
        throw ipc::SegmentError(where, "too small for a triple buffer");
    if (hdr.state.load(std::memory_order_acquire) != static_cast<std::uint32_t>(ipc::SegmentState::ready))
        throw ipc::SegmentError(where, "no triple buffer has been created here");
    // The buffer may be smaller than the block it was laid out in.
    const std::size_t used = hdr.total_size <= size ? static_cast<std::size_t>(hdr.total_size) : size;
    ipc::validate_header(where, hdr, kKind, used);
    check(where, memory, used);
    Tbuf t;
    t.where_ = where;
    t.bind(static_cast<std::byte*>(memory));
    return t;
}

void Tbuf::detach() noexcept {
    seg_.detach();
    h_ = nullptr;
    back_ = front_ = detail::kNoSlot;
    slots_ = nullptr;
}

bool Tbuf::destroy() noexcept {
    const bool removed = seg_.valid() && seg_.detach_destroy_if_last();
    h_ = nullptr;
    back_ = front_ = detail::kNoSlot;
    slots_ = nullptr;
    return removed;
}

}  // namespace chimera::tbuf
