#include "canrobot/bus_config.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

#include "canrobot/cia402.hpp"
#include "robotics/ports.hpp"

namespace chimera::canrobot {

namespace rb = chimera::robotics;

namespace {
std::string at_line(const LocalConfig& lc, std::string_view key) {
    const LocalConfig::Entry* e = lc.find(key);
    return "line " + std::to_string(e ? e->line : 0) + ": LOCAL " + std::string(key);
}
}  // namespace

BusConfig BusConfig::from_local(const LocalConfig& lc, std::size_t ndof) {
    BusConfig c;
    const auto n = static_cast<Eigen::Index>(ndof);
    c.interface = rb::local_word(lc, "INTERFACE", "");
    if (c.interface.empty()) rb::config_error(lc, "LOCAL INTERFACE (the SocketCAN interface, e.g. can0) is missing");

    const std::vector<double> nodes = lc.numbers("NODES");  // throws naming the key when absent
    if (nodes.size() != ndof)
        rb::config_error(lc, at_line(lc, "NODES") + " has " + std::to_string(nodes.size()) +
                                 " node ids, the robot has " + std::to_string(ndof) + " joints");
    for (double v : nodes) {
        if (v != std::floor(v) || v < cia402::kMinNode || v > cia402::kMaxNode)
            rb::config_error(lc, at_line(lc, "NODES") + ": node id " + std::to_string(v) + " is not 1..127");
        const int id = static_cast<int>(v);
        if (std::find(c.nodes.begin(), c.nodes.end(), id) != c.nodes.end())
            rb::config_error(lc, at_line(lc, "NODES") + ": node id " + std::to_string(id) + " appears twice");
        c.nodes.push_back(id);
    }

    c.counts_per_rev = rb::local_vector(lc, "COUNTS_PER_REV", ndof, 1048576.0);
    if ((c.counts_per_rev.array() <= 0).any())
        rb::config_error(lc, at_line(lc, "COUNTS_PER_REV") + " must be positive");
    if (!lc.has("RATED_TORQUE"))
        rb::config_error(lc, "LOCAL RATED_TORQUE (N m per joint, the unit of torque on the bus) is missing");
    c.rated_torque = rb::local_vector(lc, "RATED_TORQUE", ndof);
    if ((c.rated_torque.array() <= 0).any())
        rb::config_error(lc, at_line(lc, "RATED_TORQUE") + " must be positive");
    const Eigen::VectorXd carried = c.rated_torque * (32767.0 / 1000.0);
    c.torque_limit = lc.has("TLIMIT") ? rb::local_vector(lc, "TLIMIT", ndof) : carried;
    for (Eigen::Index j = 0; j < n; ++j) {
        if (!(c.torque_limit[j] > 0))
            rb::config_error(lc, at_line(lc, "TLIMIT") + " must be positive");
        if (c.torque_limit[j] > carried[j] * (1 + 1e-12))
            rb::config_error(lc, at_line(lc, "TLIMIT") + ": joint " + std::to_string(j + 1) + "'s " +
                                     std::to_string(c.torque_limit[j]) + " N m is more than the bus can carry (" +
                                     std::to_string(carried[j]) + " N m = 32.767 x RATED_TORQUE)");
    }
    // Checked where they are used (CommandLimiter): their meaning depends on MODE.
    constexpr double none = std::numeric_limits<double>::infinity();
    c.vlimit = rb::local_vector(lc, "VLIMIT", ndof, none);
    c.trate = rb::local_vector(lc, "TRATE", ndof, none);
    return c;
}

}  // namespace chimera::canrobot
