// dout — digital output SAI module (thesis §7.3): a typed SVAR, one element per
// port, drives a range of PIO ports (GPIO lines, §7.2).
//
//   INVAR   DOUT     one element per port: byte, word, unsigned, short, int,
//                    float or double, wide enough for the device's WIDTH
//   LOCAL   DATABASE file  DEVICE name  PORTS first [last]  SAFE value...
//           [INVERT mask...]  [ILLEGAL hold|safe]
//
// The outputs show SAFE whenever the task is not cycling: the lines are
// requested at SAFE in init (they never show another value first), and SAFE
// is driven again on off, kill, every error and clear. A command that is no
// value of its port (negative, fractional, NaN, too wide) is a fault: every
// port goes SAFE and the task halts in ERROR, naming the port and the value.
// See README.md.
#include <chimera/module.hpp>

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
constexpr chimera::LocalKey kDoutLocalKeys[] = {
    {"DATABASE", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "the device database file", ""},
    {"DEVICE", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "the device's name in the database", ""},
    {"PORTS", chimera::LocalType::numbers, 0.0, 1000000.0, false, "the device's ports this task drives", ""},
    {"INVERT", chimera::LocalType::text, -chimera::unbounded, chimera::unbounded, true, "bit mask of the inverted lines, per port or one for all (decimal or 0x hex)", "0"},
    {"SAFE", chimera::LocalType::text, -chimera::unbounded, chimera::unbounded, true, "the value of each port from init, after off and kill, and on an error, per port or one for all (decimal or 0x hex)", ""},
    {"ILLEGAL", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, true, "hold: the last commands stay while the configuration is illegal; safe: SAFE then", "hold"},
};

class Dout : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kDoutLocalKeys; }

    Result init(chimera::Task& t) override {
        // Everything that can be wrong is found here, before the ports are
        // opened; the cycle only maps and writes.
        cfg_ = dio::read_config(t.rmod_file(), dio::Direction::out, t.type());
        in_ = dio::value_port(t, "DOUT", dio::Direction::out, cfg_);
        raw_.assign(static_cast<std::size_t>(cfg_.nports()), 0);
        make_safe_raw();
        dev_ = dio::open_ports(cfg_, dio::Direction::out, 0, safe_raw_.data());
        return Result::OK;
    }

    // on(): nothing to do; the outputs stay SAFE until the first cycle.

    Result cycle(chimera::Task& t) override {
        // ILLEGAL safe: while a reconfiguration is under way or a task has
        // halted on an error, the commands may come from nobody.
        if (cfg_.safe_when_illegal && t.illegal_configuration()) {
            if (const long rc = dev_->write(safe_raw_.data(), safe_raw_.size()); rc < 0)
                return io_failed(t, "writing SAFE", rc);
            return Result::OK;
        }
        const std::uint32_t max = cfg_.port_mask();
        for (std::size_t k = 0; k < raw_.size(); ++k) {
            std::uint32_t v = 0;
            // Never a guess at what was meant: no port is written this cycle.
            if (!dio::load(in_.type, in_.data, k, max, v)) return bad_command(t, k);
            raw_[k] = v ^ cfg_.invert[k];
        }
        if (const long rc = dev_->write(raw_.data(), raw_.size()); rc < 0) return io_failed(t, "write", rc);
        return Result::OK;
    }

    Result off(chimera::Task& t) override {
        if (const long rc = drive_safe(); rc < 0) return io_failed(t, "writing SAFE", rc);
        return Result::OK;
    }

    Result error(chimera::Task&, const chimera::err::Error&) override {
        drive_safe();  // whatever failed, the outputs must not hold the last command
        return Result::ERROR;
    }

    Result clear(chimera::Task&, const chimera::err::Error&) override {
        // Cleared only when SAFE can be driven again (not with the device gone).
        return drive_safe() < 0 ? Result::ERROR : Result::OFF;
    }

    Result kill(chimera::Task& t) override {
        if (!dev_) return Result::OK;  // init failed before opening
        // The runtime has run off() already when the task was ON; drive SAFE
        // again in case that failed, then free the ports. (What a released
        // line shows is the GPIO controller's business: most keep the last
        // value, gpio-sim shows its pull.)
        const long rc = drive_safe();
        dev_.reset();
        if (rc < 0) return io_failed(t, "writing SAFE before releasing the lines", rc);
        return Result::OK;
    }

    Result set(chimera::Task& t) override {
        const std::string_view arg = t.arg();
        dio::update_config(cfg_, t.rmod_file(), dio::Direction::out, t.type(), arg.substr(0, arg.find(' ')));
        make_safe_raw();
        // Not cycling: the outputs show SAFE, so show the new SAFE (or INVERT).
        if (t.state() != chimera::State::ON) {
            if (const long rc = drive_safe(); rc < 0) return io_failed(t, "writing SAFE", rc);
        }
        return Result::OK;
    }

    ~Dout() override {
        if (dev_) drive_safe();  // kill() normally did it
    }

