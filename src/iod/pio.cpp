// PIO on GPIO lines through libgpiod 1.6. A port is `width` adjacent lines
// (bit i of the port value = line first+i). Input lines are requested with
// both-edge events: a port "has new data" when an edge was seen on one of its
// lines since the previous read, which is what the WAIT flags wait for (for
// at most WAIT_TIMEOUT). Output lines are requested at their initial values.
#include "driver.hpp"

#if CHIMERA_HAVE_GPIOD
#include <gpiod.h>
#include <poll.h>
#endif

#include <bit>
#include <cerrno>
#include <cstring>
#include <ctime>

namespace chimera::iod::detail {

#if CHIMERA_HAVE_GPIOD

namespace {

class PioDevice final : public Device {
public:
    PioDevice(const DeviceSpec& spec, int start, int end, unsigned flags, const void* initial)
        : Device(spec, start, end, flags) {
        const std::string who = describe(spec);
        const unsigned dir = flags & kDirectionMask;
        if (dir == RW)
            throw Error(who + ": a GPIO line is an input or an output at any one time: open it "
                              "READ or WRITE, not RW");
        if ((dir & ~spec.directions) != 0)
            throw Error(who + ": opened " + (dir == READ ? "READ" : "WRITE") +
                        " but its DIRECTION is " + (spec.directions == READ ? "IN" : "OUT"));
        const std::string why = check_flags(flags);
        if (!why.empty()) throw Error(who + ": " + why);

        chip_ = gpiod_chip_open_lookup(spec.path.c_str());
        if (!chip_) {
            const int e = errno;
            if (e == ENOENT || e == ENODEV)
                throw Error(who + ": no gpiochip " + spec.path +
                            " (no GPIO controller with that name, label, number or path: is its "
                            "driver loaded? see gpiodetect)");
            throw Error(who + ": cannot open gpiochip " + spec.path + ": " + std::strerror(e));
        }
        nlines_ = nports() * spec.width;
        const unsigned first = static_cast<unsigned>(start * spec.width);
        if (first + nlines_ > gpiod_chip_num_lines(chip_)) {
            gpiod_chip_close(chip_);
            throw Error(who + ": lines " + std::to_string(first) + ".." +
                        std::to_string(first + nlines_ - 1) + " do not exist on " + spec.path +
                        " (" + std::to_string(gpiod_chip_num_lines(chip_)) + " lines)");
        }
        if (dir == NONE) return;  // status only: nothing requested
        unsigned offsets[GPIOD_LINE_BULK_MAX_LINES];
        for (unsigned i = 0; i < nlines_; ++i) offsets[i] = first + i;
        gpiod_line_bulk_init(&bulk_);
        int rc = gpiod_chip_get_lines(chip_, offsets, nlines_, &bulk_);
        if (rc == 0) {
            const std::string consumer = "chimera:" + spec.name;
            if (dir == READ) {
                rc = gpiod_line_request_bulk_both_edges_events(&bulk_, consumer.c_str());
            } else {
                // Requested straight at their initial values: a line never
                // drives 0 first on the way to a safe state of 1.
                int values[GPIOD_LINE_BULK_MAX_LINES] = {};
                if (initial) lines_of(initial, values);
                rc = gpiod_line_request_bulk_output(&bulk_, consumer.c_str(), values);
            }
        }
        if (rc != 0) {
            const int e = errno;
            gpiod_chip_close(chip_);
            throw Error(who + ": cannot request lines of " + spec.path + ": " + std::strerror(e) +
                        (e == EBUSY ? " (in use by another process)" : ""));
        }
        requested_ = true;
    }

    ~PioDevice() override {
        if (requested_) gpiod_line_release_bulk(&bulk_);
        if (chip_) gpiod_chip_close(chip_);
    }

    long read(void* buf, std::size_t count) noexcept override {
        if (!(flags() & READ)) return -EBADF;
        if (count < static_cast<std::size_t>(nports())) return -EINVAL;
        const std::uint64_t all = nports() >= 64 ? ~0ull : ((1ull << nports()) - 1);
        if (long rc = drain(nullptr, true); rc < 0) return rc;
        const unsigned wait = flags() & kWaitMask;
        auto waiting = [&] {
            return (wait == WAITALL && (changed_ & all) != all) || (wait == WAITONE && changed_ == 0);
        };
        if (waiting()) {
            WaitBound bound(timeout_us_);
            do {
                const timespec* left = nullptr;
                if (!bound.left(left)) return 0;  // edges stay pending
                if (long rc = drain(left, false); rc < 0) return rc;
            } while (waiting());
        }
        if (wait == WAITNOALL && (changed_ & all) != all) return 0;
        const long fresh = std::popcount(changed_ & all);
        changed_ = 0;
        int values[GPIOD_LINE_BULK_MAX_LINES];
        if (gpiod_line_get_value_bulk(&bulk_, values) != 0) return -errno;
        const int w = spec().width;
        for (int p = 0; p < nports(); ++p) {
            std::uint32_t raw = 0;
            for (int b = 0; b < w; ++b)
                if (values[p * w + b]) raw |= 1u << b;
            port_to_element(raw, buf, p, w);
        }
        return fresh;
    }

