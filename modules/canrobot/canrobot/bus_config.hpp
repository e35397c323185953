// canrobot/bus_config.hpp — what the canrobot module and the simulated drives
// must agree on, read from the same .rmod LOCAL section by both:
//
//   INTERFACE       can0                   SocketCAN interface (required)
//   NODES           1 2 3 4 5 6            node id of each joint's drive, joint order (required)
//   COUNTS_PER_REV  1048576                encoder counts per joint revolution (1 or NDOF values)
//   RATED_TORQUE    10 20 10 2 2 2         N m, the unit of torque on the bus (required)
//   TLIMIT          97.6 186.4 ...         N m, the drive's maximum torque (default: the
//                                          largest the bus can carry, 32.767 x RATED_TORQUE)
//   VLIMIT          3 3 3 5 5 5            rad/s, joint speed limit (optional; canrobot/command_limits.hpp)
//   TRATE           500 ...                N m/s, torque rate limit (optional; torque mode only)
#pragma once

#include <chimera/sbs_files.hpp>

#include <cstddef>
#include <string>
#include <vector>

#include <Eigen/Core>

namespace chimera::canrobot {

struct BusConfig {
    std::string interface;
    std::vector<int> nodes;
    Eigen::VectorXd counts_per_rev;
    Eigen::VectorXd rated_torque;
    Eigen::VectorXd torque_limit;
    Eigen::VectorXd vlimit;  ///< rad/s; infinity where absent (no limit)
    Eigen::VectorXd trate;   ///< N m/s; infinity where absent (no limit)

    /// Reads the keys above for a robot of `ndof` joints. Throws
    /// std::invalid_argument naming the .rmod, line and key.
    static BusConfig from_local(const LocalConfig& local, std::size_t ndof);
};

}  // namespace chimera::canrobot
