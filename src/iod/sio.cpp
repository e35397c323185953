// SIO on a termios serial line: a stream device with one port; read and write
// move bytes, SIO_GET/SIO_SET translate the thesis's iodSioParam_t to termios.
#include "driver.hpp"

#include <fcntl.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <termios.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>

namespace chimera::iod::detail {

namespace {

struct BaudCode {
    int baud;
    speed_t code;
};
constexpr BaudCode kBauds[] = {
    {50, B50}, {75, B75}, {110, B110}, {134, B134}, {150, B150}, {200, B200}, {300, B300},
    {600, B600}, {1200, B1200}, {1800, B1800}, {2400, B2400}, {4800, B4800}, {9600, B9600},
    {19200, B19200}, {38400, B38400}, {57600, B57600}, {115200, B115200}, {230400, B230400},
    {460800, B460800}, {500000, B500000}, {576000, B576000}, {921600, B921600},
    {1000000, B1000000}, {1152000, B1152000}, {1500000, B1500000}, {2000000, B2000000},
    {2500000, B2500000}, {3000000, B3000000}, {3500000, B3500000}, {4000000, B4000000}};

bool baud_code(int baud, speed_t& out) noexcept {
    for (const BaudCode& b : kBauds)
        if (b.baud == baud) {
            out = b.code;
            return true;
        }
    return false;
}

int baud_of(speed_t code) noexcept {
    for (const BaudCode& b : kBauds)
        if (b.code == code) return b.baud;
    return 0;
}

// Raw mode plus the requested line settings; -EINVAL for values termios has
// no code for.
int apply(int fd, const SioParam& p) noexcept {
    termios t{};
    if (tcgetattr(fd, &t) != 0) return -errno;
    cfmakeraw(&t);
    speed_t in, out;
    if (!baud_code(p.baud_rx, in) || !baud_code(p.baud_tx, out)) return -EINVAL;
    // glibc's termios does not pass a separate input rate to Linux (CIBAUD):
    // refuse split rates rather than pretend to set them.
    if (p.baud_rx != p.baud_tx) return -EINVAL;
    if (p.bits < 5 || p.bits > 8 || (p.stop != 1 && p.stop != 2) || p.parity > SIO_SPACE)
        return -EINVAL;
    cfsetispeed(&t, in);
    cfsetospeed(&t, out);
    t.c_cflag &= ~static_cast<tcflag_t>(CSIZE | CSTOPB | PARENB | PARODD | CMSPAR);
    static constexpr tcflag_t sizes[] = {CS5, CS6, CS7, CS8};
    t.c_cflag |= sizes[p.bits - 5] | CREAD | CLOCAL;
    if (p.stop == 2) t.c_cflag |= CSTOPB;
    switch (p.parity) {
    case SIO_ODD: t.c_cflag |= PARENB | PARODD; break;
    case SIO_EVEN: t.c_cflag |= PARENB; break;
    case SIO_MARK: t.c_cflag |= PARENB | CMSPAR | PARODD; break;
    case SIO_SPACE: t.c_cflag |= PARENB | CMSPAR; break;
    default: break;
    }
    t.c_cc[VMIN] = 0;
    t.c_cc[VTIME] = 0;
    if (tcsetattr(fd, TCSANOW, &t) != 0) return -errno;
    return 0;
}

int query(int fd, SioParam& p) noexcept {
    termios t{};
    if (tcgetattr(fd, &t) != 0) return -errno;
    p.baud_rx = baud_of(cfgetispeed(&t));
    p.baud_tx = baud_of(cfgetospeed(&t));
    switch (t.c_cflag & CSIZE) {
    case CS5: p.bits = 5; break;
    case CS6: p.bits = 6; break;
    case CS7: p.bits = 7; break;
    default: p.bits = 8; break;
    }
    p.stop = (t.c_cflag & CSTOPB) ? 2 : 1;
    if (!(t.c_cflag & PARENB)) p.parity = SIO_NONE;
    else if (t.c_cflag & CMSPAR) p.parity = (t.c_cflag & PARODD) ? SIO_MARK : SIO_SPACE;
    else p.parity = (t.c_cflag & PARODD) ? SIO_ODD : SIO_EVEN;
    return 0;
}

class SioDevice final : public Device {
public:
    SioDevice(const DeviceSpec& spec, int start, int end, unsigned flags)
        : Device(spec, start, end, flags) {
        const std::string who = describe(spec);
        const std::string why = check_flags(flags);
        if (!why.empty()) throw Error(who + ": " + why);
        int mode = O_RDWR;
        if ((flags & kDirectionMask) == READ) mode = O_RDONLY;
        if ((flags & kDirectionMask) == WRITE) mode = O_WRONLY;
        fd_ = ::open(spec.path.c_str(), mode | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
        if (fd_ < 0) {
            const int e = errno;
            throw Error(who + ": cannot open serial line " + spec.path + ": " + std::strerror(e));
        }
        if (!isatty(fd_)) {
            ::close(fd_);
            throw Error(who + ": " + spec.path + " is not a terminal (termios)");
        }
        if (const int rc = apply(fd_, spec.sio); rc != 0) {
            ::close(fd_);
            throw Error(who + ": cannot apply BAUD/BITS/STOP/PARITY to " + spec.path + ": " +
                        std::strerror(-rc));
        }
    }
    ~SioDevice() override { ::close(fd_); }

    long read(void* buf, std::size_t count) noexcept override {
        if (!(flags() & READ)) return -EBADF;
        auto* p = static_cast<unsigned char*>(buf);
        const unsigned wait = flags() & kWaitMask;
        if (wait == WAITNOALL) {
            int avail = 0;
            if (ioctl(fd_, FIONREAD, &avail) != 0) return -errno;
            if (static_cast<std::size_t>(avail) < count) return 0;
        }
        if (timeout_us_ >= 0 && (wait == WAITALL || wait == WAITONE)) {
            // Bounded: wait until enough bytes are queued, so that on a
            // timeout nothing has been taken and all stays pending.
            const std::size_t enough = wait == WAITALL ? count : 1;
            WaitBound bound(timeout_us_);
            for (;;) {
                int avail = 0;
                if (ioctl(fd_, FIONREAD, &avail) != 0) return -errno;
                if (static_cast<std::size_t>(avail) >= enough) break;
                const timespec* left = nullptr;
                if (!bound.left(left)) return 0;
                pollfd pf{fd_, POLLIN, 0};
                if (::ppoll(&pf, 1, left, nullptr) < 0 && errno != EINTR) return -errno;
                // A line that delivers bytes one by one wakes poll each time: FIONREAD decides.
                if (avail > 0 && wait == WAITALL) {
                    const timespec pause{0, 200'000};
                    ::nanosleep(&pause, nullptr);
                }
            }
        }
        std::size_t got = 0;
        while (got < count) {
            const ssize_t r = ::read(fd_, p + got, count - got);
            if (r > 0) {
                got += static_cast<std::size_t>(r);
                if (wait != WAITALL) break;
                continue;
            }
            if (r < 0 && errno == EINTR) continue;
            if (r < 0 && errno != EAGAIN) return -errno;
            // Nothing there now.
            if (wait == WAITNONE || wait == WAITNOALL || (wait == WAITONE && got > 0)) break;
            pollfd pf{fd_, POLLIN, 0};
            if (::poll(&pf, 1, -1) < 0 && errno != EINTR) return -errno;
        }
        return static_cast<long>(got);
    }

    long write(const void* buf, std::size_t count) noexcept override {
        if (!(flags() & WRITE)) return -EBADF;
        const auto* p = static_cast<const unsigned char*>(buf);
        const unsigned wait = flags() & kWaitMask;
        std::size_t put = 0;
        while (put < count) {
            const ssize_t w = ::write(fd_, p + put, count - put);
            if (w > 0) {
                put += static_cast<std::size_t>(w);
                continue;
            }
            if (w < 0 && errno == EINTR) continue;
            if (w < 0 && errno != EAGAIN) return -errno;
            if (wait == WAITNONE || wait == WAITNOALL || (wait == WAITONE && put > 0)) break;
            pollfd pf{fd_, POLLOUT, 0};
            if (::poll(&pf, 1, -1) < 0 && errno != EINTR) return -errno;
        }
        return static_cast<long>(put);
    }

protected:
    std::string check_flags(unsigned flags) const override {
        std::string why = Device::check_flags(flags);
        if (!why.empty()) return why;
        if ((flags & kSizeMask) != BYTE) return "a serial line transfers bytes: BYTE elements only";
        if (flags & (SIGNED | TRUNC_LSB)) return "SIGNED and TRUNC_LSB do not apply to a byte stream";
        return {};
    }

    long class_status(Status cmd, long, void* arg) noexcept override {
        switch (cmd) {
        case Status::SIO_GET:
            if (!arg) return -EINVAL;
            return query(fd_, *static_cast<SioParam*>(arg));
        case Status::SIO_SET:
            if (!arg) return -EINVAL;
            return apply(fd_, *static_cast<const SioParam*>(arg));
        case Status::SIO_NREAD: {
            int avail = 0;
            if (ioctl(fd_, FIONREAD, &avail) != 0) return -errno;
            return avail;
        }
        default: return -ENOTSUP;
        }
    }

    long class_control(Control cmd, long arg) noexcept override {
        if (cmd == Control::SIO_FLUSH) return tcflush(fd_, TCIOFLUSH) == 0 ? 0 : -errno;
        if (cmd == Control::WAIT_TIMEOUT) {
            if (arg < -1) return -EINVAL;
            timeout_us_ = arg;
            return 0;
        }
        return -ENOTSUP;
    }

private:
    int fd_ = -1;
    long timeout_us_ = -1;  // WAIT_TIMEOUT for reads; -1: without bound
};

}  // namespace

std::unique_ptr<Device> make_sio(const DeviceSpec& spec, int start, int end, unsigned flags) {
    return std::make_unique<SioDevice>(spec, start, end, flags);
}

}  // namespace chimera::iod::detail
