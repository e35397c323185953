// vservo — image-based visual servoing (thesis Figures 3.15/3.16, the visual
// servoing subsystem that gives the controllers a new desired Cartesian pose):
// it drives the image features of the target towards where they are wanted.
// Each cycle the camera velocity
//     [v; w] = -GAIN * pinv(L*) * (s - s*) / FOCAL
// (L* the interaction matrix of the desired features at the desired DEPTH, a
// constant, so the cycle is one matrix-vector product) moves the desired tool
// pose X_REF for one period. The features' error then decays about as
// exp(-GAIN t) while the arm keeps up.
//
//   INVAR   FEATURES  image coordinates u1 v1 ... (pixels; NaN: target lost)
//   OUTVAR  XPOS      desired tool pose [x y z roll pitch yaw] (m, rad)
//           [ERR]     feature error, RMS over the points (pixels)
//   LOCAL   DESIRED u1 v1 ...         where the features are wanted (pixels)
//           DEPTH z                   the target's depth there (m)
//           [GAIN g]                  1/s (default 1)
//           [MAXSPEED v w]            m/s, rad/s limits on the camera's motion (default 0.2 0.5)
//           [FOCAL f] [CENTER cu cv] [SIZE w h] [MOUNT x y z r p y]   the camera, as camera.rmod
//
// On `on` X_REF starts where it is (the out-var is read before `on`, §3.5).
// A lost target holds X_REF where it is, with a warning.
#include <chimera/module.hpp>

#include <algorithm>
#include <cmath>
#include <vector>

#include <Eigen/Cholesky>

#include "robotics/kinematics.hpp"
#include "robotics/ports.hpp"
#include "vision/config.hpp"
#include "vision/pinhole.hpp"

namespace rb = chimera::robotics;
namespace vi = chimera::vision;

