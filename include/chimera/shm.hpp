// chimera/shm.hpp — dynamically allocatable global shared memory (thesis §5.4.1).
//
// shmCreate asks the XM server of the RTPU named in "rtpu:name" to allocate a
// segment of the given size there; shmAttach resolves the name through that
// server. Both return a mapping whose data() the task uses as local memory;
// anything it stores inside that must be meaningful to other processes has to
// be an offset from data(), never a pointer (each process maps it elsewhere).
// shmDetach unmaps; the last user to detach frees the segment. shmDestroy
// removes the name at once (existing mappings stay valid until detached).
#pragma once

#include "chimera/export.hpp"

#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include "chimera/ipc/segment.hpp"
#include "chimera/xmail.hpp"

namespace chimera::shm {

namespace layout {

inline constexpr std::uint32_t kShmVersion = 1;

struct ShmHeader {
    ipc::SegmentHeader segment;
    char name[64];          ///< "rtpu:name"
    std::uint64_t size;     ///< usable bytes
    std::uint64_t data_offset;
    std::uint8_t reserved[48];
};
static_assert(sizeof(ShmHeader) == 192);

}  // namespace layout

/// Checks a shared segment's image of `size` bytes as attach() does (segment
/// header, the usable area inside the segment, the name ending in its field):
/// the first bound broken, or none. A pure function over the bytes.
CHIMERA_API ipc::Fault validate(const void* image, std::size_t size) noexcept;

/// One mapping of a shared segment. Move-only; destruction detaches.
class CHIMERA_API Segment {
public:
    Segment() = default;
    Segment(Segment&&) noexcept;
    Segment& operator=(Segment&&) noexcept;
    ~Segment();

    /// shmCreate: `size` usable bytes, zero-filled, on the named RTPU.
    static Segment create(xm::Rtpu& self, std::string_view full_name, std::size_t size);
    /// shmAttach.
    static Segment attach(xm::Rtpu& self, std::string_view full_name);

    void* data() const noexcept { return data_; }
    std::size_t size() const noexcept { return size_; }
    const std::string& name() const noexcept { return name_; }
    bool valid() const noexcept { return data_ != nullptr; }
    /// Processes currently attached (this one included).
    std::uint32_t users() const noexcept;

    /// shmDetach: the last user frees the segment. True when this freed it.
    bool detach() noexcept;
    /// shmDestroy: remove the name through the owner's XM server, then detach.
    void destroy(xm::Rtpu& self);

private:
    static Segment map(std::string_view full_name, const std::string& segment);
    ipc::Segment segment_;
    void* data_ = nullptr;
    std::size_t size_ = 0;
    std::string name_;
};

}  // namespace chimera::shm
