// vision/pinhole.hpp — the pinhole camera both vision modules share (thesis
// Figures 3.15/3.16): projection of target points into the image, and the
// interaction matrix (image Jacobian) of a point feature, which says how the
// feature moves for a camera velocity. Header-only, no allocation.
//
// The camera frame: origin at the optical centre, z along the optical axis
// (out of the lens), x to the right of the image and y down it. A point at
// (X, Y, Z) in that frame images at u = F X/Z + CU, v = F Y/Z + CV (pixels).
#pragma once

#include <Eigen/Core>
#include <kdl/frames.hpp>

namespace chimera::vision {

struct Pinhole {
    double focal = 800;                ///< F, pixels
    double cu = 320, cv = 240;         ///< principal point, pixels
    double width = 640, height = 480;  ///< image size, pixels
};

/// Images world point `p` with the camera at `camera` (its frame in the world).
/// False when the point is behind the camera (Z < 1 cm) or outside the image.
inline bool project(const Pinhole& cam, const KDL::Frame& camera, const KDL::Vector& p, double& u,
                    double& v) noexcept {
    const KDL::Vector c = camera.Inverse(p);
    if (!(c.z() > 0.01)) return false;
    u = cam.focal * c.x() / c.z() + cam.cu;
    v = cam.focal * c.y() / c.z() + cam.cv;
    return u >= 0 && u <= cam.width && v >= 0 && v <= cam.height;
}

/// Rows of the interaction matrix for a point feature at normalised image
/// coordinates (x, y) = ((u - CU)/F, (v - CV)/F) and depth Z: d(x, y)/dt =
/// L [v; w] for the camera's linear velocity v and angular velocity w, both in
/// the camera frame (Chaumette & Hutchinson, "Visual servo control, part I",
/// IEEE RAM 2006, eq. 11).
inline void interaction(double x, double y, double z, Eigen::Ref<Eigen::Matrix<double, 2, 6>> l) noexcept {
    l << -1 / z, 0, x / z, x * y, -(1 + x * x), y,  //
        0, -1 / z, y / z, 1 + y * y, -x * y, -x;
}

}  // namespace chimera::vision
