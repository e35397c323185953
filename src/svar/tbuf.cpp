// The triple buffer's set-up paths and its validator (the hot paths are
// inline in tbuf.hpp).
#include "chimera/tbuf.hpp"

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
    const std::uint32_t s = h.state.load(std::memory_order_relaxed);
    return fault_if(!detail::state_valid(s), "state word (three distinct slots)", s, 0x7f);
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
        take_guess_ = o.take_guess_;
        back_ = std::exchange(o.back_, 3);
        guess_ = o.guess_;
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

std::uint64_t Tbuf::refuse(std::uint32_t s) noexcept {
    fault_ = ipc::Fault{"state word (three distinct slots)", -1, s, 0x7f};
    return kCorrupt;
}

bool Tbuf::become_writer() noexcept {
    if (!h_) return false;
    // Acquire: the stamps of an item another process published are visible.
    const std::uint32_t s = h_->state.load(std::memory_order_acquire);
    if (!detail::state_valid(s)) {
        refuse(s);
        return false;
    }
    // The newest item's counter-stamp goes on from there. One at 2^63 or more
    // was not written by counting (that takes centuries); going on from it
    // would wrap into kCorrupt and 0 ("never held an item"), so a published
    // item would look refused and the reader would see none.
    const std::uint64_t seq = stamp((s & detail::kFresh) ? detail::middle_of(s) : detail::front_of(s)).seq;
    if (seq >= detail::kMaxSeq) {
        fault_ = ipc::Fault{"counter-stamp of the newest item", -1, seq, detail::kMaxSeq - 1};
        return false;
    }
    back_ = detail::back_of(s);
    seq_ = seq;
    guess_ = s;
    return true;
}

std::uint64_t Tbuf::lost_writer_slot(std::uint32_t s) noexcept {
    if (!detail::state_valid(s)) return refuse(s);
    fault_ = ipc::Fault{"back slot (another writer has published since this handle wrote)", -1,
                        detail::back_of(s), back_, "equal to"};
    back_ = 3;  // the next write starts from the state word again
    return kCorrupt;
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
    // Writer owns slot 0, the reader slot 2, slot 1 is in the middle.
    h.state.store(detail::make_state(0, 1, 2, false), std::memory_order_relaxed);
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
    back_ = 3;
    slots_ = nullptr;
}

bool Tbuf::destroy() noexcept {
    const bool removed = seg_.valid() && seg_.detach_destroy_if_last();
    h_ = nullptr;
    back_ = 3;
    slots_ = nullptr;
    return removed;
}

}  // namespace chimera::tbuf
