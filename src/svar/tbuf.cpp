// The triple buffer's set-up paths (the hot paths are inline in tbuf.hpp).
#include "chimera/tbuf.hpp"

#include <cstdio>
#include <utility>

namespace chimera::tbuf {

using detail::Header;
using detail::SlotHeader;

namespace {

constexpr ipc::SegmentKind kKind{ipc::ObjectType::tbuf, kLayoutVersion};

std::size_t stride_for(std::size_t item_size) noexcept {
    return ipc::align_up(sizeof(SlotHeader) + item_size, 64);
}

std::string memory_name(const void* memory) {
    char buf[48];
    std::snprintf(buf, sizeof buf, "<memory %p>", memory);
    return buf;
}

}  // namespace

std::size_t required_size(std::size_t item_size) noexcept {
    return sizeof(Header) + 3 * stride_for(item_size);
}

Tbuf::Tbuf(Tbuf&& o) noexcept
    : seg_(std::move(o.seg_)), base_(std::exchange(o.base_, nullptr)), h_(std::exchange(o.h_, nullptr)) {}

Tbuf& Tbuf::operator=(Tbuf&& o) noexcept {
    if (this != &o) {
        seg_ = std::move(o.seg_);
        base_ = std::exchange(o.base_, nullptr);
        h_ = std::exchange(o.h_, nullptr);
    }
    return *this;
}

Tbuf::Tbuf(ipc::Segment seg)
    : seg_(std::move(seg)), base_(static_cast<std::byte*>(seg_.base())), h_(seg_.at_bytes<Header>(0)) {}

Header& Tbuf::init(void* memory, std::size_t size, std::size_t item_size) {
    auto* base = static_cast<std::byte*>(memory);
    auto& h = *reinterpret_cast<Header*>(base);
    // Everything but the segment header (its owner fills it).
    std::memset(base + sizeof(ipc::SegmentHeader), 0, size - sizeof(ipc::SegmentHeader));
    h.item_size = item_size;
    h.slot_stride = stride_for(item_size);
    h.slots_offset = sizeof(Header);
    // Writer owns slot 0, the reader slot 2, slot 1 is in the middle.
    h.back = 0;
    h.front = 2;
    h.middle.store(1, std::memory_order_relaxed);
    h.next_counter = 0;  // "the counter-stamp begins at zero" (§5.6.1)
    return h;
}

void Tbuf::check(const std::string& where, void* memory, std::size_t size) {
    const auto& h = *static_cast<const Header*>(memory);
    if (size < sizeof(Header) || h.item_size == 0 ||
        h.slot_stride != stride_for(h.item_size) || h.slots_offset != sizeof(Header) ||
        required_size(h.item_size) > size || h.back > 2 || h.front > 2)
        throw ipc::SegmentError(where, "corrupt triple-buffer header");
}

Tbuf Tbuf::create(const std::string& name, std::size_t item_size,
                  const ipc::CreateOptions& options) {
    if (item_size == 0) throw ipc::SegmentError(name, "a triple buffer needs an item size above 0");
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
    if (item_size == 0) throw ipc::SegmentError(where, "a triple buffer needs an item size above 0");
    if (size < required_size(item_size))
        throw ipc::SegmentError(where, std::to_string(size) + " bytes, a triple buffer of " +
                                           std::to_string(item_size) + "-byte items needs " +
                                           std::to_string(required_size(item_size)));
    auto* hdr = static_cast<ipc::SegmentHeader*>(memory);
    ipc::init_header(*hdr, kKind, size);
    init(memory, size, item_size);
    hdr->state.store(static_cast<std::uint32_t>(ipc::SegmentState::ready), std::memory_order_release);
    Tbuf t;
    t.base_ = static_cast<std::byte*>(memory);
    t.h_ = static_cast<Header*>(memory);
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
    ipc::validate_header(where, hdr, kKind, static_cast<std::size_t>(hdr.total_size) <= size
                                               ? static_cast<std::size_t>(hdr.total_size)
                                               : size);
    check(where, memory, size);
    Tbuf t;
    t.base_ = static_cast<std::byte*>(memory);
    t.h_ = static_cast<Header*>(memory);
    return t;
}

void Tbuf::detach() noexcept {
    seg_.detach();
    base_ = nullptr;
    h_ = nullptr;
}

bool Tbuf::destroy() noexcept {
    const bool removed = seg_.valid() && seg_.detach_destroy_if_last();
    base_ = nullptr;
    h_ = nullptr;
    return removed;
}

}  // namespace chimera::tbuf
