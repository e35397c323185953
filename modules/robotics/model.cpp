// Robot models: DH + rigid-body parameters -> KDL chain; the DH out-const layout;
// PUMA 560 and planar two-link models; URDF chains through kdl_parser.
#include "robotics/model.hpp"

#include <cmath>
#include <stdexcept>
#include <utility>

#include <kdl/tree.hpp>
#include <kdl_parser/kdl_parser.hpp>
#include <urdf_parser/urdf_parser.h>

#include <fstream>
#include <sstream>

namespace chimera::robotics {

RobotModel::RobotModel(std::string name, std::vector<DhLink> links, Eigen::Vector3d gravity)
    : name_(std::move(name)), links_(std::move(links)), gravity_(gravity), has_dh_(true) {
    build_chain();
}

void RobotModel::build_chain() {
    chain_ = KDL::Chain();
    for (const DhLink& l : links_) {
        // KDL segment pose = RotZ(q) * f_tip; with f_tip = DH(a, alpha, d, theta0)
        // this is the standard DH transform with theta = q + theta0.
        // Rotor inertia and friction are added by Dynamics itself, not left to KDL
        // (whose solvers differ between versions in whether they include them).
        KDL::Joint joint(KDL::Joint::RotZ);
        KDL::Frame tip = KDL::Frame::DH(l.a, l.alpha, l.d, l.theta0);
        // RTB order Ixx Iyy Izz Ixy Iyz Ixz; KDL's is Ixx Iyy Izz Ixy Ixz Iyz.
        KDL::RotationalInertia ic(l.inertia[0], l.inertia[1], l.inertia[2], l.inertia[3],
                                  l.inertia[5], l.inertia[4]);
        KDL::RigidBodyInertia rbi(l.mass, KDL::Vector(l.com[0], l.com[1], l.com[2]), ic);
        chain_.addSegment(KDL::Segment(joint, tip, rbi));
    }
}

void RobotModel::pack_dh(std::span<double> out) const {
    if (!has_dh_) {
        throw std::invalid_argument("robot model " + name_ +
                                    " has no DH parameters (it came from a URDF chain)");
    }
    if (out.size() != dh_size(ndof())) {
        throw std::invalid_argument("DH of " + name_ + ": needs " +
                                    std::to_string(dh_size(ndof())) + " elements for NDOF " +
                                    std::to_string(ndof()) + ", have " +
                                    std::to_string(out.size()));
    }
    for (double& v : out) v = 0;
    out[0] = dh_layout_version;
    out[1] = gravity_.x();
    out[2] = gravity_.y();
    out[3] = gravity_.z();
    for (std::size_t i = 0; i < links_.size(); ++i) {
        const DhLink& l = links_[i];
        double* r = out.data() + dh_stride * (i + 1);
        r[0] = l.a;
        r[1] = l.alpha;
        r[2] = l.d;
        r[3] = l.theta0;
        r[4] = l.mass;
        for (int k = 0; k < 3; ++k) r[5 + k] = l.com[k];
        for (int k = 0; k < 6; ++k) r[8 + k] = l.inertia[k];
        r[14] = l.rotor_inertia;
        r[15] = l.damping;
        r[16] = l.coulomb_pos;
        r[17] = l.coulomb_neg;
    }
}

RobotModel RobotModel::unpack_dh(std::span<const double> dh, long ndof, std::string name) {
    if (ndof < 1 || ndof > 64) {
        throw std::invalid_argument("NDOF is " + std::to_string(ndof) +
                                    ", must be between 1 and 64");
    }
    const auto n = static_cast<std::size_t>(ndof);
    if (dh.size() != dh_size(n)) {
        throw std::invalid_argument(name + " has " + std::to_string(dh.size()) +
                                    " elements but NDOF " + std::to_string(ndof) + " needs " +
                                    std::to_string(dh_size(n)) + " (18 x (NDOF+1))");
    }
    if (dh[0] != dh_layout_version) {
        throw std::invalid_argument(name + " header says layout version " + std::to_string(dh[0]) +
                                    ", expected 2 (was it written by a robot interface?)");
    }
    std::vector<DhLink> links(n);
    for (std::size_t i = 0; i < n; ++i) {
        const double* r = dh.data() + dh_stride * (i + 1);
        DhLink& l = links[i];
        l.a = r[0];
        l.alpha = r[1];
        l.d = r[2];
        l.theta0 = r[3];
        l.mass = r[4];
        for (int k = 0; k < 3; ++k) l.com[k] = r[5 + k];
        for (int k = 0; k < 6; ++k) l.inertia[k] = r[8 + k];
        l.rotor_inertia = r[14];
        l.damping = r[15];
        l.coulomb_pos = r[16];
        l.coulomb_neg = r[17];
        if (!(l.coulomb_pos >= 0) || !(l.coulomb_neg <= 0)) {
            throw std::invalid_argument(name + " link " + std::to_string(i + 1) +
                                        " has Coulomb friction forward " +
                                        std::to_string(l.coulomb_pos) + ", backward " +
                                        std::to_string(l.coulomb_neg) +
                                        " (must be >= 0 and <= 0: it opposes the motion)");
        }
        if (!(l.mass >= 0) || !std::isfinite(l.a) || !std::isfinite(l.alpha) ||
            !std::isfinite(l.d) || !std::isfinite(l.theta0)) {
            throw std::invalid_argument(name + " link " + std::to_string(i + 1) +
                                        " has a negative mass or a non-finite parameter");
        }
    }
    return RobotModel(std::move(name), std::move(links), Eigen::Vector3d(dh[1], dh[2], dh[3]));
}

RobotModel RobotModel::from_urdf(const std::string& path, const std::string& root,
                                 const std::string& tip) {
    // Read and parse with urdfdom ourselves: Debian's kdl_parser::treeFromFile
    // dereferences a null model when the file is missing or malformed.
    std::ifstream in(path);
    if (!in) throw std::runtime_error(path + ": cannot open URDF file");
    std::stringstream text;
    text << in.rdbuf();
    const urdf::ModelInterfaceSharedPtr urdf_model = urdf::parseURDF(text.str());
    if (!urdf_model) throw std::runtime_error(path + ": not a valid URDF robot description");
    KDL::Tree tree;
    if (!kdl_parser::treeFromUrdfModel(*urdf_model, tree)) {
        throw std::runtime_error(path + ": kdl_parser cannot build a KDL tree from this URDF");
    }
    RobotModel m;
    if (!tree.getChain(root, tip, m.chain_)) {
        throw std::runtime_error(path + ": no chain from link '" + root + "' to link '" + tip +
                                 "'");
    }
    m.name_ = path + ":" + root + "->" + tip;
    m.gravity_ = Eigen::Vector3d(0, 0, -9.81);
    m.has_dh_ = false;
    // Joints only; fixed segments stay in the chain as part of the kinematics.
    m.links_.resize(m.chain_.getNrOfJoints());
    if (m.links_.empty()) {
        throw std::runtime_error(path + ": chain '" + root + "'->'" + tip + "' has no moving joint");
    }
    return m;
}

RobotModel puma560(double base_height) {
    constexpr double pi = 3.141592653589793;
    // Per joint, measured at the motor: Jm, G (gear ratio), B (viscous), Tc
    // (Coulomb, forward then backward). At the joint the armature inertia is
    // Jm*G^2, the viscous friction B*G^2 and the Coulomb friction Tc*|G|, as the
    // toolbox's Link.friction() and rne() scale them.
    struct Motor { double jm, g, b, tc_pos, tc_neg; };
    const Motor mot[6] = {{200e-6, -62.6111, 1.48e-3, 0.395, -0.435},
                          {200e-6, 107.815, 0.817e-3, 0.126, -0.071},
                          {200e-6, -53.7063, 1.38e-3, 0.132, -0.105},
                          {33e-6, 76.0364, 71.2e-6, 11.2e-3, -16.9e-3},
                          {33e-6, 71.923, 82.6e-6, 9.26e-3, -14.5e-3},
                          {33e-6, 76.686, 36.7e-6, 3.96e-3, -10.5e-3}};
    std::vector<DhLink> l(6);
    //            a        alpha   d
    l[0] = {0.0,    pi / 2,  base_height, 0, 0.0,  {0, 0, 0},               {0, 0.35, 0, 0, 0, 0}, 0, 0};
    l[1] = {0.4318, 0.0,     0.0,     0, 17.4, {-0.3638, 0.006, 0.2275}, {0.13, 0.524, 0.539, 0, 0, 0}, 0, 0};
    l[2] = {0.0203, -pi / 2, 0.15005, 0, 4.8,  {-0.0203, -0.0141, 0.070}, {0.066, 0.086, 0.0125, 0, 0, 0}, 0, 0};
    l[3] = {0.0,    pi / 2,  0.4318,  0, 0.82, {0, 0.019, 0},            {1.8e-3, 1.3e-3, 1.8e-3, 0, 0, 0}, 0, 0};
    l[4] = {0.0,    -pi / 2, 0.0,     0, 0.34, {0, 0, 0},                {0.3e-3, 0.4e-3, 0.3e-3, 0, 0, 0}, 0, 0};
    l[5] = {0.0,    0.0,     0.0,     0, 0.09, {0, 0, 0.032},            {0.15e-3, 0.15e-3, 0.04e-3, 0, 0, 0}, 0, 0};
    for (int i = 0; i < 6; ++i) {
        l[i].rotor_inertia = mot[i].jm * mot[i].g * mot[i].g;
        l[i].damping = mot[i].b * mot[i].g * mot[i].g;
        l[i].coulomb_pos = mot[i].tc_pos * std::abs(mot[i].g);
        l[i].coulomb_neg = mot[i].tc_neg * std::abs(mot[i].g);
    }
    return RobotModel("puma560", std::move(l), Eigen::Vector3d(0, 0, -9.81));
}

RobotModel planar2(double l1, double l2, double m1, double m2, double g) {
    std::vector<DhLink> l(2);
    l[0].a = l1;
    l[0].mass = m1;
    l[1].a = l2;
    l[1].mass = m2;
    // com (0,0,0) in the link frame = the distal end of the link: point masses.
    return RobotModel("planar2", std::move(l), Eigen::Vector3d(0, -g, 0));
}

}  // namespace chimera::robotics