    long write(const void* buf, std::size_t count) noexcept override {
        if (!(flags() & WRITE)) return -EBADF;
        if (count < static_cast<std::size_t>(nports())) return -EINVAL;
        int values[GPIOD_LINE_BULK_MAX_LINES];
        lines_of(buf, values);
        if (gpiod_line_set_value_bulk(&bulk_, values) != 0) return -errno;
        return nports();
    }

protected:
    long class_status(Status cmd, long arg, void*) noexcept override {
        if (cmd == Status::PIO_EVENTS) return static_cast<long>(events_);
        if (cmd == Status::PIO_PORT_EVENTS) {
            if (arg < start_port() || arg > end_port()) return -EINVAL;
            return static_cast<long>(port_events_[static_cast<std::size_t>(arg - start_port())]);
        }
        return -ENOTSUP;
    }

    long class_control(Control cmd, long arg) noexcept override {
        if (cmd == Control::WAIT_TIMEOUT) {
            if (arg < -1) return -EINVAL;
            timeout_us_ = arg;
            return 0;
        }
        return -ENOTSUP;
    }

private:
    // One element per port of `buf` (write()'s layout) -> one value per line.
    void lines_of(const void* buf, int* values) const noexcept {
        const int w = spec().width;
        for (int p = 0; p < nports(); ++p) {
            const std::uint32_t raw = element_to_port(buf, p, w);
            for (int b = 0; b < w; ++b) values[p * w + b] = (raw >> b) & 1u;
        }
    }


    // Reads pending edge events into changed_ and the counters. `poll_only`:
    // do not wait at all; otherwise wait up to `timeout` (nullptr: until an
    // edge). Polls the lines' event descriptors directly (no allocation).
    long drain(const timespec* timeout, bool poll_only) noexcept {
        if (!(flags() & READ)) return 0;
        pollfd fds[GPIOD_LINE_BULK_MAX_LINES];
        for (unsigned i = 0; i < nlines_; ++i) {
            fds[i].fd = gpiod_line_event_get_fd(bulk_.lines[i]);
            fds[i].events = POLLIN | POLLPRI;
            fds[i].revents = 0;
        }
        const timespec zero{};
        int n = ::ppoll(fds, nlines_, poll_only ? &zero : timeout, nullptr);
        if (n < 0) return errno == EINTR ? 0 : -errno;
        for (unsigned i = 0; i < nlines_ && n > 0; ++i) {
            if (!(fds[i].revents & (POLLIN | POLLPRI))) continue;
            gpiod_line_event ev[16];
            const int got = gpiod_line_event_read_multiple(bulk_.lines[i], ev, 16);
            if (got < 0) return -errno;
            if (got > 0) {
                const unsigned port = i / static_cast<unsigned>(spec().width);
                events_ += static_cast<unsigned long>(got);
                port_events_[port] += static_cast<unsigned long>(got);
                changed_ |= 1ull << port;
            }
        }
        return 0;
    }

    gpiod_chip* chip_ = nullptr;
    gpiod_line_bulk bulk_{};
    unsigned nlines_ = 0;
    bool requested_ = false;
    std::uint64_t changed_ = 0;  // bit per port: an edge since the last read
    unsigned long events_ = 0;
    unsigned long port_events_[GPIOD_LINE_BULK_MAX_LINES] = {};  // per opened port
    long timeout_us_ = -1;       // WAIT_TIMEOUT; -1: wait for as long as it takes
};

}  // namespace

std::unique_ptr<Device> make_pio(const DeviceSpec& spec, int start, int end, unsigned flags,
                                 const void* initial) {
    return std::make_unique<PioDevice>(spec, start, end, flags, initial);
}

#else

std::unique_ptr<Device> make_pio(const DeviceSpec& spec, int, int, unsigned, const void*) {
    throw Error(describe(spec) + ": this build of Chimera has no PIO driver (libgpiod was not "
                                 "found when it was configured: meson option gpiod)");
}

#endif

}  // namespace chimera::iod::detail
