// jtball — joint teleoperation with a trackball on a serial line (thesis
// Figure 6.10 and Table 1; the serial port through the SIO driver, §7.2). The
// trackball's six axes are rate commands: joint j moves at GAIN[j] times the
// deflection of axis j while the operator holds the ENABLE button (protocol in
// teleop/trackball.hpp).
//
//   INCONST NDOF                (1 to 6: axis j drives joint j)
//   OUTVAR  Q_REF               reference joint positions (rad)
//   LOCAL   DATABASE file       the IOD device database (relative: from the .rmod's folder)
//           DEVICE name         its SIO device the trackball is on
//           [GAIN v...]         rad/s at full deflection, 1 or NDOF values (default 0.5)
//           [DEADBAND d]        fraction of full scale read as 0 (default 0.05)
//           [MIN q...] [MAX q...]  rad, Q_REF is kept in [MIN, MAX]
//           [TIMEOUT s]         no good packet for this long: stop and warn (default 0.5)
//
// Each cycle reads whatever the line has (WAITNONE: the task never blocks on
// the operator) and uses the newest good packet. On `on` the line is flushed,
// so nothing sent while the task was off moves the arm, and Q_REF starts where
// it is (the out-var is read before `on`, §3.5).
#include <chimera/iod.hpp>
#include <chimera/ipc/clock.hpp>
#include <chimera/module.hpp>

#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <memory>

#include "robotics/ports.hpp"
#include "teleop/trackball.hpp"

namespace rb = chimera::robotics;
namespace iod = chimera::iod;
namespace tp = chimera::teleop;

namespace {

constexpr chimera::LocalKey kJtballLocalKeys[] = {
    {"DATABASE", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "the IOD device database file", ""},
    {"DEVICE", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false, "the trackball's SIO device", ""},
    {"GAIN", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "joint speed at full deflection (rad/s)", "0.5"},
    {"DEADBAND", chimera::LocalType::number, 0.0, 0.99, false, "deflection read as zero (fraction)", "0.05"},
    {"MIN", chimera::LocalType::numbers, -chimera::unbounded, chimera::unbounded, false, "lower joint limit (rad)", "-1e300"},
    {"MAX", chimera::LocalType::numbers, -chimera::unbounded, chimera::unbounded, false, "upper joint limit (rad)", "1e300"},
    {"TIMEOUT", chimera::LocalType::number, 0.0, chimera::unbounded, false, "seconds without a packet before stopping", "0.5"},
};

class Jtball : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kJtballLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        n_ = rb::read_ndof(t);
        if (n_ > tp::kTrackballAxes)
            rb::module_error(t, "NDOF is " + std::to_string(n_) + ", the trackball has 6 axes (one per joint)");
        q_ref_ = rb::vec_port(t, "Q_REF", n_);
        gain_ = rb::local_vector(t, "GAIN", n_, 0.5);
        if ((gain_.array() <= 0).any()) rb::module_error(t, "LOCAL GAIN must be > 0");
        deadband_ = rb::local_number(t, "DEADBAND", 0.05);
        if (!(deadband_ >= 0 && deadband_ < 1)) rb::module_error(t, "LOCAL DEADBAND must be in [0, 1)");
        lo_ = rb::local_vector(t, "MIN", n_, -1e300);
        hi_ = rb::local_vector(t, "MAX", n_, 1e300);
        if ((lo_.array() > hi_.array()).any()) rb::module_error(t, "LOCAL MIN exceeds MAX");
        const double timeout = rb::local_number(t, "TIMEOUT", 0.5);
        if (!(timeout > 0)) rb::module_error(t, "LOCAL TIMEOUT must be > 0");
        timeout_ns_ = static_cast<std::int64_t>(timeout * 1e9);
        open_line(t);
        speed_.setZero(static_cast<Eigen::Index>(n_));
        return chimera::Result::OK;
    }

    chimera::Result on(chimera::Task& t) override {
        if (const long rc = line_->control(iod::Control::SIO_FLUSH, 0); rc < 0)
            rb::module_error(t, "flushing the trackball's line: " + std::string(std::strerror(static_cast<int>(-rc))));
        parser_.reset();
        speed_.setZero();
        last_packet_ns_ = chimera::ipc::now_ns();
        silent_ = false;
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        const std::int64_t now = chimera::ipc::now_ns();
        std::size_t packets = 0;
        for (;;) {  // what the line has, a bounded number of bytes per read
            const long got = line_->read(bytes_.data(), bytes_.size());
            if (got < 0) {
                t.warning("jtball: reading the trackball's line failed; holding position");
                speed_.setZero();
                break;
            }
            packets += parser_.feed(bytes_.data(), static_cast<std::size_t>(got));
            if (static_cast<std::size_t>(got) < bytes_.size()) break;
        }
        if (packets > 0) {
            use(parser_.latest());
            last_packet_ns_ = now;
            silent_ = false;
        } else if (!silent_ && now - last_packet_ns_ > timeout_ns_) {
            speed_.setZero();  // the trackball went quiet: stop, whatever it said last
            silent_ = true;
            t.warning("jtball: no packet from the trackball, holding position");
        }
        const auto n = static_cast<Eigen::Index>(n_);
        Eigen::Map<Eigen::VectorXd> q_ref(q_ref_, n);
        q_ref = (q_ref + t.period() * speed_).cwiseMax(lo_).cwiseMin(hi_);
        return chimera::Result::OK;
    }

private:
    void open_line(chimera::Task& t) {
        std::filesystem::path db = rb::local_word(t, "DATABASE", "");
        const std::string device = rb::local_word(t, "DEVICE", "");
        if (db.empty()) rb::module_error(t, "LOCAL DATABASE (the IOD device database) is missing");
        if (device.empty()) rb::module_error(t, "LOCAL DEVICE (the trackball's SIO device) is missing");
        if (db.is_relative()) db = std::filesystem::path(t.rmod_file().path).parent_path() / db;
        try {
            db_ = iod::Database::load(db.string());
            const iod::DeviceSpec* spec = db_.find(device);
            if (!spec) throw iod::Error(db.string() + ": no device named " + device);
            if (spec->device_class != iod::DeviceClass::SIO)
                throw iod::Error("device " + device + " (" + spec->file + ":" + std::to_string(spec->line) +
                                 ") is not a serial line (SIO)");
            line_ = iod::open(db_, device, 0, 0, iod::READ | iod::BYTE | iod::WAITNONE);
        } catch (const std::exception& e) {
            rb::module_error(t, std::string("trackball: ") + e.what());
        }
    }

    void use(const tp::TrackballPacket& p) noexcept {
        for (std::size_t j = 0; j < n_; ++j) {
            const double d = p.deflection(j);
            // Outside the deadband, speed rises from 0 at its edge to GAIN at full scale.
            const double live = std::fabs(d) <= deadband_ ? 0.0 : (std::fabs(d) - deadband_) / (1 - deadband_);
            const auto i = static_cast<Eigen::Index>(j);
            speed_[i] = p.enabled() ? std::copysign(live, d) * gain_[i] : 0.0;
        }
    }

    std::size_t n_ = 0;
    double* q_ref_ = nullptr;
    iod::Database db_;
    std::unique_ptr<iod::Device> line_;
    tp::TrackballParser parser_;
    std::array<std::uint8_t, 256> bytes_{};
    Eigen::VectorXd gain_, lo_, hi_, speed_;
    double deadband_ = 0.05;
    std::int64_t timeout_ns_ = 0, last_packet_ns_ = 0;
    bool silent_ = false;
};

}  // namespace

CHIMERA_MODULE(jtball, Jtball)
