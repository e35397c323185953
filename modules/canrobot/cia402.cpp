#include "canrobot/cia402.hpp"

#include <cmath>
#include <limits>

namespace chimera::canrobot::cia402 {

std::string_view to_string(NmtState s) noexcept {
    switch (s) {
    case NmtState::boot_up: return "boot-up";
    case NmtState::stopped: return "stopped";
    case NmtState::operational: return "operational";
    case NmtState::preoperational: return "pre-operational";
    }
    return "unknown";
}

std::string_view to_string(DriveState s) noexcept {
    switch (s) {
    case DriveState::not_ready_to_switch_on: return "not ready to switch on";
    case DriveState::switch_on_disabled: return "switch on disabled";
    case DriveState::ready_to_switch_on: return "ready to switch on";
    case DriveState::switched_on: return "switched on";
    case DriveState::operation_enabled: return "operation enabled";
    case DriveState::quick_stop_active: return "quick stop active";
    case DriveState::fault_reaction_active: return "fault reaction active";
    case DriveState::fault: return "fault";
    }
    return "unknown";
}

std::string_view error_name(std::uint16_t code) noexcept {
    switch (code) {
    case kErrNone: return "no error";
    case kErrSoftware: return "software (simulation diverged)";
    case kErrParameter: return "unsupported mode of operation";
    case kErrRpdoTimeout: return "RPDO timeout";
    default: return "";
    }
}

namespace {
template <typename Int>
Int round_saturate(double v) noexcept {
    if (std::isnan(v)) return 0;
    constexpr double lo = std::numeric_limits<Int>::min();
    constexpr double hi = std::numeric_limits<Int>::max();
    const double r = std::nearbyint(v);
    return r <= lo ? std::numeric_limits<Int>::min() : r >= hi ? std::numeric_limits<Int>::max() : static_cast<Int>(r);
}
constexpr double kTwoPi = 6.283185307179586;
}  // namespace

std::int16_t torque_to_permille(double newton_metres, double rated_torque) noexcept {
    return round_saturate<std::int16_t>(newton_metres * 1000.0 / rated_torque);
}

std::int32_t to_counts(double radians, double counts_per_rev) noexcept {
    return round_saturate<std::int32_t>(radians * counts_per_rev / kTwoPi);
}

double from_counts(std::int32_t counts, double counts_per_rev) noexcept {
    return counts * kTwoPi / counts_per_rev;
}

}  // namespace chimera::canrobot::cia402
