// POSIX shared-memory segments with the common header (segment.hpp).
#include "chimera/ipc/segment.hpp"

#include <fcntl.h>
#include <signal.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <climits>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <thread>
#include <utility>

#include "chimera/ipc/clock.hpp"

namespace chimera::ipc {
namespace {

std::string describe(const std::string& name, const std::string& message) {
    return "segment " + name + ": " + message;
}

[[noreturn]] void fail_errno(const std::string& name, const std::string& what, int err) {
    throw SegmentError(name, what + ": " + std::strerror(err), err);
}

void check_name(const std::string& name) {
    if (name.size() < 2 || name[0] != '/')
        throw SegmentError(name, "a segment name starts with '/' and is not empty");
    if (name.find('/', 1) != std::string::npos)
        throw SegmentError(name, "a segment name holds no '/' after the first");
    if (name.size() > NAME_MAX)
        throw SegmentError(name, "name longer than " + std::to_string(NAME_MAX) + " characters");
}

// Maps `fd` and applies the prefault/lock options; returns the address.
void* map_fd(const std::string& name, int fd, std::size_t size, bool prefault, bool lock,
             bool& locked) {
    int flags = MAP_SHARED;
    if (prefault) flags |= MAP_POPULATE;
    void* base = mmap(nullptr, size, PROT_READ | PROT_WRITE, flags, fd, 0);
    if (base == MAP_FAILED) fail_errno(name, "mmap", errno);
    locked = lock && mlock(base, size) == 0;
    return base;
}

}  // namespace

std::string object_type_name(ObjectType type) {
    switch (type) {
        case ObjectType::test: return "test";
        case ObjectType::svar_table: return "svar_table";
        case ObjectType::tbuf: return "tbuf";
        case ObjectType::xmail_mailbox: return "xmail_mailbox";
        case ObjectType::xmail_shm: return "xmail_shm";
        case ObjectType::xmail_sem: return "xmail_sem";
        case ObjectType::xmail_msg: return "xmail_msg";
        case ObjectType::prof_status: return "prof_status";
        case ObjectType::sbs_control: return "sbs_control";
        case ObjectType::name_server: return "name_server";
    }
    return "type " + std::to_string(static_cast<std::uint32_t>(type));
}

SegmentError::SegmentError(std::string name, std::string message, int error_number)
    : std::runtime_error(describe(name, message)), name_(std::move(name)), errno_(error_number) {}

std::string segment_name(std::string_view subsystem, std::string_view object) {
    std::string name = "/chimera.";
    name += subsystem;
    name += '.';
    name += object;
    if (subsystem.empty() || object.empty())
        throw SegmentError(name, "subsystem and object names must not be empty");
    if (subsystem.find('/') != std::string_view::npos || object.find('/') != std::string_view::npos)
        throw SegmentError(name, "subsystem and object names hold no '/'");
    check_name(name);
    return name;
}

void init_header(SegmentHeader& h, SegmentKind kind, std::size_t total_size) noexcept {
    h.magic = kSegmentMagic;
    h.layout_version = kind.layout_version;
    h.object_type = static_cast<std::uint32_t>(kind.type);
    h.byte_order = kByteOrderCode;
    h.total_size = total_size;
    h.attach_count.store(1, std::memory_order_relaxed);
    h.creator_pid = static_cast<std::int32_t>(getpid());
    h.state.store(static_cast<std::uint32_t>(SegmentState::building), std::memory_order_relaxed);
    h.header_size = sizeof(SegmentHeader);
    h.created_ns = static_cast<std::uint64_t>(now_ns());
    std::memset(h.reserved, 0, sizeof h.reserved);
}

void validate_header(const std::string& name, const SegmentHeader& h, SegmentKind kind,
                     std::size_t mapped_size) {
    if (mapped_size < sizeof(SegmentHeader))
        throw SegmentError(name, "size " + std::to_string(mapped_size) +
                                     " bytes is smaller than a segment header");
    if (h.magic == __builtin_bswap32(kSegmentMagic) && h.byte_order == __builtin_bswap32(kByteOrderCode))
        throw SegmentError(name, "byte-order code 0x04030201: created by a machine of the other "
                                 "byte order");
    if (h.magic != kSegmentMagic) {
        char buf[128];
        std::snprintf(buf, sizeof buf, "bad magic 0x%08x (expected 0x%08x): not a chimera segment",
                      h.magic, kSegmentMagic);
        throw SegmentError(name, buf);
    }
    if (h.byte_order != kByteOrderCode) {
        char buf[128];
        std::snprintf(buf, sizeof buf,
                      "byte-order code 0x%08x, this machine writes 0x%08x: created with the "
                      "other byte order",
                      h.byte_order, kByteOrderCode);
        throw SegmentError(name, buf);
    }
    if (h.object_type != static_cast<std::uint32_t>(kind.type))
        throw SegmentError(name, "holds a " + object_type_name(static_cast<ObjectType>(h.object_type)) +
                                     ", expected a " + object_type_name(kind.type));
    if (h.layout_version != kind.layout_version)
        throw SegmentError(name, "layout version " + std::to_string(h.layout_version) +
                                     ", this library expects " +
                                     std::to_string(kind.layout_version));
    if (h.header_size != sizeof(SegmentHeader))
        throw SegmentError(name, "header size " + std::to_string(h.header_size) +
                                     ", this library expects " +
                                     std::to_string(sizeof(SegmentHeader)));
    if (h.total_size != mapped_size)
        throw SegmentError(name, "header says " + std::to_string(h.total_size) +
                                     " bytes, the segment has " + std::to_string(mapped_size));
}

Segment::Segment(Segment&& o) noexcept
    : name_(std::move(o.name_)),
      base_(std::exchange(o.base_, nullptr)),
      size_(std::exchange(o.size_, 0)),
      locked_(std::exchange(o.locked_, false)),
      creator_(std::exchange(o.creator_, false)),
      published_(std::exchange(o.published_, false)) {}

Segment& Segment::operator=(Segment&& o) noexcept {
    if (this != &o) {
        detach();
        name_ = std::move(o.name_);
        base_ = std::exchange(o.base_, nullptr);
        size_ = std::exchange(o.size_, 0);
        locked_ = std::exchange(o.locked_, false);
        creator_ = std::exchange(o.creator_, false);
        published_ = std::exchange(o.published_, false);
    }
    return *this;
}

Segment::~Segment() { detach(); }

Segment Segment::create(const std::string& name, std::size_t size, SegmentKind kind,
                        const CreateOptions& options) {
    check_name(name);
    if (size < sizeof(SegmentHeader))
        throw SegmentError(name, "size " + std::to_string(size) + " is smaller than the header");
    const int fd = shm_open(name.c_str(), O_RDWR | O_CREAT | O_EXCL, options.mode);
    if (fd < 0) {
        if (errno == EEXIST) throw SegmentError(name, "already exists", EEXIST);
        fail_errno(name, "shm_open", errno);
    }
    Segment seg;
    seg.name_ = name;
    seg.creator_ = true;
    try {
        // fchmod: the umask must not narrow the mode the caller asked for.
        if (fchmod(fd, options.mode) != 0) fail_errno(name, "fchmod", errno);
        if (ftruncate(fd, static_cast<off_t>(size)) != 0) fail_errno(name, "ftruncate", errno);
        seg.base_ = map_fd(name, fd, size, options.prefault, options.lock, seg.locked_);
        seg.size_ = size;
    } catch (...) {
        close(fd);
        shm_unlink(name.c_str());
        throw;
    }
    close(fd);
    init_header(seg.header(), kind, size);
    return seg;
}

Segment Segment::attach(const std::string& name, SegmentKind kind, const AttachOptions& options) {
    check_name(name);
    const int fd = shm_open(name.c_str(), O_RDWR, 0);
    if (fd < 0) {
        if (errno == ENOENT) throw SegmentError(name, "does not exist", ENOENT);
        fail_errno(name, "shm_open", errno);
    }
    struct stat st {};
    if (fstat(fd, &st) != 0) {
        const int err = errno;
        close(fd);
        fail_errno(name, "fstat", err);
    }
    const auto size = static_cast<std::size_t>(st.st_size);
    if (size < sizeof(SegmentHeader)) {
        close(fd);
        throw SegmentError(name, "size " + std::to_string(size) +
                                     " bytes is smaller than a segment header");
    }
    Segment seg;
    seg.name_ = name;
    try {
        seg.base_ = map_fd(name, fd, size, options.prefault, options.lock, seg.locked_);
    } catch (...) {
        close(fd);
        throw;
    }
    close(fd);
    seg.size_ = size;
    SegmentHeader& h = seg.header();
    // A segment still being built: wait for publish() a bounded time.
    const std::int64_t deadline = now_ns() + options.ready_timeout_ns;
    for (;;) {
        const auto state = static_cast<SegmentState>(h.state.load(std::memory_order_acquire));
        if (state == SegmentState::ready) break;
        if (state == SegmentState::destroyed || now_ns() > deadline) {
            std::string why = state == SegmentState::destroyed
                                  ? "is being destroyed"
                                  : "is still being built by pid " + std::to_string(h.creator_pid);
            munmap(seg.base_, seg.size_);
            seg.base_ = nullptr;
            throw SegmentError(name, why);
        }
        std::this_thread::sleep_for(std::chrono::microseconds(200));
    }
    try {
        validate_header(name, h, kind, size);
    } catch (...) {
        munmap(seg.base_, seg.size_);
        seg.base_ = nullptr;
        throw;
    }
    // Count ourselves in, then make sure the last user is not destroying it
    // right now (seq_cst pairs with release(): either we see `destroyed`, or
    // the destroyer sees our count and keeps the segment).
    h.attach_count.fetch_add(1, std::memory_order_seq_cst);
    if (h.state.load(std::memory_order_seq_cst) != static_cast<std::uint32_t>(SegmentState::ready)) {
        h.attach_count.fetch_sub(1, std::memory_order_seq_cst);
        munmap(seg.base_, seg.size_);
        seg.base_ = nullptr;
        throw SegmentError(name, "is being destroyed");
    }
    seg.published_ = true;
    return seg;
}

void Segment::publish() noexcept {
    if (!base_) return;
    header().state.store(static_cast<std::uint32_t>(SegmentState::ready), std::memory_order_release);
    published_ = true;
}

bool Segment::release(bool destroy_if_last) noexcept {
    if (!base_) return false;
    SegmentHeader& h = header();
    bool destroy = false;
    if (creator_ && !published_) {
        destroy = true;  // a creation that failed half-way leaves nothing behind
    } else {
        const std::uint32_t before = h.attach_count.fetch_sub(1, std::memory_order_seq_cst);
        if (before == 1 && destroy_if_last) {
            auto ready = static_cast<std::uint32_t>(SegmentState::ready);
            if (h.state.compare_exchange_strong(
                    ready, static_cast<std::uint32_t>(SegmentState::destroyed),
                    std::memory_order_seq_cst)) {
                if (h.attach_count.load(std::memory_order_seq_cst) == 0) {
                    destroy = true;
                } else {
                    // Someone attached meanwhile: it is a user now, keep the segment.
                    h.state.store(static_cast<std::uint32_t>(SegmentState::ready),
                                  std::memory_order_seq_cst);
                }
            }
        }
    }
    if (locked_) munlock(base_, size_);
    munmap(base_, size_);
    base_ = nullptr;
    size_ = 0;
    locked_ = false;
    if (destroy) shm_unlink(name_.c_str());
    return destroy;
}

void Segment::detach() noexcept { release(false); }

bool Segment::detach_destroy_if_last() noexcept { return release(true); }

bool Segment::unlink(const std::string& name) noexcept { return shm_unlink(name.c_str()) == 0; }

bool Segment::exists(const std::string& name) noexcept {
    const int fd = shm_open(name.c_str(), O_RDONLY, 0);
    if (fd < 0) return false;
    close(fd);
    return true;
}

bool Segment::is_stale(const std::string& name) noexcept {
    const int fd = shm_open(name.c_str(), O_RDONLY, 0);
    if (fd < 0) return false;
    struct stat st {};
    bool stale = true;  // too small or unreadable to be anybody's segment
    if (fstat(fd, &st) == 0 && static_cast<std::size_t>(st.st_size) >= sizeof(SegmentHeader)) {
        void* p = mmap(nullptr, sizeof(SegmentHeader), PROT_READ, MAP_SHARED, fd, 0);
        if (p != MAP_FAILED) {
            const auto* h = static_cast<const SegmentHeader*>(p);
            const int pid = h->magic == kSegmentMagic ? h->creator_pid : 0;
            stale = !(pid > 0 && (kill(pid, 0) == 0 || errno == EPERM));
            munmap(p, sizeof(SegmentHeader));
        }
    }
    close(fd);
    return stale;
}

}  // namespace chimera::ipc