namespace {

constexpr chimera::LocalKey kVservoLocalKeys[] = {
    {"DESIRED", chimera::LocalType::numbers, -chimera::unbounded, chimera::unbounded, false, "desired features u v each (pixels)", ""},
    {"DEPTH", chimera::LocalType::number, 0.0, chimera::unbounded, false, "target depth at the desired features (m)", ""},
    {"GAIN", chimera::LocalType::number, 0.0, 100.0, true, "convergence rate (1/s)", "1"},
    {"MAXSPEED", chimera::LocalType::numbers, 0.0, chimera::unbounded, true, "camera speed limits: linear (m/s) angular (rad/s)", "0.2 0.5"},
    {"FOCAL", chimera::LocalType::number, 0.0, chimera::unbounded, false, "focal length (pixels)", "800"},
    {"CENTER", chimera::LocalType::numbers, -chimera::unbounded, chimera::unbounded, false, "principal point u v (pixels)", "320 240"},
    {"SIZE", chimera::LocalType::numbers, 0.0, chimera::unbounded, false, "image width height (pixels)", "640 480"},
    {"MOUNT", chimera::LocalType::numbers, -chimera::unbounded, chimera::unbounded, false, "camera pose in the tool frame x y z roll pitch yaw", "0 0 0 0 0 0"},
};

using Twist = Eigen::Matrix<double, 6, 1>;

class Vservo : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kVservoLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        const std::size_t nf = rb::port_nelem(t, "FEATURES");
        if (nf < 6 || nf % 2 != 0)
            rb::module_error(t, "port FEATURES must have 2 elements per point, at least 3 points (6 degrees of freedom)");
        n_ = static_cast<Eigen::Index>(nf);
        features_ = rb::vec_port(t, "FEATURES", nf);
        xpos_ = rb::vec_port(t, "XPOS", 6);
        if (rb::has_out_var(t, "ERR")) err_ = rb::vec_port(t, "ERR", 1);
        cam_ = vi::local_pinhole(t);
        mount_ = vi::local_mount(t);
        const std::vector<double> desired = vi::local_exactly(t, "DESIRED", nf);
        desired_ = Eigen::Map<const Eigen::VectorXd>(desired.data(), n_);
        const double depth = rb::local_number(t, "DEPTH", 0);
        if (!(depth > 0)) rb::module_error(t, "LOCAL DEPTH (the target's depth at the desired features, m) must be > 0");
        read_gains(t);
        // L* and its pseudo-inverse, once: the cycle only multiplies.
        Eigen::MatrixXd l(n_, 6);
        for (Eigen::Index i = 0; i < n_ / 2; ++i) {
            const double x = (desired_[2 * i] - cam_.cu) / cam_.focal, y = (desired_[2 * i + 1] - cam_.cv) / cam_.focal;
            vi::interaction(x, y, depth, l.block<2, 6>(2 * i, 0));
        }
        // pinv(L*) = (L*^T L*)^-1 L*^T, L* of full column rank: refused when its
        // 6 x 6 normal matrix is (nearly) singular.
        const Eigen::MatrixXd normal = l.transpose() * l;
        const Eigen::LDLT<Eigen::MatrixXd> ldlt(normal);
        const Eigen::VectorXd d = ldlt.vectorD().cwiseAbs();
        if (ldlt.info() != Eigen::Success || !(d.minCoeff() > 1e-12 * d.maxCoeff()))
            rb::module_error(t, "LOCAL DESIRED: these features do not fix all 6 degrees of freedom of the camera "
                                "(points in a line or repeated?)");
        const Eigen::MatrixXd pinv = ldlt.solve(l.transpose());
        pinv_ = pinv;
        error_.setZero(n_);
        return chimera::Result::OK;
    }

    chimera::Result set(chimera::Task& t) override {
        return rb::apply_local(t, [&] { read_gains(t); });
    }

    chimera::Result on(chimera::Task&) override {
        lost_ = false;
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        const Eigen::Map<const Eigen::VectorXd> s(features_, n_);
        if (!s.allFinite()) {
            if (!lost_) t.warning("vservo: target lost, holding the desired pose");
            lost_ = true;
            return chimera::Result::OK;
        }
        lost_ = false;
        error_ = s - desired_;
        if (err_) *err_ = std::sqrt(error_.squaredNorm() / static_cast<double>(n_ / 2));
        twist_.noalias() = pinv_ * error_;
        twist_ *= -gain_ / cam_.focal;
        // Limits scale the whole twist, so the camera keeps its direction.
        const double over = std::max({twist_.head<3>().norm() / max_v_, twist_.tail<3>().norm() / max_w_, 1.0});
        twist_ /= over;
        // Move the camera by the twist for one period, in its own frame; the
        // tool goes with it: T' = T M D M^-1.
        const double dt = t.period();
        const KDL::Frame step(KDL::Rot(KDL::Vector(twist_[3], twist_[4], twist_[5]) * dt),
                              KDL::Vector(twist_[0], twist_[1], twist_[2]) * dt);
        Eigen::Map<rb::Vector6d> x(xpos_);
        x = rb::frame_to_pose(rb::pose_to_frame(x) * mount_ * step * mount_.Inverse());
        return chimera::Result::OK;
    }

private:
    void read_gains(const chimera::Task& t) {
        const double gain = rb::local_number(t, "GAIN", 1);
        std::vector<double> lim{0.2, 0.5};
        if (t.local().has("MAXSPEED")) lim = vi::local_exactly(t, "MAXSPEED", 2);
        if (!(gain > 0) || !(lim[0] > 0) || !(lim[1] > 0))
            rb::module_error(t, "LOCAL GAIN and MAXSPEED must be > 0");
        gain_ = gain;
        max_v_ = lim[0];
        max_w_ = lim[1];
    }

    Eigen::Index n_ = 0;
    const double* features_ = nullptr;
    double* xpos_ = nullptr;
    double* err_ = nullptr;
    vi::Pinhole cam_;
    KDL::Frame mount_;
    Eigen::VectorXd desired_, error_;
    Eigen::Matrix<double, 6, Eigen::Dynamic> pinv_;
    Twist twist_ = Twist::Zero();
    double gain_ = 1, max_v_ = 0.2, max_w_ = 0.5;
    bool lost_ = false;
};

}  // namespace

CHIMERA_MODULE(vservo, Vservo)
