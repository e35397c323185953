// bridge_config.hpp — what a ddsbridge .rmod says, parsed and checked before
// anything touches the network: for each port a topic, a direction, a message
// type, a QoS profile and (subscriptions) an age limit and what stale data does.
//
//   LOCAL
//   DOMAIN    17                      DDS domain id (default 0)
//   CONFIG    cyclone.xml             Cyclone DDS XML configuration, relative to the .rmod (default: Cyclone's own)
//   AGE_CLOCK receive                 receive | source (see README: which clock the age is on)
//   NOTIFY    poll                    poll | spin | wake: how the bridge thread learns of a value to publish
//   JOINT_NAMES j1 j2 j3 j4 j5 j6     the joints' names in JointState.name, published and matched on
//                                     receipt (default: joint1 .. jointN, N the port's elements)
//   JOINT_SUBSET update               update | refuse: a received JointState naming some joints only
//   UNNAMED   refuse                  refuse | positional: a received JointState without names
//   VLIMIT_Q_REF 2 2 2 3 3 3          velocity limit per joint (or one for all) of a subscribed
//                                     JointState.position (its change per cycle) or .velocity port
//   TRATE_T_REF  50 50 50 10 10 10    torque-rate limit per joint (or one for all) of a subscribed
//                                     JointState.effort port (its change per cycle)
//   TOPIC_Q_MEZ  puma/joint_positions  pub  JointState.position  state
//   TOPIC_T_REF  puma/joint_torques    sub  JointState.effort    command  0.02 illegal
//   STAMP_T_REF  T_REF_RX               an OUTVAR of 3 doubles: counter, age, new/repeat/stale
//
// One TOPIC_<port> line per INVAR (pub) and OUTVAR (sub) port but those named
// by a STAMP_ line, and none else.
// Errors are std::invalid_argument naming the .rmod, the line and the key.
#pragma once

#include <chimera/sbs_files.hpp>

#include <cstdint>
#include <string>
#include <vector>

namespace ddsbridge {

enum class Direction : std::uint8_t { pub, sub };
/// What carries the variable: one field of sensor_msgs/JointState, or chimera_msgs/StateVar.
enum class Message : std::uint8_t { joint_position, joint_velocity, joint_effort, state_var };
/// state: best effort, keep last 1 (TBUF: the newest value, never a queue);
/// command: reliable, keep last 1 (the newest value, retransmitted until it arrives).
enum class Qos : std::uint8_t { state, command };
/// What a subscription's cycle does while its newest sample is older than the age limit.
enum class StaleAction : std::uint8_t {
    warn,     ///< a warning; the port keeps the last value received
    hold,     ///< as warn (the last value kept, STAMP -1): the name that says the consumers
              ///< hold on the stamp (pid, trajgen STALE hold), so a STAMP_<port> is required
    zero,     ///< a warning; the port reads zeros (a torque command's safe value)
    illegal,  ///< a warning and the illegal-configuration flag (§3.10) until fresh data returns:
              ///< critical modules (robotsim, canrobot) run their local-stability loop
    error,    ///< the cycle fails: the task goes to ERROR (an operator clears it)
};
/// Which clock a received sample's age is measured on.
enum class AgeClock : std::uint8_t {
    receive,  ///< this machine's CLOCK_MONOTONIC at the sample's arrival: needs no clock sync
    source,   ///< the sender's stamp (header.stamp, CLOCK_REALTIME): needs PTP or chrony
};

/// How the bridge thread learns that the task wrote a value to publish.
enum class Notify : std::uint8_t {
    poll,  ///< it looks at the TBUFs when the task's write is due: no system call on the task thread
    spin,  ///< as poll, but from just before the write is due it keeps looking (a busy wait on
           ///< another CPU, a few % of one) until the write appears: no system call on the task
           ///< thread, and no wake-up between the write and dds_write
    wake,  ///< the task wakes it (futex) after writing: one more system call per cycle, a
           ///< thread wake-up instead of the poll's lag (bench/results/dds.md compares them)
};

struct TopicSpec {
    std::string port;        ///< the internal port name (INVAR or OUTVAR)
    std::string ros_name;    ///< ROS 2 topic name, without "rt/"
    Direction direction = Direction::pub;
    Message message = Message::state_var;
    Qos qos = Qos::state;
    double age_limit = 0;    ///< seconds (sub only)
    StaleAction stale = StaleAction::warn;
    /// STAMP_<port> OUTVAR (sub only): an out-var of 3 doubles the cycle fills
    /// with [counter, age (s; -1 before the first value), 1 new value | 0 a repeat | -1 stale],
    /// for a consumer module that wants to see the stamps itself. Empty: none.
    std::string stamp_port;
    /// VLIMIT_<port> (sub, JointState.position or .velocity) or TRATE_<port>
    /// (sub, JointState.effort): per joint, or one for every joint; empty: none.
    std::vector<double> limits;
    int limits_line = 0;     ///< of the VLIMIT_ or TRATE_ line
    int line = 0;            ///< of the TOPIC_ line

    std::string dds_topic() const { return "rt/" + ros_name; }
};

struct BridgeConfig {
    int domain = 0;
    std::string config_file;  ///< empty: Cyclone's defaults (or CYCLONEDDS_URI); relative: to the .rmod's folder
    AgeClock age_clock = AgeClock::receive;
    Notify notify = Notify::poll;
    std::vector<std::string> joint_names;  ///< empty: joint1 .. jointN for each port (joint_names_for)
    bool refuse_subset = false;   ///< JOINT_SUBSET refuse
    bool accept_unnamed = false;  ///< UNNAMED positional
    std::vector<TopicSpec> topics;  ///< in_vars first (pub), then out_vars (sub), in .rmod order
};

/// Parses and checks the LOCAL section against the .rmod's in_vars and out_vars.
BridgeConfig parse_config(const chimera::RmodFile& rmod);

/// The joint names of a JointState port of `nelem` joints: JOINT_NAMES, or
/// joint1 .. jointN. Throws std::invalid_argument when JOINT_NAMES has
/// another count (naming the .rmod, the key and the port).
std::vector<std::string> joint_names_for(const BridgeConfig& c, const TopicSpec& spec, std::size_t nelem,
                                         const std::string& rmod_file);
/// A port's limits, one per joint (VLIMIT_/TRATE_ gave one or nelem values);
/// throws std::invalid_argument for another count.
std::vector<double> limits_for(const TopicSpec& spec, std::size_t nelem, const std::string& rmod_file);

/// The DDS type name of a message ("sensor_msgs::msg::dds_::JointState_").
const char* type_name(Message m) noexcept;
const char* to_string(StaleAction a) noexcept;

/// Why `name` is not a ROS 2 topic name ("" when it is): letters, digits, '_'
/// and '/', no leading digit, no empty token.
std::string ros_name_problem(const std::string& name);

}  // namespace ddsbridge