private:
    // SAFE as the lines show it (after INVERT).
    void make_safe_raw() {
        safe_raw_.resize(cfg_.safe.size());
        for (std::size_t k = 0; k < safe_raw_.size(); ++k) safe_raw_[k] = cfg_.safe[k] ^ cfg_.invert[k];
    }

    long drive_safe() noexcept { return dev_ ? dev_->write(safe_raw_.data(), safe_raw_.size()) : 0; }

    // The messages are built without allocating; global error handling then
    // calls error(), which drives SAFE (unless a handler says continue).
    Result io_failed(chimera::Task& t, const char* what, long rc) {
        std::snprintf(msg_, sizeof msg_, "%s on device %s ports %d..%d failed: %s", what, cfg_.device.name.c_str(),
                      cfg_.first_port, cfg_.last_port, std::strerror(static_cast<int>(-rc)));
        return t.error(dio::kErrIo, msg_);  // CONTINUE when a handler said so
    }

    Result bad_command(chimera::Task& t, std::size_t k) {
        char value[48];
        format_element(k, value, sizeof value);
        std::snprintf(msg_, sizeof msg_, "DOUT[%zu] is %s, not a value of the %d-bit port %d (0..%u): all ports driven SAFE",
                      k, value, cfg_.device.width, cfg_.first_port + static_cast<int>(k), cfg_.port_mask());
        drive_safe();  // not only the bad port: the command set as a whole is suspect
        return t.error(dio::kErrCommand, msg_);  // CONTINUE: SAFE this cycle, the next commands next cycle
    }

    void format_element(std::size_t k, char* buf, std::size_t size) const noexcept {
        using chimera::svar::Type;
        switch (in_.type) {
        case Type::byte_: std::snprintf(buf, size, "%u", unsigned{static_cast<const std::uint8_t*>(in_.data)[k]}); break;
        case Type::word: std::snprintf(buf, size, "%u", unsigned{static_cast<const std::uint16_t*>(in_.data)[k]}); break;
        case Type::unsigned_: std::snprintf(buf, size, "%u", static_cast<const std::uint32_t*>(in_.data)[k]); break;
        case Type::short_: std::snprintf(buf, size, "%d", int{static_cast<const std::int16_t*>(in_.data)[k]}); break;
        case Type::int_: std::snprintf(buf, size, "%d", static_cast<const std::int32_t*>(in_.data)[k]); break;
        case Type::float_: std::snprintf(buf, size, "%.9g", double{static_cast<const float*>(in_.data)[k]}); break;
        case Type::double_: std::snprintf(buf, size, "%.17g", static_cast<const double*>(in_.data)[k]); break;
        default: std::snprintf(buf, size, "?"); break;
        }
    }

    dio::Config cfg_;
    dio::ValuePort in_;
    std::unique_ptr<iod::Device> dev_;
    std::vector<std::uint32_t> raw_;       // this cycle's port values (after INVERT)
    std::vector<std::uint32_t> safe_raw_;  // SAFE as the lines show it
    char msg_[224] = {};
};

}  // namespace

CHIMERA_MODULE(dout, Dout)
