// MEM: a block of shared memory standing for a memory-mapped board (§7.2).
// The block is an ipc::Segment (header + SIZE bytes) named by PATH: the first
// instance anywhere creates it, the others attach, the last one out removes
// it. read/write copy bytes at the offset set with Control::MEM_SEEK; mmap()
// gives the block itself for code that wants to work in place.
#include "driver.hpp"

#include "chimera/ipc/segment.hpp"

#include <cerrno>
#include <cstring>

namespace chimera::iod::detail {

namespace {

// Not in ipc::ObjectType's registry (owned by the ipc service); a value well
// clear of the registered ones until it is added there.
constexpr auto kMemObjectType = static_cast<ipc::ObjectType>(0x10D0);
constexpr std::uint32_t kMemLayoutVersion = 1;
constexpr std::size_t kBody = ipc::align_up(sizeof(ipc::SegmentHeader), 64);

class MemDevice final : public Device {
public:
    MemDevice(const DeviceSpec& spec, int start, int end, unsigned flags)
        : Device(spec, start, end, flags) {
        const std::string who = describe(spec);
        const std::string why = check_flags(flags);
        if (!why.empty()) throw Error(who + ": " + why);
        const ipc::SegmentKind kind{kMemObjectType, kMemLayoutVersion};
        const std::string name = spec.path.front() == '/' ? spec.path : "/" + spec.path;
        try {
            try {
                seg_ = ipc::Segment::create(name, kBody + spec.size, kind);
                seg_.publish();
            } catch (const ipc::SegmentError& e) {
                if (e.error_number() != EEXIST) throw;
                seg_ = ipc::Segment::attach(name, kind);
            }
        } catch (const ipc::SegmentError& e) {
            throw Error(who + ": " + e.what());
        }
        if (seg_.size() < kBody + spec.size)
            throw Error(who + ": segment " + name + " holds " + std::to_string(seg_.size() - kBody) +
                        " bytes, the database says SIZE " + std::to_string(spec.size));
        body_ = seg_.at_bytes<unsigned char>(kBody);
    }
    ~MemDevice() override { seg_.detach_destroy_if_last(); }

    long read(void* buf, std::size_t count) noexcept override {
        if (!(flags() & READ)) return -EBADF;
        const std::size_t n = clip(count);
        if ((flags() & kWaitMask) == WAITNOALL && n < count) return 0;
        std::memcpy(buf, body_ + offset_, n);
        return static_cast<long>(n);
    }
    long write(const void* buf, std::size_t count) noexcept override {
        if (!(flags() & WRITE)) return -EBADF;
        const std::size_t n = clip(count);
        if ((flags() & kWaitMask) == WAITNOALL && n < count) return 0;
        std::memcpy(body_ + offset_, buf, n);
        return static_cast<long>(n);
    }
    void* mmap() noexcept override { return body_; }

protected:
    std::string check_flags(unsigned flags) const override {
        std::string why = Device::check_flags(flags);
        if (!why.empty()) return why;
        if ((flags & kSizeMask) != BYTE) return "a memory block transfers bytes: BYTE elements only";
        return {};
    }
    long class_status(Status cmd, long, void*) noexcept override {
        if (cmd == Status::MEM_SIZE) return static_cast<long>(spec().size);
        return -ENOTSUP;
    }
    long class_control(Control cmd, long arg) noexcept override {
        if (cmd != Control::MEM_SEEK) return -ENOTSUP;
        if (arg < 0 || static_cast<std::size_t>(arg) > spec().size) return -EINVAL;
        offset_ = static_cast<std::size_t>(arg);
        return 0;
    }

private:
    std::size_t clip(std::size_t count) const noexcept {
        return std::min(count, spec().size - offset_);
    }

    ipc::Segment seg_;
    unsigned char* body_ = nullptr;
    std::size_t offset_ = 0;
};

}  // namespace

std::unique_ptr<Device> make_mem(const DeviceSpec& spec, int start, int end, unsigned flags) {
    return std::make_unique<MemDevice>(spec, start, end, flags);
}

}  // namespace chimera::iod::detail
