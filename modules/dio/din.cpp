// din — digital input SAI module (thesis §7.3): the levels of a range of PIO
// ports (GPIO lines, §7.2) become a typed SVAR, one element per port.
//
//   OUTVAR  DIN      one element per port: byte, word, unsigned, short, int,
//                    float or double, wide enough for the device's WIDTH
//           [EDGES]  unsigned, one element per port: edges seen on the port's
//                    lines since the task was turned on (wraps at 2^32)
//   LOCAL   DATABASE file  DEVICE name  PORTS first [last]  [INVERT mask...]
//           [SYNC_TIMEOUT seconds]  (synchronous tasks)
//
// Periodic (or aperiodic) task: each cycle reads the levels now, never
// waiting. Synchronous task (§7.3, "its timing is based on the timing of the
// sensor"): sync() blocks until an edge on one of the ports, then the cycle
// publishes the levels read at that moment; the tasks using DIN never block.
// See README.md.
#include <chimera/module.hpp>

#include <algorithm>
#include <cstdio>
#include <cstring>
#include <memory>
#include <vector>

#include "dio/digital.hpp"

namespace dio = chimera::dio;
namespace iod = chimera::iod;
using chimera::Result;

namespace {

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kDinLocalKeys[] = {
    {"DATABASE", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "the device database file", ""},
    {"DEVICE", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "the device's name in the database", ""},
    {"PORTS", chimera::LocalType::numbers, 0.0, 1000000.0, false, "the device's ports this task reads", ""},
    {"INVERT", chimera::LocalType::text, -chimera::unbounded, chimera::unbounded, true, "bit mask of the inverted lines, per port or one for all (decimal or 0x hex)", "0"},
    {"SYNC_TIMEOUT", chimera::LocalType::number, 0.0, 1.0, true, "synchronous task: seconds to wait for an edge", ""},
};

class Din : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kDinLocalKeys; }

    Result init(chimera::Task& t) override {
        // Everything that can be wrong is found here, before the ports are
        // opened; the cycle only reads, maps and counts.
        cfg_ = dio::read_config(t.rmod_file(), dio::Direction::in, t.type());
        out_ = dio::value_port(t, "DIN", dio::Direction::in, cfg_);
        const auto& outs = t.rmod_file().out_vars;
        if (std::find(outs.begin(), outs.end(), "EDGES") != outs.end())
            edges_ = dio::edges_port(t, "EDGES", cfg_);
        synchronous_ = t.type() == chimera::TaskType::synchronous;
        const auto n = static_cast<std::size_t>(cfg_.nports());
        raw_.assign(n, 0);
        edge_base_.assign(n, 0);
        dev_ = dio::open_ports(cfg_, dio::Direction::in, synchronous_ ? iod::WAITONE : iod::WAITNONE, nullptr);
        if (synchronous_ && dev_->control(iod::Control::WAIT_TIMEOUT, cfg_.sync_timeout_us) != 0)
            throw dio::ConfigError(cfg_.rmod + ": the PIO driver refused WAIT_TIMEOUT");
        return Result::OK;
    }

    Result on(chimera::Task& t) override {
        // DIN is valid from `on`, not from the first cycle: read the levels
        // now (without waiting, whatever the task type), and count edges from here.
        if (synchronous_)
            if (const long rc = set_wait(iod::WAITNONE); rc < 0) return io_failed(t, "setting WAITNONE", rc);
        const long n = dev_->read(raw_.data(), raw_.size());
        if (synchronous_)
            if (const long rc = set_wait(iod::WAITONE); rc < 0) return io_failed(t, "setting WAITONE", rc);
        if (n < 0) return io_failed(t, "read", n);
        for (std::size_t k = 0; k < raw_.size(); ++k) edge_base_[k] = port_events(k);
        publish();
        return Result::OK;
    }

    Result sync(chimera::Task& t) override {
        // Blocks on the lines' edge events, for at most SYNC_TIMEOUT at a time
        // so that a command (off, kill, set) is never held up longer.
        for (;;) {
            const long n = dev_->read(raw_.data(), raw_.size());
            if (n > 0) return Result::OK;
            if (n < 0) return io_failed(t, "read", n);
            if (t.command_pending()) return Result::OFF;  // the runtime takes the command
        }
    }

    Result cycle(chimera::Task& t) override {
        if (!synchronous_) {  // the synchronous task's sync() has just read them
            const long n = dev_->read(raw_.data(), raw_.size());
            if (n < 0) return io_failed(t, "read", n);
        }
        publish();
        return Result::OK;
    }

    Result set(chimera::Task& t) override {
        const std::string_view arg = t.arg();
        dio::update_config(cfg_, t.rmod_file(), dio::Direction::in, t.type(), arg.substr(0, arg.find(' ')));
        if (synchronous_)
            if (const long rc = dev_->control(iod::Control::WAIT_TIMEOUT, cfg_.sync_timeout_us); rc < 0)
                return io_failed(t, "setting the wait timeout", rc);
        return Result::OK;
    }

    Result kill(chimera::Task&) override {
        dev_.reset();  // the ports are free for another task at once
        return Result::OK;
    }

private:
    void publish() noexcept {
        for (std::size_t k = 0; k < raw_.size(); ++k) dio::store(out_.type, out_.data, k, raw_[k] ^ cfg_.invert[k]);
        if (edges_)
            for (std::size_t k = 0; k < raw_.size(); ++k) edges_[k] = port_events(k) - edge_base_[k];
    }

    std::uint32_t port_events(std::size_t k) const noexcept {
        const long e = dev_->status(iod::Status::PIO_PORT_EVENTS, cfg_.first_port + static_cast<long>(k));
        return e < 0 ? 0u : static_cast<std::uint32_t>(e);
    }

    [[nodiscard]] long set_wait(unsigned wait) noexcept {
        return dev_->control(iod::Control::SET_FLAGS, iod::READ | iod::LONG | wait);
    }

    // Raises the driver's failure through global error handling (the task's
    // error() decides); the message is built without allocating.
    Result io_failed(chimera::Task& t, const char* what, long rc) {
        std::snprintf(msg_, sizeof msg_, "%s of device %s ports %d..%d failed: %s", what, cfg_.device.name.c_str(),
                      cfg_.first_port, cfg_.last_port, std::strerror(static_cast<int>(-rc)));
        return t.error(dio::kErrIo, msg_);  // CONTINUE when a handler said so: DIN keeps its last values
    }

    dio::Config cfg_;
    dio::ValuePort out_;
    std::uint32_t* edges_ = nullptr;
    bool synchronous_ = false;
    std::unique_ptr<iod::Device> dev_;
    std::vector<std::uint32_t> raw_;        // port values as read (before INVERT)
    std::vector<std::uint32_t> edge_base_;  // the driver's per-port counts at `on`
    char msg_[192] = {};
};

}  // namespace

CHIMERA_MODULE(din, Din)
