// canrobot/cia402.hpp — the CAN protocol between the canrobot SAI module and
// its joint drives: a documented subset of CANopen (CiA 301 communication,
// CiA 402 drive profile). Both sides include this header — the module
// (modules/canrobot/canrobot.cpp) and the drive simulator (drive_sim.hpp) —
// so they cannot disagree on an identifier, a bit or a unit. The protocol in
// prose, with a bus-load estimate, is in modules/canrobot/README.md.
//
// One drive per joint, node id 1..127, 11-bit identifiers of the CiA 301
// predefined connection set. Payloads little-endian; every field of one frame
// has the same width, so each frame is `FRAME id IN|OUT <ports> <bits>` of
// the IOD RCB driver (iod.hpp):
//
//   frame      COB-ID      dir      fields                                      sent
//   NMT        0x000       master   command u8, node u8 (0 = all)               on demand
//   SYNC       0x080       master   counter u8 (1..240)                         once per cycle, after the RPDOs
//   RPDO1      0x200+node  master   controlword u16, mode i16, target torque i16 every cycle
//   RPDO2      0x300+node  master   target position i32, velocity offset i32   every cycle in CSP
//   TPDO1      0x180+node  drive    statusword u16, mode display i16, error u16 on change, on entering
//                                                                               operational, and every
//                                                                               event-timer period
//   TPDO2      0x280+node  drive    position actual i32, velocity actual i32   at every SYNC (latched then)
//   heartbeat  0x700+node  drive    NMT state u8                                every heartbeat period
//
// Units: positions in encoder counts (COUNTS_PER_REV per joint revolution),
// velocities in counts/s, torques in thousandths of the joint's rated torque
// (CiA 402 objects 0x6071/0x6076). A target torque takes effect at the next
// SYNC, as in cyclic synchronous mode.
#pragma once

#include <cstdint>
#include <string_view>

