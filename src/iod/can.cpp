// RCB on SocketCAN raw sockets. Each FRAME of the device database maps one CAN
// identifier to `ports` ports of `port_bits` bits, packed little-endian in the
// payload (port k at bit k*port_bits). An instance has its own socket whose
// receive filter passes only the input frames of its ports, plus every error
// frame (counted, reported through status). Frames carry kernel receive
// timestamps (SO_TIMESTAMPNS).
#include "driver.hpp"

#if CHIMERA_HAVE_SOCKETCAN
#include <linux/can.h>
#include <linux/can/error.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>
#endif

#include <cerrno>
#include <cstring>
#include <vector>

namespace chimera::iod::detail {

#if CHIMERA_HAVE_SOCKETCAN

namespace {

struct FrameState {
    FrameSpec spec;
    bool in_range = false;   // carries at least one opened port
    bool fresh = false;      // received since the last read
    std::uint64_t payload = 0;
    std::int64_t stamp_ns = 0;
};

class CanDevice final : public Device {
public:
    CanDevice(const DeviceSpec& spec, int start, int end, unsigned flags)
        : Device(spec, start, end, flags) {
        const std::string who = describe(spec);
        const std::string why = check_flags(flags);
        if (!why.empty()) throw Error(who + ": " + why);
        const unsigned dir = flags & kDirectionMask;
        for (const FrameSpec& f : spec.frames) {
            FrameState s;
            s.spec = f;
            s.in_range = f.first_port <= end && f.first_port + f.ports - 1 >= start;
            if (s.in_range) {
                // Direction errors are caught here, never in the cycle (§7.2.1).
                if (f.input && dir == WRITE)
                    throw Error(who + ": opened WRITE but frame " + hex(f.can_id) + " (ports " +
                                range(f) + ") is IN");
                if (!f.input && dir == READ)
                    throw Error(who + ": opened READ but frame " + hex(f.can_id) + " (ports " +
                                range(f) + ") is OUT");
            }
            frames_.push_back(s);
        }
        for (int p = start; p <= end; ++p) port_frame_.push_back(frame_of(p));

        fd_ = ::socket(PF_CAN, SOCK_RAW | SOCK_CLOEXEC | SOCK_NONBLOCK, CAN_RAW);
        if (fd_ < 0) {
            const int e = errno;
            if (e == EAFNOSUPPORT || e == EPROTONOSUPPORT || e == EINVAL)
                throw Error(who + ": no AF_CAN support in this kernel (CAN_RAW socket: " +
                            std::strerror(e) + "; modules can and can-raw loaded?)");
            throw Error(who + ": CAN socket: " + std::strerror(e));
        }
        const unsigned ifindex = if_nametoindex(spec.path.c_str());
        if (ifindex == 0) {
            ::close(fd_);
            throw Error(who + ": no CAN interface named " + spec.path);
        }
        std::vector<can_filter> filters;
        for (const FrameState& s : frames_) {
            if (!s.in_range || !s.spec.input) continue;
            can_filter cf{};
            cf.can_id = s.spec.can_id | (spec.extended ? CAN_EFF_FLAG : 0);
            cf.can_mask = (spec.extended ? CAN_EFF_MASK : CAN_SFF_MASK) | CAN_EFF_FLAG | CAN_RTR_FLAG;
            filters.push_back(cf);
        }
        const can_err_mask_t err_mask = CAN_ERR_MASK;
        const int on = 1;
        sockaddr_can addr{};
        addr.can_family = AF_CAN;
        addr.can_ifindex = static_cast<int>(ifindex);
        if (setsockopt(fd_, SOL_CAN_RAW, CAN_RAW_FILTER, filters.empty() ? nullptr : filters.data(),
                       static_cast<socklen_t>(filters.size() * sizeof(can_filter))) != 0 ||
            setsockopt(fd_, SOL_CAN_RAW, CAN_RAW_ERR_FILTER, &err_mask, sizeof err_mask) != 0 ||
            setsockopt(fd_, SOL_SOCKET, SO_TIMESTAMPNS, &on, sizeof on) != 0 ||
            bind(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
            const int e = errno;
            ::close(fd_);
            throw Error(who + ": cannot set up CAN socket on " + spec.path + ": " + std::strerror(e));
        }
    }

    ~CanDevice() override {
        if (fd_ >= 0) ::close(fd_);
    }

    long read(void* buf, std::size_t count) noexcept override {
        if (!(flags() & READ)) return -EBADF;
        if (count < static_cast<std::size_t>(nports())) return -EINVAL;
        const timespec now{};
        if (long rc = drain(&now); rc < 0) return rc;
        const unsigned wait = flags() & kWaitMask;
        WaitBound bound(timeout_us_);
        for (;;) {
            int wanted = 0, fresh = 0;
            for (const FrameState& s : frames_)
                if (s.in_range && s.spec.input) {
                    ++wanted;
                    fresh += s.fresh;
                }
            const bool enough = wait == WAITALL ? fresh == wanted
                              : wait == WAITONE ? fresh > 0
                                                : true;
            if (wait == WAITNOALL && fresh != wanted) return 0;
            if (enough) break;
            const timespec* left = nullptr;
            if (!bound.left(left)) return 0;  // what arrived stays fresh for the next read
            if (long rc = drain(left, true); rc < 0) return rc;
        }
        long n = 0;
        for (int i = 0; i < nports(); ++i) {
            const FrameState& s = frames_[static_cast<std::size_t>(port_frame_[static_cast<std::size_t>(i)])];
            if (!s.spec.input) continue;  // an output port of an RW instance
            const int k = start_port() + i - s.spec.first_port;
            const int bits = s.spec.port_bits;
            const std::uint64_t m = bits >= 64 ? ~0ull : ((1ull << bits) - 1);
            port_to_element(static_cast<std::uint32_t>((s.payload >> (k * bits)) & m), buf, i, bits);
            n += s.fresh;
        }
        for (FrameState& s : frames_) s.fresh = false;
        return n;
    }

    long write(const void* buf, std::size_t count) noexcept override {
        if (!(flags() & WRITE)) return -EBADF;
        if (count < static_cast<std::size_t>(nports())) return -EINVAL;
        long ports = 0;  // opened output ports, the return value
        for (int i = 0; i < nports(); ++i) {
            FrameState& s = frames_[static_cast<std::size_t>(port_frame_[static_cast<std::size_t>(i)])];
            if (s.spec.input) continue;
            ++ports;
            const int k = start_port() + i - s.spec.first_port;
            const int bits = s.spec.port_bits;
            const std::uint64_t m = (bits >= 64 ? ~0ull : ((1ull << bits) - 1)) << (k * bits);
            const std::uint64_t v = static_cast<std::uint64_t>(element_to_port(buf, i, bits)) << (k * bits);
            s.payload = (s.payload & ~m) | (v & m);
        }
        for (FrameState& s : frames_) {
            if (!s.in_range || s.spec.input) continue;
            can_frame f{};
            f.can_id = s.spec.can_id | (spec().extended ? CAN_EFF_FLAG : 0);
            f.can_dlc = static_cast<std::uint8_t>((s.spec.ports * s.spec.port_bits + 7) / 8);
            for (int b = 0; b < 8; ++b) f.data[b] = static_cast<std::uint8_t>(s.payload >> (8 * b));
            for (;;) {
                const ssize_t w = ::write(fd_, &f, sizeof f);
                if (w == static_cast<ssize_t>(sizeof f)) break;
                if (w < 0 && errno == EINTR) continue;
                if (w < 0 && (errno == EAGAIN || errno == ENOBUFS)) {
                    const unsigned wait = flags() & kWaitMask;
                    if (wait == WAITNONE || wait == WAITNOALL) return -EAGAIN;  // transmit queue full
                    pollfd p{fd_, POLLOUT, 0};
                    if (::poll(&p, 1, 10) < 0 && errno != EINTR) return -errno;
                    continue;
                }
                return w < 0 ? -errno : -EIO;
            }
        }
        return ports;
    }

protected:
    long class_control(Control cmd, long arg) noexcept override {
        if (cmd != Control::WAIT_TIMEOUT) return -ENOTSUP;
        if (arg < -1) return -EINVAL;
        timeout_us_ = arg;
        return 0;
    }

    long class_status(Status cmd, long arg, void*) noexcept override {
        switch (cmd) {
        case Status::CAN_RX_FRAMES: return static_cast<long>(rx_frames_);
        case Status::CAN_ERRORS: return static_cast<long>(errors_);
        case Status::CAN_LAST_ERROR: return static_cast<long>(last_error_);
        case Status::CAN_TIMESTAMP: {
            const int p = static_cast<int>(arg);
            if (p < start_port() || p > end_port()) return -EINVAL;
            return static_cast<long>(
                frames_[static_cast<std::size_t>(port_frame_[static_cast<std::size_t>(p - start_port())])].stamp_ns);
        }
        default: return -ENOTSUP;
        }
    }

private:
    static std::string hex(std::uint32_t v) {
        char b[16];
        std::snprintf(b, sizeof b, "0x%X", v);
        return b;
    }
    static std::string range(const FrameSpec& f) {
        return std::to_string(f.first_port) + ".." + std::to_string(f.first_port + f.ports - 1);
    }
    int frame_of(int port) const noexcept {
        for (std::size_t i = 0; i < frames_.size(); ++i)
            if (port < frames_[i].spec.first_port + frames_[i].spec.ports) return static_cast<int>(i);
        return -1;
    }

    // Receives every queued frame; with `block`, first waits for one (for
    // at most `timeout`, nullptr: without bound).
    long drain(const timespec* timeout, bool block = false) noexcept {
        if (block) {
            pollfd p{fd_, POLLIN, 0};
            if (::ppoll(&p, 1, timeout, nullptr) < 0 && errno != EINTR) return -errno;
        }
        for (;;) {
            can_frame f;
            alignas(cmsghdr) char control[CMSG_SPACE(sizeof(timespec))];
            iovec iov{&f, sizeof f};
            msghdr msg{};
            msg.msg_iov = &iov;
            msg.msg_iovlen = 1;
            msg.msg_control = control;
            msg.msg_controllen = sizeof control;
            const ssize_t r = ::recvmsg(fd_, &msg, MSG_DONTWAIT);
            if (r < 0) {
                if (errno == EAGAIN || errno == EWOULDBLOCK) return 0;
                if (errno == EINTR) continue;
                return -errno;
            }
            if (r < static_cast<ssize_t>(sizeof f)) continue;
            if (f.can_id & CAN_ERR_FLAG) {
                ++errors_;
                last_error_ = f.can_id & CAN_ERR_MASK;
                continue;
            }
            const std::uint32_t id = f.can_id & (spec().extended ? CAN_EFF_MASK : CAN_SFF_MASK);
            for (FrameState& s : frames_) {
                if (!s.spec.input || s.spec.can_id != id) continue;
                std::uint64_t v = 0;
                for (int b = 0; b < f.can_dlc && b < 8; ++b) v |= std::uint64_t{f.data[b]} << (8 * b);
                s.payload = v;
                s.fresh = true;
                ++rx_frames_;
                for (cmsghdr* c = CMSG_FIRSTHDR(&msg); c; c = CMSG_NXTHDR(&msg, c))
                    if (c->cmsg_level == SOL_SOCKET && c->cmsg_type == SO_TIMESTAMPNS) {
                        timespec ts;
                        std::memcpy(&ts, CMSG_DATA(c), sizeof ts);
                        s.stamp_ns = ts.tv_sec * 1'000'000'000LL + ts.tv_nsec;
                    }
                break;
            }
        }
    }

    int fd_ = -1;
    long timeout_us_ = -1;  // WAIT_TIMEOUT; -1: wait for as long as it takes
    std::vector<FrameState> frames_;
    std::vector<int> port_frame_;  // frame index of each opened port
    unsigned long rx_frames_ = 0;
    unsigned long errors_ = 0;
    std::uint32_t last_error_ = 0;
};

}  // namespace

std::unique_ptr<Device> make_can(const DeviceSpec& spec, int start, int end, unsigned flags) {
    return std::make_unique<CanDevice>(spec, start, end, flags);
}

#else

std::unique_ptr<Device> make_can(const DeviceSpec& spec, int, int, unsigned) {
    throw Error(describe(spec) + ": this build of Chimera has no CAN driver (linux/can.h was not "
                                 "found when it was configured: meson option socketcan)");
}

#endif

}  // namespace chimera::iod::detail
