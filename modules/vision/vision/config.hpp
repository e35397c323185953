// vision/config.hpp — the LOCAL values both vision modules read: the camera's
// intrinsics and mounting, and lists of exactly so many numbers.
#pragma once

#include <chimera/module.hpp>

#include <string>
#include <string_view>
#include <vector>

#include <Eigen/Core>
#include <kdl/frames.hpp>

#include "robotics/kinematics.hpp"
#include "robotics/ports.hpp"
#include "vision/pinhole.hpp"

namespace chimera::vision {

/// LOCAL `key` with exactly `n` numbers; init errors name the rmod and key.
inline std::vector<double> local_exactly(const Task& t, std::string_view key, std::size_t n) {
    if (!t.local().has(key)) robotics::module_error(t, "LOCAL " + std::string(key) + " is missing");
    const std::vector<double> v = t.local().numbers(key);
    if (v.size() != n)
        robotics::module_error(t, "LOCAL " + std::string(key) + " has " + std::to_string(v.size()) +
                                      " values, expected " + std::to_string(n));
    return v;
}

/// FOCAL f, CENTER cu cv, SIZE width height (pixels).
inline Pinhole local_pinhole(const Task& t) {
    Pinhole c;
    c.focal = robotics::local_number(t, "FOCAL", 800);
    if (!(c.focal > 0)) robotics::module_error(t, "LOCAL FOCAL must be > 0 (pixels)");
    if (t.local().has("CENTER")) {
        const auto v = local_exactly(t, "CENTER", 2);
        c.cu = v[0];
        c.cv = v[1];
    }
    if (t.local().has("SIZE")) {
        const auto v = local_exactly(t, "SIZE", 2);
        c.width = v[0];
        c.height = v[1];
    }
    if (!(c.width > 0 && c.height > 0)) robotics::module_error(t, "LOCAL SIZE must be > 0 (pixels)");
    return c;
}

/// MOUNT x y z roll pitch yaw: the camera frame in the tool frame (default: the tool frame).
inline KDL::Frame local_mount(const Task& t) {
    if (!t.local().has("MOUNT")) return KDL::Frame::Identity();
    const auto v = local_exactly(t, "MOUNT", 6);
    return robotics::pose_to_frame(robotics::Vector6d(Eigen::Map<const robotics::Vector6d>(v.data())));
}

}  // namespace chimera::vision
