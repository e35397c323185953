// Simulated CANopen joint drives (see canrobot/drive_sim.hpp).
#include "canrobot/drive_sim.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>


#include "canrobot/sdo.hpp"
#include "robotics/ports.hpp"

#if CHIMERA_HAVE_SOCKETCAN
#include <linux/can.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <ctime>
#endif

namespace chimera::canrobot {

namespace rb = chimera::robotics;
using namespace cia402;

namespace {
std::int64_t seconds_to_ns(const LocalConfig& lc, std::string_view key, double fallback) {
    const double s = lc.number(key, fallback);  // throws naming file, line and key
    if (!(s >= 0) || s > 3600)
        rb::config_error(lc, "LOCAL " + std::string(key) + " must be 0..3600 seconds");
    return static_cast<std::int64_t>(std::llround(s * 1e9));
}
}  // namespace

DriveConfig DriveConfig::from_rmod(const RmodFile& rmod) {
    const LocalConfig& lc = rmod.local;
    DriveConfig c;
    c.model = rb::robot_from_local(lc);
    const std::size_t n = c.model.ndof();
    c.bus = BusConfig::from_local(lc, n);
    c.q0 = rb::local_vector(lc, "Q0", n, 0.0);
    // A stiff position loop: a drive does not know the arm's gravity, the
    // integral carries it.
    c.csp.kp = rb::local_vector(lc, "DRIVE_KP", n, 2000.0);
    c.csp.ki = rb::local_vector(lc, "DRIVE_KI", n, 10000.0);
    c.csp.kd = rb::local_vector(lc, "DRIVE_KD", n, 200.0);
    c.csp.ilimit = rb::local_vector(lc, "DRIVE_ILIMIT", n, 0.05);
    c.csp.ulimit = c.bus.torque_limit;
    c.heartbeat_ns = seconds_to_ns(lc, "DRIVE_HEARTBEAT", 0.1);
    c.rpdo_timeout_ns = seconds_to_ns(lc, "DRIVE_RPDO_TIMEOUT", 0.1);
    c.tpdo1_event_ns = seconds_to_ns(lc, "DRIVE_EVENT_TIMER", 0.1);
    c.max_step = lc.number("DRIVE_STEP", 0.00025);
    if (!(c.max_step >= 1e-6 && c.max_step <= 0.01))
        rb::config_error(lc, "LOCAL DRIVE_STEP must be 1e-6..0.01 seconds");
    if (c.heartbeat_ns == 0) rb::config_error(lc, "LOCAL DRIVE_HEARTBEAT must be more than 0");
    return c;
}

DriveSim::DriveSim(DriveConfig config) : cfg_(std::move(config)), sim_(cfg_.model) {
    const std::size_t n = cfg_.model.ndof();
    const auto en = static_cast<Eigen::Index>(n);
    if (cfg_.bus.nodes.size() != n || cfg_.q0.size() != en || cfg_.bus.counts_per_rev.size() != en ||
        cfg_.bus.rated_torque.size() != en || cfg_.bus.torque_limit.size() != en || cfg_.csp.kp.size() != en ||
        cfg_.csp.ki.size() != en || cfg_.csp.kd.size() != en || cfg_.csp.ilimit.size() != en)
        throw std::invalid_argument("DriveSim: every per-joint parameter needs " + std::to_string(n) +
                                    " values (the robot's joints)");
    drives_.resize(n);
    for (std::size_t j = 0; j < n; ++j) drives_[j].node = cfg_.bus.nodes[j];
    tau_.setZero(en);
    integral_.setZero(en);
    demand_.setZero(en);
    in_cst_.assign(n, 0);
    // The speed limit's storage, sized once: a step allocates nothing.
    q_before_.setZero(en);
    qd_before_.setZero(en);
    qd_base_.setZero(en);
    tau_try_.setZero(en);
    over_.reserve(n);
    response_.setZero(en, en);
    want_.setZero(en);
    sim_.reset(cfg_.q0, Eigen::VectorXd::Zero(en));
    last_good_q_ = cfg_.q0;
    for (std::size_t j = 0; j < n; ++j) sim_.set_locked(j, true);  // unpowered: brakes on
}

int DriveSim::joint_of(int node) const noexcept {
    for (std::size_t j = 0; j < drives_.size(); ++j)
        if (drives_[j].node == node) return static_cast<int>(j);
    return -1;
}

void DriveSim::power_on(std::int64_t now, Out& out) {
    now_ = now;
    powered_ = true;
    for (std::size_t j = 0; j < drives_.size(); ++j) {
        Drive& d = drives_[j];
        d = Drive{.node = d.node};
        nmt_command(d, j, NmtCommand::reset_node, now, out);
    }
}

void DriveSim::nmt_command(Drive& d, std::size_t joint, NmtCommand c, std::int64_t now, Out& out) {
    switch (c) {
    case NmtCommand::start:
        if (d.nmt == NmtState::operational) return;
        d.nmt = NmtState::operational;
        d.last_rpdo1 = now;  // the RPDO deadline starts now, not at the last RPDO
        send_tpdo1(d, now, out, false);
        return;
    case NmtCommand::stop: d.nmt = NmtState::stopped; return;
    case NmtCommand::enter_preoperational: d.nmt = NmtState::preoperational; return;
    case NmtCommand::reset_node:
        // Application reset: the drive powers down its stage (brake) and forgets
        // its mode and error, then communication restarts as at power-on.
        d.state = DriveState::switch_on_disabled;  // not-ready passes at once: no self-test here
        d.error = kErrNone;
        d.mode = kModeNone;
        d.controlword = 0;
        d.pending_torque = d.torque_target = 0;
        d.pending_position_valid = false;
        d.max_speed = d.torque_slope = 0;  // application parameters back to their power-on values
        d.max_torque = 0;
        update_brake(joint);
        [[fallthrough]];
    case NmtCommand::reset_communication: {
        Frame boot{.id = cob_id(kHeartbeat, d.node), .len = 1, .data = {}};
        boot.data[0] = static_cast<std::uint8_t>(NmtState::boot_up);
        out.push_back(boot);
        d.nmt = NmtState::preoperational;
        d.next_heartbeat = now + cfg_.heartbeat_ns;
        d.sent_statusword = 0xFFFF;
        d.sent_mode = -1;
        d.sent_error = 0xFFFF;
        return;
    }
    }
}

void DriveSim::update_brake(std::size_t joint) {
    const bool locked = !producing_torque(drives_[joint]);
    if (locked != sim_.locked(joint)) {
        sim_.set_locked(joint, locked);
        integral_[static_cast<Eigen::Index>(joint)] = 0;
    }
}

void DriveSim::set_state(Drive& d, std::size_t joint, DriveState s, std::int64_t now, Out& out) {
    if (s == d.state) return;
    const DriveState before = d.state;
    d.state = s;
    if (before == DriveState::fault && s == DriveState::switch_on_disabled) d.error = kErrNone;
    if (s == DriveState::operation_enabled) {
        // Enabled from rest: no torque until the first SYNC applies a target,
        // and CSP holds where the joint is, so enabling never makes a jump.
        d.torque_target = 0;
        const auto j = static_cast<Eigen::Index>(joint);
        d.position_target = sim_.q()[j];
        d.velocity_offset = 0;
        d.pending_position_valid = false;
        d.last_rpdo1 = now;
    }
    update_brake(joint);
    send_tpdo1(d, now, out, true);
}

void DriveSim::fault(Drive& d, std::size_t joint, std::uint16_t code, std::int64_t now, Out& out) {
    if (d.state == DriveState::fault) return;
    d.error = code;
    set_state(d, joint, DriveState::fault, now, out);
}

void DriveSim::send_tpdo1(Drive& d, std::int64_t now, Out& out, bool only_if_changed) {
    if (d.nmt != NmtState::operational) return;
    const std::uint16_t sw = encode_statusword(d.state);
    if (only_if_changed && sw == d.sent_statusword && d.mode == d.sent_mode && d.error == d.sent_error) return;
    Frame f{.id = cob_id(kTpdo1, d.node), .len = 6, .data = {}};
    put_u16(f, 0, sw);
    put_u16(f, 2, static_cast<std::uint16_t>(d.mode));
    put_u16(f, 4, d.error);
    out.push_back(f);
    d.sent_statusword = sw;
    d.sent_mode = d.mode;
    d.sent_error = d.error;
    d.next_tpdo1 = now + cfg_.tpdo1_event_ns;
}

void DriveSim::send_tpdo2(std::size_t joint, Out& out) {
    const Drive& d = drives_[joint];
    const auto j = static_cast<Eigen::Index>(joint);
    const double cpr = cfg_.bus.counts_per_rev[j];
    Frame f{.id = cob_id(kTpdo2, d.node), .len = 8, .data = {}};
    put_u32(f, 0, static_cast<std::uint32_t>(to_counts(sim_.q()[j], cpr)));
    put_u32(f, 4, static_cast<std::uint32_t>(to_counts(sim_.qd()[j], cpr)));
    out.push_back(f);
}

bool DriveSim::advance(std::int64_t now) {
    // Frames come in bursts (a master's RPDOs, then its SYNC): integrating
    // each microsecond gap would cost a dynamics step per frame. Less than
    // one step waits for the next event; the motion it leaves out is at most
    // one step's.
    if (now - now_ < static_cast<std::int64_t>(cfg_.max_step * 1e9)) return true;
    // A simulator stalled for a long time (a debugger, a suspended process)
    // resumes rather than integrating the whole gap.
    const double dt = std::min(1.0, static_cast<double>(now - now_) * 1e-9);
    now_ = now;
    const int steps = std::max(1, static_cast<int>(std::ceil(dt / cfg_.max_step)));
    const double h = dt / steps;
    for (int s = 0; s < steps; ++s)
        if (!step_once(h)) return false;
    last_good_q_ = sim_.q();
    return true;
}

double DriveSim::max_speed(std::size_t joint) const noexcept {
    const std::uint32_t v = drives_[joint].max_speed;
    return v ? from_counts(static_cast<std::int32_t>(v), cfg_.bus.counts_per_rev[static_cast<Eigen::Index>(joint)])
             : std::numeric_limits<double>::infinity();
}

double DriveSim::torque_slope(std::size_t joint) const noexcept {
    const std::uint32_t s = drives_[joint].torque_slope;
    return s ? s * cfg_.bus.rated_torque[static_cast<Eigen::Index>(joint)] / 1000.0
             : std::numeric_limits<double>::infinity();
}

double DriveSim::torque_limit(std::size_t joint) const noexcept {
    const auto j = static_cast<Eigen::Index>(joint);
    const std::uint16_t m = drives_[joint].max_torque;
    const double tl = cfg_.bus.torque_limit[j];
    return m ? std::min(tl, permille_to_torque(static_cast<std::int16_t>(m), cfg_.bus.rated_torque[j])) : tl;
}

bool DriveSim::step_once(double h) {
    const auto n = static_cast<Eigen::Index>(drives_.size());
    for (Eigen::Index j = 0; j < n; ++j) {
        const auto js = static_cast<std::size_t>(j);
        const Drive& d = drives_[js];
        const double limit = torque_limit(js);
        double t = 0;
        const bool cst = producing_torque(d) && d.mode == kModeCst;
        if (cst) {
            // 0x6087: the demand moves toward the target at most slope x h,
            // from the torque applied when CST began (0 from the brake).
            if (!in_cst_[js]) demand_[j] = tau_[j];
            const double target = permille_to_torque(d.torque_target, cfg_.bus.rated_torque[j]);
            const double slope = torque_slope(js) * h;
            demand_[j] = std::isfinite(slope) ? std::clamp(target, demand_[j] - slope, demand_[j] + slope) : target;
            t = demand_[j];
        } else if (producing_torque(d)) {  // CSP: the drive's own position loop
            const double e = d.position_target - sim_.q()[j];
            const double il = cfg_.csp.ilimit[j];
            integral_[j] = std::clamp(integral_[j] + e * h, -il, il);
            t = cfg_.csp.kp[j] * e + cfg_.csp.ki[j] * integral_[j] +
                cfg_.csp.kd[j] * (d.velocity_offset - sim_.qd()[j]);
        }
        in_cst_[js] = cst;
        tau_[j] = std::clamp(t, -limit, limit);
    }
    bool any_speed_limit = false;
    for (std::size_t j = 0; j < drives_.size(); ++j)
        any_speed_limit = any_speed_limit || (drives_[j].max_speed && producing_torque(drives_[j]));
    if (!any_speed_limit) return sim_.step(tau_, h, 1);

    // 0x6080: the step is tried; a joint that would end it faster than its
    // limit gets the torque that ends it at the limit. The speed after a
    // semi-implicit Euler step is affine in the torque (qd + h M^-1 (tau -
    // bias), all at the step's start), so the joints concerned are solved
    // together from the response to a unit torque on each; a joint the
    // correction pushes over joins them, at most n rounds of one re-step.
    q_before_ = sim_.q();
    qd_before_ = sim_.qd();
    if (!sim_.step(tau_, h, 1)) return false;
    over_.clear();
    if (!find_over()) return true;
    ++speed_limited_;
    for (Eigen::Index round = 0; round < n; ++round) {
        if (!correct_over(h)) return false;
        if (!find_over()) break;
    }
    return true;
}

// Adds to over_ (capacity n, reserved) the joints producing torque faster than
// their 0x6080 limit; true when one was added.
bool DriveSim::find_over() noexcept {
    bool added = false;
    const auto n = static_cast<Eigen::Index>(drives_.size());
    for (Eigen::Index j = 0; j < n; ++j) {
        const Drive& d = drives_[static_cast<std::size_t>(j)];
        if (!d.max_speed || !producing_torque(d) || std::fabs(sim_.qd()[j]) <= max_speed(static_cast<std::size_t>(j)))
            continue;
        if (std::find(over_.begin(), over_.end(), j) == over_.end()) {
            over_.push_back(j);
            added = true;
        }
    }
    return added;
}

// One round: the response of the over_ joints' speeds to a unit torque on
// each, the torque change that puts them just inside their limits, the step
// again with it. False when the simulation diverged. The response is read off
// the step just taken: its speeds are qd + h M^-1 (tau - bias), and a change
// on a moving joint changes neither bias nor which joints friction holds, so
// column c is h M^-1 e_c, with no step taken.
bool DriveSim::correct_over(double h) {
    qd_base_ = sim_.qd();
    const auto m = static_cast<Eigen::Index>(over_.size());
    for (Eigen::Index c = 0; c < m; ++c) {
        tau_try_.setZero();
        tau_try_[over_[c]] = 1.0;
        sim_.mass_factor().solveInPlace(tau_try_);
        for (Eigen::Index r = 0; r < m; ++r) response_(r, c) = h * tau_try_[over_[r]];
    }
    for (Eigen::Index r = 0; r < m; ++r) {
        const Eigen::Index j = over_[r];
        // Aim just inside the limit, so rounding never leaves it above.
        want_[r] = std::copysign(max_speed(static_cast<std::size_t>(j)) * (1 - 1e-12), qd_base_[j]) - qd_base_[j];
    }
    if (solve_in_place(response_.topLeftCorner(m, m), want_.head(m))) {
        for (Eigen::Index r = 0; r < m; ++r) {
            const Eigen::Index j = over_[r];
            const double limit = torque_limit(static_cast<std::size_t>(j));
            if (std::isfinite(want_[r])) tau_[j] = std::clamp(tau_[j] + want_[r], -limit, limit);
        }
    }
    sim_.reset(q_before_, qd_before_);
    return sim_.step(tau_, h, 1);
}

// a x = b by Gaussian elimination with partial pivoting, in place (x in b):
// the few joints over their limit, with no allocation. False when a pivot
// vanishes (a joint whose speed no torque moves).
bool DriveSim::solve_in_place(Eigen::Ref<Eigen::MatrixXd> a, Eigen::Ref<Eigen::VectorXd> b) noexcept {
    const Eigen::Index m = a.rows();
    for (Eigen::Index k = 0; k < m; ++k) {
        Eigen::Index p = k;
        for (Eigen::Index r = k + 1; r < m; ++r)
            if (std::fabs(a(r, k)) > std::fabs(a(p, k))) p = r;
        if (!(std::fabs(a(p, k)) > 1e-300)) return false;
        a.row(k).swap(a.row(p));
        std::swap(b[k], b[p]);
        for (Eigen::Index r = k + 1; r < m; ++r) {
            const double f = a(r, k) / a(k, k);
            a.row(r).tail(m - k) -= f * a.row(k).tail(m - k);
            b[r] -= f * b[k];
        }
    }
    for (Eigen::Index k = m - 1; k >= 0; --k) {
        b[k] = (b[k] - a.row(k).tail(m - k - 1).dot(b.tail(m - k - 1))) / a(k, k);
    }
    return true;
}

void DriveSim::advance_or_fault(std::int64_t now, Out& out) {
    if (advance(now)) return;
    // Non-finite state: every drive faults and brakes where the arm last was.
    const auto n = static_cast<Eigen::Index>(drives_.size());
    sim_.reset(last_good_q_, Eigen::VectorXd::Zero(n));
    tau_.setZero();
    for (std::size_t j = 0; j < drives_.size(); ++j) fault(drives_[j], j, kErrSoftware, now, out);
}

void DriveSim::receive(const Frame& f, std::int64_t now, Out& out) {
    if (!powered_) return;
    advance_or_fault(now, out);
    if (f.id == kNmt) {
        if (f.len < 2) return;
        const auto c = static_cast<NmtCommand>(f.data[0]);
        const int node = f.data[1];
        for (std::size_t j = 0; j < drives_.size(); ++j)
            if (node == 0 || drives_[j].node == node) nmt_command(drives_[j], j, c, now, out);
        return;
    }
    if (f.id == kSync) {
        ++syncs_;
        for (std::size_t j = 0; j < drives_.size(); ++j) {
            Drive& d = drives_[j];
            if (d.nmt != NmtState::operational) continue;
            // Targets received since the last SYNC take effect now; the
            // feedback is latched now (cyclic synchronous modes).
            d.torque_target = d.pending_torque;
            if (d.pending_position_valid) {
                const auto jj = static_cast<Eigen::Index>(j);
                d.position_target = from_counts(d.pending_position, cfg_.bus.counts_per_rev[jj]);
                d.velocity_offset = from_counts(d.pending_velocity, cfg_.bus.counts_per_rev[jj]);
            }
            send_tpdo2(j, out);
        }
        return;
    }
    const std::uint32_t function = f.id & 0x780;
    const int j = joint_of(static_cast<int>(f.id & 0x7F));
    if (j >= 0 && function == sdo::kRequest) {
        sdo_request(drives_[static_cast<std::size_t>(j)], f, out);
        return;
    }
    if (j < 0 || (function != kRpdo1 && function != kRpdo2)) return;
    const auto joint = static_cast<std::size_t>(j);
    Drive& d = drives_[joint];
    if (d.nmt != NmtState::operational) {
        ++ignored_;  // PDOs are not processed outside operational
        return;
    }
    if (function == kRpdo1) {
        if (f.len < 6) {
            ++ignored_;
            return;
        }
        const std::uint16_t cw = get_u16(f, 0);
        const auto mode = static_cast<std::int16_t>(get_u16(f, 2));
        d.last_rpdo1 = now;
        d.pending_torque = static_cast<std::int16_t>(get_u16(f, 4));
        if (mode != d.mode) {
            if (mode != kModeNone && mode != kModeCsp && mode != kModeCst) {
                d.mode = mode;
                fault(d, joint, kErrParameter, now, out);
                return;
            }
            d.mode = mode;
            if (mode == kModeCsp) {  // hold where the joint is until a target arrives
                d.position_target = sim_.q()[static_cast<Eigen::Index>(joint)];
                d.velocity_offset = 0;
                d.pending_position_valid = false;
            }
            integral_[static_cast<Eigen::Index>(joint)] = 0;
        }
        set_state(d, joint, next_state(d.state, cw, d.controlword), now, out);
        d.controlword = cw;
        update_brake(joint);  // the mode alone may start or stop the torque
        send_tpdo1(d, now, out, true);
    } else {
        if (f.len < 8) {
            ++ignored_;
            return;
        }
        d.pending_position = static_cast<std::int32_t>(get_u32(f, 0));
        d.pending_velocity = static_cast<std::int32_t>(get_u32(f, 4));
        d.pending_position_valid = true;
    }
}

// The SDO server (canrobot/sdo.hpp): expedited downloads of the limits, in
// pre-operational and operational (CiA 301: not in stopped).
void DriveSim::sdo_request(Drive& d, const Frame& f, Out& out) {
    if (d.nmt != NmtState::preoperational && d.nmt != NmtState::operational) {
        ++ignored_;
        return;
    }
    const auto r = sdo::decode_request(f);
    if (!r) {
        ++ignored_;  // not an SDO frame (not 8 bytes)
        return;
    }
    auto abort = [&](std::uint32_t code) { out.push_back(sdo::abort_frame(d.node, r->index, r->subindex, code, true)); };
    if (r->kind == sdo::Request::Kind::abort) return;  // the master gave up: nothing outstanding here
    if (r->kind != sdo::Request::Kind::download) return abort(sdo::kAbortCommand);
    std::uint8_t size = 0;
    std::uint32_t max = 0;
    switch (r->index) {
    case sdo::kMaxMotorSpeed:
    case sdo::kTorqueSlope: size = 4; max = 0x7FFFFFFF; break;
    case sdo::kMaxTorque: size = 2; max = 0x7FFF; break;
    default: return abort(sdo::kAbortNoObject);
    }
    if (r->subindex != 0) return abort(sdo::kAbortNoSubindex);
    if (r->size != 0 && r->size != size) return abort(sdo::kAbortLength);
    // 0 would be a drive that cannot move: refused, as anything beyond the
    // objects' signed range (a velocity actual is an i32).
    if (r->value == 0 || r->value > max) return abort(sdo::kAbortRange);
    switch (r->index) {
    case sdo::kMaxMotorSpeed: d.max_speed = r->value; break;
    case sdo::kTorqueSlope: d.torque_slope = r->value; break;
    default: d.max_torque = static_cast<std::uint16_t>(r->value); break;
    }
    out.push_back(sdo::download_response(d.node, r->index, r->subindex));
}

void DriveSim::tick(std::int64_t now, Out& out) {
    if (!powered_) return;
    advance_or_fault(now, out);
    for (std::size_t j = 0; j < drives_.size(); ++j) {
        Drive& d = drives_[j];
        if (now >= d.next_heartbeat) {
            Frame hb{.id = cob_id(kHeartbeat, d.node), .len = 1, .data = {}};
            hb.data[0] = static_cast<std::uint8_t>(d.nmt);
            out.push_back(hb);
            d.next_heartbeat += cfg_.heartbeat_ns;
            if (d.next_heartbeat <= now) d.next_heartbeat = now + cfg_.heartbeat_ns;  // fell behind
        }
        if (d.nmt == NmtState::operational && cfg_.tpdo1_event_ns > 0 && now >= d.next_tpdo1)
            send_tpdo1(d, now, out, false);
        // RPDO deadline monitoring: a drive producing torque with no master
        // behind it stops (fault, brake) — the master crashed, or the bus broke.
        if (cfg_.rpdo_timeout_ns > 0 && d.state == DriveState::operation_enabled &&
            now - d.last_rpdo1 > cfg_.rpdo_timeout_ns)
            fault(d, j, kErrRpdoTimeout, now, out);
    }
}

std::int64_t DriveSim::next_timer() const noexcept {
    std::int64_t next = INT64_MAX;
    for (const Drive& d : drives_) {
        next = std::min(next, d.next_heartbeat);
        if (d.nmt == NmtState::operational && cfg_.tpdo1_event_ns > 0) next = std::min(next, d.next_tpdo1);
        if (cfg_.rpdo_timeout_ns > 0 && d.state == DriveState::operation_enabled)
            next = std::min(next, d.last_rpdo1 + cfg_.rpdo_timeout_ns + 1);
    }
    return next;
}

// --- on a SocketCAN interface ---------------------------------------------------------------

#if CHIMERA_HAVE_SOCKETCAN

namespace {

std::int64_t monotonic_ns() noexcept {
    timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec * 1'000'000'000LL + ts.tv_nsec;
}

// CLOCK_MONOTONIC - CLOCK_REALTIME now (the two differ by a constant between
// clock steps).
std::int64_t realtime_to_monotonic() noexcept {
    timespec rt;
    clock_gettime(CLOCK_REALTIME, &rt);
    return monotonic_ns() - (rt.tv_sec * 1'000'000'000LL + rt.tv_nsec);
}

class CanSocket {
public:
    explicit CanSocket(const std::string& interface) {
        fd_ = ::socket(PF_CAN, SOCK_RAW | SOCK_CLOEXEC | SOCK_NONBLOCK, CAN_RAW);
        if (fd_ < 0) {
            const int e = errno;
            if (e == EAFNOSUPPORT || e == EPROTONOSUPPORT || e == EINVAL)
                throw std::runtime_error("no AF_CAN support in this kernel (CAN_RAW socket: " +
                                         std::string(std::strerror(e)) + "; modules can and can-raw loaded?)");
            throw std::runtime_error("CAN socket: " + std::string(std::strerror(e)));
        }
        const unsigned ifindex = if_nametoindex(interface.c_str());
        if (ifindex == 0) {
            ::close(fd_);
            throw std::runtime_error("no CAN interface named " + interface);
        }
        // Room for a few seconds of a busy bus: a simulator that is not
        // scheduled for a while (no real-time priority) must not drop frames.
        const int bytes = 4 << 20;
        if (::setsockopt(fd_, SOL_SOCKET, SO_RCVBUFFORCE, &bytes, sizeof bytes) != 0)
            ::setsockopt(fd_, SOL_SOCKET, SO_RCVBUF, &bytes, sizeof bytes);  // up to rmem_max
        const int on = 1;
        ::setsockopt(fd_, SOL_SOCKET, SO_TIMESTAMPNS, &on, sizeof on);
        sockaddr_can addr{};
        addr.can_family = AF_CAN;
        addr.can_ifindex = static_cast<int>(ifindex);
        if (::bind(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
            const int e = errno;
            ::close(fd_);
            throw std::runtime_error("cannot bind a CAN socket to " + interface + ": " + std::strerror(e));
        }
    }
    ~CanSocket() { ::close(fd_); }
    CanSocket(const CanSocket&) = delete;
    CanSocket& operator=(const CanSocket&) = delete;

    int fd() const noexcept { return fd_; }

    void send(DriveSim::Out& out) {
        for (const Frame& f : out) {
            can_frame cf{};
            cf.can_id = f.id;
            cf.can_dlc = f.len;
            std::memcpy(cf.data, f.data, sizeof cf.data);
            for (int attempt = 0;; ++attempt) {
                if (::write(fd_, &cf, sizeof cf) == static_cast<ssize_t>(sizeof cf)) break;
                if (errno == EINTR) continue;
                if ((errno == EAGAIN || errno == ENOBUFS) && attempt < 10) {
                    pollfd p{fd_, POLLOUT, 0};
                    ::poll(&p, 1, 2);
                    continue;
                }
                ++dropped_;  // a full bus: the frame is lost, as on hardware
                break;
            }
        }
        out.clear();
    }

    /// One frame and the CLOCK_MONOTONIC time it reached the interface (the
    /// kernel's receive stamp), or false when none is waiting.
    bool receive(Frame& f, std::int64_t& arrived) {
        can_frame cf;
        alignas(cmsghdr) char control[CMSG_SPACE(sizeof(timespec))];
        for (;;) {
            iovec iov{&cf, sizeof cf};
            msghdr msg{};
            msg.msg_iov = &iov;
            msg.msg_iovlen = 1;
            msg.msg_control = control;
            msg.msg_controllen = sizeof control;
            const ssize_t r = ::recvmsg(fd_, &msg, MSG_DONTWAIT);
            if (r < 0 && errno == EINTR) continue;
            if (r != static_cast<ssize_t>(sizeof cf)) return false;
            if (cf.can_id & (CAN_ERR_FLAG | CAN_EFF_FLAG | CAN_RTR_FLAG)) continue;  // not ours
            f.id = cf.can_id & CAN_SFF_MASK;
            f.len = std::min<std::uint8_t>(cf.can_dlc, 8);
            std::memcpy(f.data, cf.data, sizeof f.data);
            arrived = monotonic_ns();
            for (cmsghdr* c = CMSG_FIRSTHDR(&msg); c; c = CMSG_NXTHDR(&msg, c))
                if (c->cmsg_level == SOL_SOCKET && c->cmsg_type == SO_TIMESTAMPNS) {
                    timespec ts;
                    std::memcpy(&ts, CMSG_DATA(c), sizeof ts);
                    // The stamp is CLOCK_REALTIME: moved onto the monotonic clock.
                    arrived = std::min<std::int64_t>(arrived, ts.tv_sec * 1'000'000'000LL + ts.tv_nsec + realtime_to_monotonic());
                }
            return true;
        }
    }

private:
    int fd_ = -1;
    std::uint64_t dropped_ = 0;
};

}  // namespace

void run_drive_bus(DriveSim& sim, const std::string& interface, const std::atomic<bool>& stop,
                   const std::function<void(const DriveSim&)>& each_second) {
    CanSocket bus(interface);
    DriveSim::Out out;
    out.reserve(4 * sim.ndof() + 8);
    sim.power_on(monotonic_ns(), out);
    bus.send(out);
    std::int64_t next_report = monotonic_ns() + 1'000'000'000;
    while (!stop.load(std::memory_order_relaxed)) {
        const std::int64_t now = monotonic_ns();
        // Wake for the next timer, and at least every 100 ms to see `stop`.
        const std::int64_t wait_ns = std::clamp<std::int64_t>(sim.next_timer() - now, 0, 100'000'000);
        pollfd p{bus.fd(), POLLIN, 0};
        if (::poll(&p, 1, static_cast<int>((wait_ns + 999'999) / 1'000'000)) < 0 && errno != EINTR)
            throw std::runtime_error("poll on " + interface + ": " + std::strerror(errno));
        // Each frame acts at the time it arrived, not when this process got
        // to it: a drive's firmware is never descheduled, so a simulator that
        // was must not let the arm run on under a held torque meanwhile. (Its
        // answers still leave late; the master sees that as missed feedback.)
        // Timers run in the same order, at the arrival of the first frame
        // after them: a heartbeat is due while a busy bus is read, and the
        // RPDO deadline is judged on the RPDOs that had arrived by then, never
        // while some wait unread (a simulator descheduled for 0.5 s faulted
        // its drives with RPDOs queued: issue #36).
        Frame f;
        std::int64_t arrived = 0;
        while (bus.receive(f, arrived)) {
            if (sim.next_timer() <= arrived) sim.tick(arrived, out);
            sim.receive(f, arrived, out);
            bus.send(out);
        }
        sim.tick(monotonic_ns(), out);
        bus.send(out);
        if (each_second && monotonic_ns() >= next_report) {
            each_second(sim);
            next_report += 1'000'000'000;
        }
    }
}

#else

void run_drive_bus(DriveSim&, const std::string& interface, const std::atomic<bool>&,
                   const std::function<void(const DriveSim&)>&) {
    throw std::runtime_error("cannot open " + interface +
                             ": this build of Chimera has no SocketCAN (linux/can/raw.h was not found "
                             "when it was configured: meson option socketcan)");
}

#endif

}  // namespace chimera::canrobot
