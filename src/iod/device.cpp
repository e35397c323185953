// The IOD object: flag checks, port reservation, element conversion, and the
// status/control commands common to every class (thesis §7.2.1).
#include "driver.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <bit>
#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>

namespace chimera::iod {

namespace {

constexpr std::uint32_t mask(int bits) noexcept {
    return bits >= 32 ? 0xFFFFFFFFu : ((std::uint32_t{1} << bits) - 1u);
}

int element_bits_of(unsigned flags) noexcept {
    switch (flags & kSizeMask) {
    case BYTE: return 8;
    case WORD: return 16;
    default: return 32;
    }
}

bool is_port_class(DeviceClass c) noexcept {
    return c != DeviceClass::SIO && c != DeviceClass::MEM;
}

}  // namespace

std::uint32_t convert_in(std::uint32_t raw, int port_bits, int elem_bits, unsigned flags) noexcept {
    raw &= mask(port_bits);
    if (elem_bits >= port_bits) {
        std::uint32_t v = raw;
        if ((flags & SIGNED) && port_bits > 0 && ((raw >> (port_bits - 1)) & 1u)) v |= ~mask(port_bits);
        return v & mask(elem_bits);
    }
    if (flags & TRUNC_LSB) return (raw >> (port_bits - elem_bits)) & mask(elem_bits);
    return raw & mask(elem_bits);
}

std::uint32_t convert_out(std::uint32_t value, int elem_bits, int port_bits, unsigned flags) noexcept {
    value &= mask(elem_bits);
    if (port_bits >= elem_bits) {
        if (flags & TRUNC_LSB) return (value << (port_bits - elem_bits)) & mask(port_bits);
        std::uint32_t v = value;
        if ((flags & SIGNED) && elem_bits > 0 && ((value >> (elem_bits - 1)) & 1u)) v |= ~mask(elem_bits);
        return v & mask(port_bits);
    }
    if (flags & TRUNC_LSB) return (value >> (elem_bits - port_bits)) & mask(port_bits);
    return value & mask(port_bits);
}

std::string lock_directory() {
    const char* d = std::getenv("CHIMERA_IOD_LOCKDIR");
    return d && *d ? d : "/dev/shm";
}

namespace detail {
std::string describe(const DeviceSpec& spec) {
    return "device " + spec.name + " (" + spec.file + ":" + std::to_string(spec.line) + ")";
}
}  // namespace detail

Device::Device(const DeviceSpec& spec, int start, int end, unsigned flags)
    : spec_(spec), start_(start), end_(end), flags_(flags) {}

Device::~Device() {
    if (lock_fd_ >= 0) ::close(lock_fd_);  // releases the port reservation
}

int Device::element_bytes() const noexcept { return element_bits_of(flags_) / 8; }

std::string Device::check_flags(unsigned flags) const {
    const unsigned wait = flags & kWaitMask;
    if (std::popcount(wait) > 1) return "more than one WAIT flag";
    if (std::popcount(flags & kSizeMask) > 1) return "more than one of BYTE, WORD, LONG";
    const unsigned known = kDirectionMask | kWaitMask | kSizeMask | SIGNED | TRUNC_LSB;
    if (flags & ~known) return "unknown flag bits";
    return {};
}

std::uint32_t Device::element_to_port(const void* buf, int index, int port_bits) const noexcept {
    const int eb = element_bits_of(flags_);
    std::uint32_t v = 0;
    const auto* p = static_cast<const unsigned char*>(buf);
    switch (eb) {
    case 8: v = p[index]; break;
    case 16: {
        std::uint16_t w;
        std::memcpy(&w, p + 2 * index, 2);
        v = w;
        break;
    }
    default: std::memcpy(&v, p + 4 * index, 4); break;
    }
    return convert_out(v, eb, port_bits, flags_);
}

void Device::port_to_element(std::uint32_t raw, void* buf, int index, int port_bits) const noexcept {
    const int eb = element_bits_of(flags_);
    const std::uint32_t v = convert_in(raw, port_bits, eb, flags_);
    auto* p = static_cast<unsigned char*>(buf);
    switch (eb) {
    case 8: p[index] = static_cast<unsigned char>(v); break;
    case 16: {
        const auto w = static_cast<std::uint16_t>(v);
        std::memcpy(p + 2 * index, &w, 2);
        break;
    }
    default: std::memcpy(p + 4 * index, &v, 4); break;
    }
}

long Device::status(Status cmd, long arg) noexcept {
    switch (cmd) {
    case Status::PORTSIZE: {
        const int bits = spec_.port_bits(static_cast<int>(arg));
        return bits < 0 ? -EINVAL : bits;
    }
    case Status::PORTNUM: return spec_.port_count();
    case Status::FLAGS: return static_cast<long>(flags_);
    default: return class_status(cmd, arg, nullptr);
    }
}

long Device::status(Status cmd, void* arg) noexcept {
    switch (cmd) {
    case Status::PORTSIZE:
    case Status::PORTNUM:
    case Status::FLAGS: return status(cmd, 0L);
    default: return class_status(cmd, 0, arg);
    }
}

long Device::control(Control cmd, long arg) noexcept {
    if (cmd == Control::SET_FLAGS) {
        auto f = static_cast<unsigned>(arg);
        if ((f & kDirectionMask) != (flags_ & kDirectionMask)) return -EINVAL;
        // A flag set without a WAIT or size flag keeps the current one.
        if (!(f & kWaitMask)) f |= flags_ & kWaitMask;
        if (!(f & kSizeMask)) f |= flags_ & kSizeMask;
        try {
            if (!check_flags(f).empty()) return -EINVAL;
        } catch (...) {
            return -ENOMEM;
        }
        flags_ = f;
        return 0;
    }
    return class_control(cmd, arg);
}

long Device::class_status(Status, long, void*) noexcept { return -ENOTSUP; }
long Device::class_control(Control, long) noexcept { return -ENOTSUP; }

namespace {
// Reserves ports start..end of a device for one instance: an OFD write lock
// on bytes start..end of the device's lock file. OFD locks belong to the open
// file description, so a second instance conflicts even in the same process,
// and the kernel drops them when the process dies.
// The ports' lock file, trusted only when it is ours and no one else may
// write it: another user's file there could be locked by them for ever,
// denying us the device. Root replaces such a file; anyone else is told whose
// it is. Never through a symlink.
int open_lock_file(const DeviceSpec& spec, const std::string& path) {
    for (int attempt = 0;; ++attempt) {
        const int fd = ::open(path.c_str(), O_RDWR | O_CREAT | O_NOFOLLOW | O_CLOEXEC, 0600);
        if (fd < 0)
            throw Error(detail::describe(spec) + ": cannot open lock file " + path + ": " + std::strerror(errno));
        struct stat st {};
        if (::fstat(fd, &st) != 0) {
            const int e = errno;
            ::close(fd);
            throw Error(detail::describe(spec) + ": cannot stat lock file " + path + ": " + std::strerror(e));
        }
        if (st.st_uid == ::geteuid() && (st.st_mode & 022) == 0) return fd;
        ::close(fd);
        char mode[8];
        std::snprintf(mode, sizeof mode, "%04o", static_cast<unsigned>(st.st_mode & 07777));
        const std::string whose = "uid " + std::to_string(st.st_uid) + "'s, mode " + mode;
        if (::geteuid() != 0 || attempt > 0)
            throw Error(detail::describe(spec) + ": lock file " + path + " is " + whose +
                        ", not this user's: remove it (sudo rm " + path + ") and open again");
        std::fprintf(stderr, "chimera: %s: lock file %s was %s: removed, to be created anew\n",
                     detail::describe(spec).c_str(), path.c_str(), whose.c_str());
        if (::unlink(path.c_str()) != 0 && errno != ENOENT)
            throw Error(detail::describe(spec) + ": cannot remove lock file " + path + ": " + std::strerror(errno));
    }
}

int reserve_ports(const DeviceSpec& spec, int start, int end) {
    const std::string path = lock_directory() + "/chimera.iod." + spec.name + ".lock";
    const int fd = open_lock_file(spec, path);
    struct flock fl {};
    fl.l_type = F_WRLCK;
    fl.l_whence = SEEK_SET;
    fl.l_start = start;
    fl.l_len = end - start + 1;
    if (fcntl(fd, F_OFD_SETLK, &fl) != 0) {
        const int e = errno;
        ::close(fd);
        if (e == EAGAIN || e == EACCES)
            throw Error(detail::describe(spec) + ": ports " + std::to_string(start) + ".." +
                        std::to_string(end) + " (or some of them) are already open in another instance");
        throw Error(detail::describe(spec) + ": cannot lock " + path + ": " + std::strerror(e));
    }
    return fd;
}

}  // namespace

std::unique_ptr<Device> open(const Database& db, std::string_view name, int start, int end,
                             unsigned flags, const void* initial) {
    const DeviceSpec* spec = db.find(name);
    if (!spec) throw Error("iod: no device named " + std::string(name) + " in the device database");
    const std::string who = detail::describe(*spec);
    const int nports = spec->port_count();
    if (start < 0 || end < start || end >= nports)
        throw Error(who + ": port range " + std::to_string(start) + ".." + std::to_string(end) +
                    " outside 0.." + std::to_string(nports - 1));
    if (!is_port_class(spec->device_class) && start != end)
        throw Error(who + ": a " + std::string(class_name(spec->device_class)) +
                    " device opens one port at a time");

    // Defaults of §7.2.1: WAITALL for port devices, WAITONE for streams. PIO
    // is the exception: a GPIO level is always valid data, so without a WAIT
    // flag a read returns the levels at once (WAITNONE); waiting is asked for.
    if (!(flags & kWaitMask)) {
        if (spec->device_class == DeviceClass::PIO) flags |= WAITNONE;
        else if (is_port_class(spec->device_class)) flags |= WAITALL;
        else flags |= WAITONE;
    }
    if (!(flags & kSizeMask)) flags |= is_port_class(spec->device_class) ? LONG : BYTE;
    if (initial && (spec->device_class != DeviceClass::PIO || (flags & kDirectionMask) != WRITE))
        throw Error(who + ": initial values are for PIO devices opened WRITE only");

    // Reserve first: a refused double open never touches the hardware.
    const int lock_fd = reserve_ports(*spec, start, end);
    std::unique_ptr<Device> dev;
    try {
    switch (spec->device_class) {
    case DeviceClass::PIO: dev = detail::make_pio(*spec, start, end, flags, initial); break;
    case DeviceClass::RCB: dev = detail::make_can(*spec, start, end, flags); break;
    case DeviceClass::SIO: dev = detail::make_sio(*spec, start, end, flags); break;
    case DeviceClass::MEM: dev = detail::make_mem(*spec, start, end, flags); break;
    default: throw Error(who + ": no driver for class " + std::string(class_name(spec->device_class)));
    }
    const std::string why = dev->check_flags(flags);
    if (!why.empty()) throw Error(who + ": " + why);
    } catch (...) {
        ::close(lock_fd);
        throw;
    }
    dev->lock_fd_ = lock_fd;
    return dev;
}

}  // namespace chimera::iod
