// Global shared memory segments by logical name (thesis §5.4.1).
#include "chimera/shm.hpp"

#include <algorithm>
#include <cstring>
#include <utility>

#include "detail.hpp"

namespace chimera::shm {

using layout::ShmHeader;

namespace {
constexpr ipc::SegmentKind kShmKind{ipc::ObjectType::xmail_shm, layout::kShmVersion};
constexpr std::uint64_t kMaxSize = std::uint64_t{1} << 40;
}  // namespace

ipc::Segment create_segment_body(const std::string& segment, const std::string& full_name,
                                 const xm::ObjectParams& params) {
    if (params.a == 0 || params.a > kMaxSize)
        throw xm::Error("shared segment '" + full_name + "': size " + std::to_string(params.a) +
                        " bytes (must be 1.." + std::to_string(kMaxSize) + ")");
    const std::uint64_t data_offset = sizeof(ShmHeader);
    ipc::Segment seg = ipc::Segment::create(segment, data_offset + params.a, kShmKind);
    auto* h = static_cast<ShmHeader*>(seg.base());
    std::memcpy(h->name, full_name.data(), std::min(full_name.size(), sizeof h->name - 1));
    h->size = params.a;
    h->data_offset = data_offset;
    seg.publish();
    return seg;
}

ipc::Fault validate(const void* image, std::size_t size) noexcept {
    if (ipc::Fault f = ipc::header_fault(image, size, kShmKind)) return f;
    if (size < sizeof(ShmHeader)) return {"size", -1, size, sizeof(ShmHeader), "at least"};
    const auto& h = *static_cast<const ShmHeader*>(image);
    using ipc::fault_if;
    if (ipc::Fault f = fault_if(h.data_offset < sizeof(ShmHeader) || h.data_offset > size, "data offset",
                                h.data_offset, sizeof(ShmHeader), "at least"))
        return f;
    if (ipc::Fault f = fault_if(h.size == 0 || h.size > size - h.data_offset, "usable size", h.size,
                                size - h.data_offset, "1 to"))
        return f;
    return fault_if(strnlen(h.name, sizeof h.name) == sizeof h.name, "name length", sizeof h.name,
                    sizeof h.name - 1);
}

Segment Segment::map(std::string_view full_name, const std::string& segment) {
    Segment s;
    try {
        s.segment_ = ipc::Segment::attach(segment, kShmKind);
    } catch (const ipc::SegmentError& e) {
        throw xm::Error("shared segment '" + std::string(full_name) + "': " + e.what());
    }
    // The usable area is checked once and kept: later writes to the header move nothing.
    if (const ipc::Fault f = validate(s.segment_.base(), s.segment_.size()))
        throw xm::Error("shared segment '" + std::string(full_name) + "': corrupt: " + ipc::describe(segment, f));
    auto* h = static_cast<ShmHeader*>(s.segment_.base());
    s.data_ = s.segment_.at_bytes<void>(h->data_offset);
    s.size_ = h->size;
    s.name_ = std::string(full_name);
    return s;
}

Segment Segment::create(xm::Rtpu& self, std::string_view full_name, std::size_t size) {
    if (size == 0 || size > kMaxSize)
        throw xm::Error("shared segment '" + std::string(full_name) + "': size " +
                        std::to_string(size) + " bytes (must be 1.." + std::to_string(kMaxSize) + ")");
    xm::ObjectParams op;
    op.a = size;
    const xm::ObjectRef ref = self.create_object(full_name, ipc::ObjectType::xmail_shm, op);
    return map(full_name, ref.segment);
}

Segment Segment::attach(xm::Rtpu& self, std::string_view full_name) {
    const xm::ObjectRef ref = self.attach_object(full_name, ipc::ObjectType::xmail_shm);
    return map(full_name, ref.segment);
}

Segment::Segment(Segment&& o) noexcept
    : segment_(std::move(o.segment_)),
      data_(std::exchange(o.data_, nullptr)),
      size_(std::exchange(o.size_, 0)),
      name_(std::move(o.name_)) {}

Segment& Segment::operator=(Segment&& o) noexcept {
    if (this != &o) {
        detach();
        segment_ = std::move(o.segment_);
        data_ = std::exchange(o.data_, nullptr);
        size_ = std::exchange(o.size_, 0);
        name_ = std::move(o.name_);
    }
    return *this;
}

Segment::~Segment() { detach(); }

std::uint32_t Segment::users() const noexcept {
    return segment_.users();
}

bool Segment::detach() noexcept {
    data_ = nullptr;
    size_ = 0;
    return segment_.valid() && segment_.detach_destroy_if_last();
}

void Segment::destroy(xm::Rtpu& self) {
    // Name first: detaching first could free the object as its last user.
    self.destroy_object(name_);
    data_ = nullptr;
    size_ = 0;
    segment_.detach();
}

}  // namespace chimera::shm

namespace chimera::xm::detail {
ipc::Segment create_shm_segment(const std::string& segment, const std::string& full_name,
                                const ObjectParams& params) {
    return shm::create_segment_body(segment, full_name, params);
}
}  // namespace chimera::xm::detail