namespace chimera::canrobot::cia402 {

// --- identifiers ---------------------------------------------------------------
inline constexpr std::uint32_t kNmt = 0x000;
inline constexpr std::uint32_t kSync = 0x080;
inline constexpr std::uint32_t kTpdo1 = 0x180;
inline constexpr std::uint32_t kRpdo1 = 0x200;
inline constexpr std::uint32_t kTpdo2 = 0x280;
inline constexpr std::uint32_t kRpdo2 = 0x300;
inline constexpr std::uint32_t kHeartbeat = 0x700;
inline constexpr int kMinNode = 1;
inline constexpr int kMaxNode = 127;
/// The SYNC counter runs 1..kSyncCounterOverflow, then wraps to 1 (CiA 301 0x1019).
inline constexpr std::uint8_t kSyncCounterOverflow = 240;

constexpr std::uint32_t cob_id(std::uint32_t function, int node) noexcept {
    return function + static_cast<std::uint32_t>(node);
}

// --- NMT (CiA 301) -----------------------------------------------------------------
enum class NmtCommand : std::uint8_t {
    start = 0x01,            ///< -> operational: PDOs are exchanged
    stop = 0x02,             ///< -> stopped: only NMT and heartbeat
    enter_preoperational = 0x80,
    reset_node = 0x81,
    reset_communication = 0x82,
};
/// The state a heartbeat carries.
enum class NmtState : std::uint8_t {
    boot_up = 0x00,  ///< sent once, as the first heartbeat after power-on
    stopped = 0x04,
    operational = 0x05,
    preoperational = 0x7F,
};
std::string_view to_string(NmtState s) noexcept;

// --- modes of operation (0x6060 / 0x6061) --------------------------------------------
inline constexpr std::int16_t kModeNone = 0;
inline constexpr std::int16_t kModeCsp = 8;   ///< cyclic synchronous position
inline constexpr std::int16_t kModeCst = 10;  ///< cyclic synchronous torque

// --- the CiA 402 power state machine -----------------------------------------------------
enum class DriveState : std::uint8_t {
    not_ready_to_switch_on,
    switch_on_disabled,
    ready_to_switch_on,
    switched_on,
    operation_enabled,   ///< the only state in which the drive produces torque
    quick_stop_active,
    fault_reaction_active,
    fault,
};
std::string_view to_string(DriveState s) noexcept;

// Controlword commands (0x6040): the bits 0..3 and 7 that select a transition.
inline constexpr std::uint16_t kCwShutdown = 0x0006;
inline constexpr std::uint16_t kCwSwitchOn = 0x0007;
inline constexpr std::uint16_t kCwEnableOperation = 0x000F;
inline constexpr std::uint16_t kCwDisableVoltage = 0x0000;
inline constexpr std::uint16_t kCwQuickStop = 0x0002;
inline constexpr std::uint16_t kCwFaultReset = 0x0080;  ///< acts on the rising edge of bit 7

// Statusword bits (0x6041).
inline constexpr std::uint16_t kSwReadyToSwitchOn = 1u << 0;
inline constexpr std::uint16_t kSwSwitchedOn = 1u << 1;
inline constexpr std::uint16_t kSwOperationEnabled = 1u << 2;
inline constexpr std::uint16_t kSwFault = 1u << 3;
inline constexpr std::uint16_t kSwVoltageEnabled = 1u << 4;
inline constexpr std::uint16_t kSwQuickStop = 1u << 5;  ///< 0 = quick stop active
inline constexpr std::uint16_t kSwSwitchOnDisabled = 1u << 6;
inline constexpr std::uint16_t kSwRemote = 1u << 9;

/// The state a statusword reports (the masks of CiA 402's state table).
constexpr DriveState decode_statusword(std::uint16_t sw) noexcept {
    if ((sw & 0x4F) == 0x00) return DriveState::not_ready_to_switch_on;
    if ((sw & 0x4F) == 0x40) return DriveState::switch_on_disabled;
    if ((sw & 0x6F) == 0x21) return DriveState::ready_to_switch_on;
    if ((sw & 0x6F) == 0x23) return DriveState::switched_on;
    if ((sw & 0x6F) == 0x27) return DriveState::operation_enabled;
    if ((sw & 0x6F) == 0x07) return DriveState::quick_stop_active;
    if ((sw & 0x4F) == 0x0F) return DriveState::fault_reaction_active;
    if ((sw & 0x4F) == 0x08) return DriveState::fault;
    return DriveState::not_ready_to_switch_on;  // not a state of the table
}

/// The statusword a drive in state `s` sends (bit 9 "remote": PDO-controlled).
constexpr std::uint16_t encode_statusword(DriveState s) noexcept {
    switch (s) {
    case DriveState::not_ready_to_switch_on: return kSwRemote;
    case DriveState::switch_on_disabled: return kSwRemote | kSwSwitchOnDisabled;
    case DriveState::ready_to_switch_on: return kSwRemote | kSwQuickStop | kSwReadyToSwitchOn;
    case DriveState::switched_on:
        return kSwRemote | kSwQuickStop | kSwVoltageEnabled | kSwSwitchedOn | kSwReadyToSwitchOn;
    case DriveState::operation_enabled:
        return kSwRemote | kSwQuickStop | kSwVoltageEnabled | kSwOperationEnabled | kSwSwitchedOn |
               kSwReadyToSwitchOn;
    case DriveState::quick_stop_active:
        return kSwRemote | kSwVoltageEnabled | kSwOperationEnabled | kSwSwitchedOn | kSwReadyToSwitchOn;
    case DriveState::fault_reaction_active:
        return kSwRemote | kSwFault | kSwOperationEnabled | kSwSwitchedOn | kSwReadyToSwitchOn;
    case DriveState::fault: return kSwRemote | kSwFault;
    }
    return kSwRemote;
}

/// Drive side: the state after receiving `cw` in state `s` (`previous_cw` is
/// the controlword received before it, for the fault-reset edge). Level
/// semantics: one transition per controlword received, so "enable operation"
/// sent repeatedly walks ready-to-switch-on -> switched-on -> enabled.
/// Internal faults and power-on are not controlword transitions: see DriveSim.
constexpr DriveState next_state(DriveState s, std::uint16_t cw, std::uint16_t previous_cw) noexcept {
    const bool disable_voltage = (cw & 0x82) == 0x00;
    const bool quick_stop = (cw & 0x86) == 0x02;
    const bool shutdown = (cw & 0x87) == 0x06;
    const bool switch_on = (cw & 0x8F) == 0x07;
    const bool enable = (cw & 0x8F) == 0x0F;
    switch (s) {
    case DriveState::not_ready_to_switch_on: return s;  // leaves on its own after power-on
    case DriveState::switch_on_disabled: return shutdown ? DriveState::ready_to_switch_on : s;
    case DriveState::ready_to_switch_on:
        if (switch_on || enable) return DriveState::switched_on;                      // 3
        if (disable_voltage || quick_stop) return DriveState::switch_on_disabled;     // 7
        return s;
    case DriveState::switched_on:
        if (enable) return DriveState::operation_enabled;                             // 4
        if (shutdown) return DriveState::ready_to_switch_on;                          // 6
        if (disable_voltage || quick_stop) return DriveState::switch_on_disabled;     // 10
        return s;
    case DriveState::operation_enabled:
        if (switch_on) return DriveState::switched_on;                                // 5
        if (shutdown) return DriveState::ready_to_switch_on;                          // 8
        if (quick_stop) return DriveState::quick_stop_active;                         // 11
        if (disable_voltage) return DriveState::switch_on_disabled;                   // 9
        return s;
    case DriveState::quick_stop_active:
        if (enable) return DriveState::operation_enabled;                             // 16
        if (disable_voltage) return DriveState::switch_on_disabled;                   // 12
        return s;
    case DriveState::fault_reaction_active: return s;  // ends on its own in `fault`
    case DriveState::fault:
        // 15: the rising edge of bit 7 only; holding 0x80 does nothing more.
        return (cw & 0x80) && !(previous_cw & 0x80) ? DriveState::switch_on_disabled : s;
    }
    return s;
}

/// Master side: the controlword that moves a drive in state `s` one step
/// toward operation enabled (fault: alternate with `previous_cw` to make the
/// reset edge). Returns kCwEnableOperation once enabled.
constexpr std::uint16_t controlword_toward_enabled(DriveState s, std::uint16_t previous_cw) noexcept {
    switch (s) {
    case DriveState::switch_on_disabled: return kCwShutdown;
    case DriveState::ready_to_switch_on: return kCwSwitchOn;
    case DriveState::switched_on:
    case DriveState::operation_enabled: return kCwEnableOperation;
    case DriveState::quick_stop_active: return kCwDisableVoltage;
    case DriveState::fault: return (previous_cw & 0x80) ? kCwDisableVoltage : kCwFaultReset;
    case DriveState::not_ready_to_switch_on:
    case DriveState::fault_reaction_active: return kCwDisableVoltage;
    }
    return kCwDisableVoltage;
}

// --- error codes (0x603F; CiA 301 emergency codes) -------------------------------------------
inline constexpr std::uint16_t kErrNone = 0x0000;
inline constexpr std::uint16_t kErrSoftware = 0x6000;       ///< simulation diverged
inline constexpr std::uint16_t kErrParameter = 0x6320;      ///< unsupported mode of operation
inline constexpr std::uint16_t kErrRpdoTimeout = 0x8250;    ///< no RPDO1 within the timeout while enabled
/// A name for the codes above ("RPDO timeout"); "" for others.
std::string_view error_name(std::uint16_t code) noexcept;

// --- unit conversions -----------------------------------------------------------------
/// Target torque (thousandths of the rated torque) for `newton_metres`,
/// rounded and saturated to the int16 range.
std::int16_t torque_to_permille(double newton_metres, double rated_torque) noexcept;
inline double permille_to_torque(std::int16_t permille, double rated_torque) noexcept {
    return permille * rated_torque / 1000.0;
}
/// Radians (or rad/s) to counts (counts/s), rounded and saturated to int32.
std::int32_t to_counts(double radians, double counts_per_rev) noexcept;
double from_counts(std::int32_t counts, double counts_per_rev) noexcept;

// --- frames as bytes (the drive simulator and the tests speak raw CAN) ---------------------------
struct Frame {
    std::uint32_t id = 0;
    std::uint8_t len = 0;
    std::uint8_t data[8] = {};
};
inline void put_u16(Frame& f, int at, std::uint16_t v) noexcept {
    f.data[at] = static_cast<std::uint8_t>(v);
    f.data[at + 1] = static_cast<std::uint8_t>(v >> 8);
}
inline void put_u32(Frame& f, int at, std::uint32_t v) noexcept {
    for (int b = 0; b < 4; ++b) f.data[at + b] = static_cast<std::uint8_t>(v >> (8 * b));
}
inline std::uint16_t get_u16(const Frame& f, int at) noexcept {
    return static_cast<std::uint16_t>(f.data[at] | (f.data[at + 1] << 8));
}
inline std::uint32_t get_u32(const Frame& f, int at) noexcept {
    std::uint32_t v = 0;
    for (int b = 0; b < 4; ++b) v |= static_cast<std::uint32_t>(f.data[at + b]) << (8 * b);
    return v;
}

}  // namespace chimera::canrobot::cia402
