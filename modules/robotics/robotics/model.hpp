// robotics/model.hpp — robot models for the control-module library (thesis §3.5, §7.3).
//
// A robot is a serial chain of revolute joints described by standard
// Denavit-Hartenberg parameters plus the rigid-body parameters of each link,
// the way the robot interface publishes it as the NDOF and DH out-consts.
// Internally every solver runs on an Orocos KDL chain built from it.
//
// Conventions (those of the Robotics Toolbox, Corke 1996/2017):
//   link i frame = Rz(theta_i + theta0_i) Tz(d_i) Tx(a_i) Rx(alpha_i) from frame i-1;
//   the link's centre of mass r_i and inertia I_i (about the centre of mass) are
//   expressed in link frame i (the distal frame of the link);
//   gravity is the acceleration vector of gravity in the base frame (m/s^2).
//
// Units: metres, radians, kilograms, kg m^2, N m s/rad.
#pragma once

#include <array>
#include <cstddef>
#include <span>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <kdl/chain.hpp>

namespace chimera::robotics {

/// One revolute link: DH kinematics and rigid-body dynamics.
struct DhLink {
    double a = 0;        ///< link length (m)
    double alpha = 0;    ///< link twist (rad)
    double d = 0;        ///< link offset (m)
    double theta0 = 0;   ///< joint angle offset (rad): theta = q + theta0
    double mass = 0;     ///< kg
    std::array<double, 3> com{};      ///< centre of mass in link frame (m)
    std::array<double, 6> inertia{};  ///< Ixx Iyy Izz Ixy Iyz Ixz about the COM (kg m^2)
    double rotor_inertia = 0;  ///< motor/armature inertia reflected to the joint (kg m^2)
    double damping = 0;        ///< viscous friction at the joint (N m s/rad)
    /// Coulomb friction at the joint (N m), the Robotics Toolbox's Tc scaled by
    /// |G|: coulomb_pos while the joint turns forward (qd > 0, >= 0), coulomb_neg
    /// while it turns backward (qd < 0, <= 0; asymmetric in general), none at rest.
    /// Inverse dynamics adds it to the torque the joint needs, as the toolbox's
    /// rne() does.
    double coulomb_pos = 0;
    double coulomb_neg = 0;
};

/// The flat double array of the DH out-const (thesis §3.5). Layout, all doubles:
///   row 0 (header):  [0] layout version (2), [1..3] gravity gx gy gz, [4..17] zero
///   row 1+i (link i): [0] a [1] alpha [2] d [3] theta0 [4] mass [5..7] com xyz
///                     [8..13] Ixx Iyy Izz Ixy Iyz Ixz [14] rotor inertia [15] damping
///                     [16] Coulomb friction forward [17] Coulomb friction backward
/// so a robot with NDOF joints needs DH of NELEM = 18 * (NDOF + 1). Version 1
/// (16 per row, no Coulomb friction) is refused with a message saying so.
inline constexpr std::size_t dh_stride = 18;
inline constexpr double dh_layout_version = 2;
constexpr std::size_t dh_size(std::size_t ndof) { return dh_stride * (ndof + 1); }

class RobotModel {
public:
    RobotModel() = default;
    RobotModel(std::string name, std::vector<DhLink> links, Eigen::Vector3d gravity);

    const std::string& name() const noexcept { return name_; }
    std::size_t ndof() const noexcept { return links_.size(); }
    const std::vector<DhLink>& links() const noexcept { return links_; }
    const Eigen::Vector3d& gravity() const noexcept { return gravity_; }
    /// The KDL chain the solvers run on (one segment per joint, plus a tool frame
    /// when the model came from a URDF file and has one).
    const KDL::Chain& chain() const noexcept { return chain_; }
    /// True when the model has DH parameters (false for a URDF chain).
    bool has_dh() const noexcept { return has_dh_; }

    /// Writes the DH out-const layout above; `out` must hold dh_size(ndof()).
    /// Throws std::invalid_argument when the size is wrong or the model has no DH.
    void pack_dh(std::span<double> out) const;
    /// Reads a DH out-const. `ndof` comes from the NDOF in-const: a DH array whose
    /// size does not match it, or with a bad header, is refused with a message
    /// saying which (std::invalid_argument).
    static RobotModel unpack_dh(std::span<const double> dh, long ndof, std::string name = "DH");

    /// A chain between two links of a URDF file, through kdl_parser/urdfdom.
    /// Gravity is (0, 0, -9.81) in the root frame. Throws std::runtime_error
    /// naming the file and links when the file or the chain cannot be read.
    static RobotModel from_urdf(const std::string& path, const std::string& root,
                                const std::string& tip);

private:
    void build_chain();

    std::string name_;
    std::vector<DhLink> links_;
    Eigen::Vector3d gravity_ = Eigen::Vector3d(0, 0, -9.81);
    KDL::Chain chain_;
    bool has_dh_ = false;
};

/// The Unimation PUMA 560, standard DH, with the dynamic parameters of the
/// Robotics Toolbox's mdl_puma560 (P. Corke), which takes its kinematics and link
/// inertial parameters from B. Armstrong, O. Khatib, J. Burdick, "The explicit
/// dynamic model and inertial parameters of the PUMA 560 arm", IEEE ICRA 1986,
/// and the link masses/centres of mass from P. Corke, B. Armstrong-Hélouvry, "A
/// search for consensus among model parameters reported for the PUMA 560 robot",
/// IEEE ICRA 1994. Armature inertia Jm*G^2, viscous friction B*G^2 and the
/// asymmetric Coulomb friction Tc*|G| as in the toolbox (roboticstoolbox-python
/// 1.5.0, models.DH.Puma560). `base_height` is d of link 1, the height of the
/// shoulder axis above the mounting surface: the toolbox's 26.45 in = 0.67183 m
/// by default (it moves the kinematics, not the torques). Gravity (0, 0, -9.81).
inline constexpr double puma560_base_height = 26.45 * 0.0254;
RobotModel puma560(double base_height = puma560_base_height);

/// Named PUMA 560 configurations of the Robotics Toolbox (rad).
namespace puma560_q {
inline constexpr std::array<double, 6> qz{0, 0, 0, 0, 0, 0};                        ///< zero angle
inline constexpr std::array<double, 6> qr{0, 1.5707963267948966, -1.5707963267948966, 0, 0, 0};  ///< ready: arm up
inline constexpr std::array<double, 6> qs{0, 0, -1.5707963267948966, 0, 0, 0};     ///< stretch: arm horizontal
inline constexpr std::array<double, 6> qn{0, 0.7853981633974483, 3.141592653589793, 0, 0.7853981633974483, 0};  ///< nominal
}  // namespace puma560_q

/// A planar two-link arm moving in the vertical x-y plane of its base (joint axes
/// along z, gravity (0, -g, 0)), each link a point mass at its distal end — the
/// textbook arm of Craig, "Introduction to Robotics", Example 6.6, whose dynamics
/// can be written down by hand.
RobotModel planar2(double l1 = 1.0, double l2 = 0.8, double m1 = 2.0, double m2 = 1.5,
                   double g = 9.81);

}  // namespace chimera::robotics
