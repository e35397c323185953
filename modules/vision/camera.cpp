// camera — a simulated camera on the robot's hand (thesis Figures 3.15/3.16,
// the sensor of the visual servoing subsystem): each cycle (30 Hz, a camera's
// frame rate) it images the points of a target from the arm's measured tool
// pose and publishes their image coordinates, as a feature tracker on a real
// camera's frames would.
//
//   INVAR   XPOS      measured tool pose [x y z roll pitch yaw] (m, rad)
//   OUTVAR  FEATURES  image coordinates u1 v1 u2 v2 ... of the target's points (pixels)
//   LOCAL   TARGET x y z ...        the points in the robot's base frame (m), 3 per feature pair
//           [FOCAL f] [CENTER cu cv] [SIZE w h]   the pinhole camera (pixels; 800, 320 240, 640 480)
//           [MOUNT x y z r p y]     the camera frame in the tool frame (default: the tool frame)
//
// TARGET may be `set` while the task runs (the target moves). A point the
// camera cannot see (behind it, outside the image) makes every feature NaN
// with a warning, as a tracker that has lost the target reports it.
#include <chimera/module.hpp>

#include <cmath>
#include <limits>
#include <vector>

#include "robotics/kinematics.hpp"
#include "robotics/ports.hpp"
#include "vision/config.hpp"
#include "vision/pinhole.hpp"

namespace rb = chimera::robotics;
namespace vi = chimera::vision;

namespace {

constexpr chimera::LocalKey kCameraLocalKeys[] = {
    {"TARGET", chimera::LocalType::numbers, -chimera::unbounded, chimera::unbounded, true, "target points in the base frame (m), x y z each", ""},
    {"FOCAL", chimera::LocalType::number, 0.0, chimera::unbounded, false, "focal length (pixels)", "800"},
    {"CENTER", chimera::LocalType::numbers, -chimera::unbounded, chimera::unbounded, false, "principal point u v (pixels)", "320 240"},
    {"SIZE", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "image width height (pixels)", "640 480"},
    {"MOUNT", chimera::LocalType::numbers, -chimera::unbounded, chimera::unbounded, false, "camera pose in the tool frame x y z roll pitch yaw", "0 0 0 0 0 0"},
};

class Camera : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kCameraLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        const std::size_t nf = rb::port_nelem(t, "FEATURES");
        if (nf == 0 || nf % 2 != 0) rb::module_error(t, "port FEATURES must have 2 elements per target point");
        points_ = nf / 2;
        features_ = rb::vec_port(t, "FEATURES", nf);
        xpos_ = rb::vec_port(t, "XPOS", 6);
        cam_ = vi::local_pinhole(t);
        mount_ = vi::local_mount(t);
        read_target(t);
        return chimera::Result::OK;
    }

    chimera::Result set(chimera::Task& t) override {
        return rb::apply_local(t, [&] { read_target(t); });
    }

    chimera::Result on(chimera::Task&) override {
        lost_ = false;
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        const KDL::Frame camera = rb::pose_to_frame(Eigen::Map<const rb::Vector6d>(xpos_)) * mount_;
        bool seen = true;
        for (std::size_t i = 0; i < points_ && seen; ++i)
            seen = vi::project(cam_, camera, target_[i], features_[2 * i], features_[2 * i + 1]);
        if (!seen) {
            for (std::size_t k = 0; k < 2 * points_; ++k) features_[k] = std::numeric_limits<double>::quiet_NaN();
            if (!lost_) t.warning("camera: target not in view");
        }
        lost_ = !seen;
        return chimera::Result::OK;
    }

private:
    void read_target(const chimera::Task& t) {
        const std::vector<double> v = vi::local_exactly(t, "TARGET", 3 * points_);
        std::vector<KDL::Vector> points(points_);
        for (std::size_t i = 0; i < points_; ++i) points[i] = KDL::Vector(v[3 * i], v[3 * i + 1], v[3 * i + 2]);
        target_ = std::move(points);  // `set` runs between cycles
    }

    std::size_t points_ = 0;
    double* features_ = nullptr;
    const double* xpos_ = nullptr;
    vi::Pinhole cam_;
    KDL::Frame mount_;
    std::vector<KDL::Vector> target_;
    bool lost_ = false;
};

}  // namespace

CHIMERA_MODULE(camera, Camera)
