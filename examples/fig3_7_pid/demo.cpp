// demo — the thesis's Figure 3.7 subsystem run by an autonomous master program
// (§4.2, §4.4.4): PID joint control of a simulated PUMA 560, then a dynamic
// reconfiguration (§3.10) that swaps the PID controller for PID with gravity
// compensation in one reconfig call while the robot interface keeps cycling.
//
//   build/examples/demo [--seconds N] [--quiet] [--robot RMOD] [--name SUBSYSTEM]
//
// --robot names the robot interface's .rmod: puma_torque (default, the
// simulated arm in-process) or puma_can (the arm's drives on a CAN bus, with
// candrive simulating them: modules/canrobot/README.md) — the transparent
// simulation of §7.3, one module swapped.
//
// The tasks (all created at start-up, as §3.10 does for dynamic
// reconfiguration; rmod files from modules/ and this folder):
//   puma_torque  torque-mode robot interface, simulated PUMA 560   RTPU robot
//   jtraj        joint trajectory generator (quintic via points)   RTPU ctrl
//   jpid         PID joint position controller                     RTPU ctrl
//   grav_comp    gravity compensation g(q)                         RTPU ctrl
//   jpidg        PID + gravity feed-forward (OFF until the swap)   RTPU ctrl
// grav_comp is on from the start so that T_GRAV is current the instant jpidg
// takes over: it runs at 100 Hz and computes only in cycle().
#include "fig3_7.hpp"

#include <chimera/ipc/segment.hpp>
#include <chimera/sbs.hpp>
#include <chimera/svar.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <memory>
#include <numbers>
#include <string>
#include <thread>
#include <vector>

namespace {

using chimera::sbs::Control;
using chimera::sbs::Subsystem;
using chimera::sbs::TaskId;
using Clock = std::chrono::steady_clock;

constexpr double kRadToDeg = 180.0 / std::numbers::pi;

struct Options {
    double seconds = 6.0;  // half before the swap, half after
    bool quiet = false;
    std::string robot = "puma_torque";
    std::string name;  // empty: fig3_7.sbs's SUBSYSTEM
};

[[noreturn]] void usage(const char* prog, int code) {
    std::fprintf(code ? stderr : stdout,
                 "usage: %s [--seconds N] [--quiet] [--robot RMOD] [--name SUBSYSTEM]\n"
                 "  Runs the thesis's Figure 3.7 subsystem (PID joint control of a simulated PUMA 560)\n"
                 "  for N seconds (default 6): half on the PID controller, then a one-call\n"
                 "  reconfiguration to PID + gravity compensation, then the other half.\n"
                 "  --quiet  leave out the tracking-error line printed every 0.5 s\n"
                 "  --robot  the robot interface: puma_torque (default, simulated in-process) or\n"
                 "           puma_can (the drives on a CAN bus; see modules/canrobot/README.md)\n"
                 "  --name   the subsystem's name (default fig3_7, from fig3_7.sbs): names are machine-wide,\n"
                 "           so two runs at once need two names\n",
                 prog);
    std::exit(code);
}

Options parse(int argc, char** argv) {
    Options o;
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        if (a == "--quiet") {
            o.quiet = true;
        } else if (a == "--seconds" && i + 1 < argc) {
            char* end = nullptr;
            o.seconds = std::strtod(argv[++i], &end);
            if (*end != '\0' || !(o.seconds >= 0.5) || o.seconds > 3600) {
                std::fprintf(stderr, "%s: --seconds takes a number from 0.5 to 3600, not '%s'\n", argv[0], argv[i]);
                std::exit(2);
            }
        } else if (a == "--robot" && i + 1 < argc) {
            o.robot = argv[++i];
        } else if (a == "--name" && i + 1 < argc) {
            o.name = argv[++i];
        } else if (a == "--help" || a == "-h") {
            usage(argv[0], 0);
        } else {
            std::fprintf(stderr, "%s: unknown argument '%s'\n", argv[0], argv[i]);
            usage(argv[0], 2);
        }
    }
    return o;
}

// The master's view of the variables it watches: one local table, one
// consistent copy (one table lock) per look.
class Watch {
public:
    explicit Watch(const std::string& subsystem)
        : table_(chimera::svar::Table::attach(chimera::ipc::segment_name(subsystem, "svar"))),
          local_(table_, std::vector<std::string>{"Q_REF", "Q_MEZ", "T_REF"}),
          set_(local_.make_set({"Q_REF", "Q_MEZ", "T_REF"})),
          ndof_(table_.var("Q_REF").nelem()),
          q_ref_(local_.translate<double>("Q_REF")),
          q_mez_(local_.translate<double>("Q_MEZ")),
          t_ref_(local_.translate<double>("T_REF")) {}

    void look() {
        const auto s = local_.copy_from_global(set_);
        if (!chimera::svar::transferred(s))
            throw chimera::sbs::Error(std::string("reading the SVAR table: ") + chimera::svar::to_string(s));
    }
    /// max over joints of |q_ref - q_mez| (rad), and the joint (1-based).
    std::pair<double, std::size_t> tracking_error() const {
        double worst = 0;
        std::size_t joint = 1;
        for (std::size_t j = 0; j < ndof_; ++j) {
            const double e = std::fabs(q_ref_[j] - q_mez_[j]);
            if (e > worst) {
                worst = e;
                joint = j + 1;
            }
        }
        return {worst, joint};
    }
    std::vector<double> torques() const { return {t_ref_, t_ref_ + ndof_}; }
    std::vector<double> reference() const { return {q_ref_, q_ref_ + ndof_}; }

private:
    chimera::svar::Table table_;
    chimera::svar::LocalTable local_;
    chimera::svar::VarSet set_;
    std::size_t ndof_;
    const double* q_ref_;
    const double* q_mez_;
    const double* t_ref_;
};

std::string vec_text(const std::vector<double>& v) {
    std::string s = "[";
    char buf[32];
    for (std::size_t i = 0; i < v.size(); ++i) {
        std::snprintf(buf, sizeof buf, "%s%7.2f", i ? " " : "", v[i]);
        s += buf;
    }
    return s + "]";
}

void print_status(const Subsystem& sbs, const char* when) {
    std::printf("\nstatus %s\n", when);
    std::printf("%s\n", chimera::sbs::format_status_header().c_str());
    for (const auto& s : sbs.status_all()) std::printf("%s\n", chimera::sbs::format_status(s).c_str());
}

// The tracking-error bounds tests/examples/test_fig3_7 asserts (rad), which
// the demo checks its own run against: holding still once settled, and moving
// (the PID has no friction model, so every start and reversal of a joint
// costs until its integral term has built up the Coulomb friction).
constexpr double kHoldBound = 0.005, kMovingBound = 0.08;
// The first second after turn-on the arm sags under gravity until jpid's
// integral term has built up (test_fig3_7: "by 1 s it has settled").
constexpr double kSettleSeconds = 1.0;
// Q_REF unchanged for this long: the reference holds still (the trajectory's
// quintic segments move it at every 100 Hz cycle).
constexpr auto kStillFor = std::chrono::milliseconds(100);

// The worst tracking error of the run (rad), by what the arm was doing; seen:
// some look fell in that case.
struct Worst {
    double rad = 0;
    bool seen = false;
    void add(double e) {
        rad = std::max(rad, e);
        seen = true;
    }
};
struct Tracking {
    Worst settling, holding, moving_jpid, moving_jpidg;
    std::vector<double> last_ref;
    Clock::time_point ref_changed{};
};

// What the columns say (§4.4.1), and what a healthy run looks like; printed
// once, under the first status table.
void print_status_legend() {
    std::printf(
        "  S      task type: P periodic, Y synchronous, S sporadic, D deferrable server, B background\n"
        "  crit   criticality: the task's priority in its RTPU's scheduler (higher runs first)\n"
        "  cycle  cycles run since the task was turned on;  miss  deadlines missed (a job late or aborted, a release skipped)\n"
        "  refF   frequency asked for (Hz);  mezF  frequency measured (Hz)\n"
        "  minC avgC maxC  CPU time per cycle (us: every time is in microseconds);  avgU%%  share of the CPU\n"
        "  latP99 release lateness, 99th percentile (us): how late the task woke after its release\n"
        "  warn   warnings since on;  policy  the Linux scheduling the thread really has\n"
        "  healthy: state ON, miss 0 (or a handful at turn-on on a busy machine), mezF within 1%% of refF,\n"
        "  maxC and latP99 far below the period (1/refF; latP99 grows on a loaded or non-PREEMPT_RT kernel),\n"
        "  policy SCHED_FIFO on the RTPU's CPU (SCHED_OTHER means no real-time privilege: run as root),\n"
        "  tracking error below %.2f deg holding still (after the first %.0f s, while the arm settles under gravity)\n"
        "  and below %.1f deg moving (the PID has no friction model); the end of the run says whether this run kept them\n",
        kHoldBound * kRadToDeg, kSettleSeconds, kMovingBound * kRadToDeg);
}

// Runs for `seconds`, looking at the table every 10 ms; every 0.5 s a line
// with the tracking error now and the worst of the last half second.
void run_phase(Subsystem& sbs, Watch& watch, TaskId robot, const char* controller, double& clock_s,
               double seconds, bool quiet, Clock::time_point turned_on, Tracking& tracking) {
    const auto start = Clock::now();
    const auto end = start + std::chrono::duration<double>(seconds);
    auto next_line = start + std::chrono::milliseconds(500);
    double worst = 0;
    for (auto next = start + std::chrono::milliseconds(10); next <= end; next += std::chrono::milliseconds(10)) {
        std::this_thread::sleep_until(next);
        watch.look();
        const auto [err, joint] = watch.tracking_error();
        worst = std::max(worst, err);
        auto ref = watch.reference();
        if (ref != tracking.last_ref) {
            tracking.last_ref = std::move(ref);
            tracking.ref_changed = next;
        }
        if (next - turned_on < std::chrono::duration<double>(kSettleSeconds))
            tracking.settling.add(err);
        else if (next - tracking.ref_changed >= kStillFor)
            tracking.holding.add(err);
        else
            (std::strcmp(controller, "jpid") == 0 ? tracking.moving_jpid : tracking.moving_jpidg).add(err);
        if (next < next_line) continue;
        next_line += std::chrono::milliseconds(500);
        clock_s += 0.5;
        if (!quiet) {
            const auto st = sbs.status(robot);
            std::printf("t=%5.1f s  %-6s max|q_ref - q_mez| %6.3f deg (joint %zu), worst of last 0.5 s %6.3f deg"
                        "   robot cycle %6llu miss %llu\n",
                        clock_s, controller, err * kRadToDeg, joint, worst * kRadToDeg,
                        static_cast<unsigned long long>(st.cycles), static_cast<unsigned long long>(st.misses));
        }
        worst = 0;
    }
    std::this_thread::sleep_until(end);
    std::fflush(stdout);
}

// One line of the tracking summary: the worst against its bound, if any.
void print_worst(const char* what, const Worst& w, double bound) {
    if (!w.seen)
        std::printf("  %-24s (no look fell here in this run)\n", what);
    else if (bound <= 0)
        std::printf("  %-24s %6.3f deg (no bound)\n", what, w.rad * kRadToDeg);
    else
        std::printf("  %-24s %6.3f deg, bound %.2f deg: %s\n", what, w.rad * kRadToDeg, bound * kRadToDeg,
                    w.rad < bound ? "kept" : "EXCEEDED");
}

void print_tracking(const Tracking& t) {
    std::printf("\ntracking error, the run's worst max|q_ref - q_mez| (looked at every 10 ms):\n");
    char settling[64];
    std::snprintf(settling, sizeof settling, "first %.0f s, settling", kSettleSeconds);
    print_worst(settling, t.settling, 0);
    print_worst("holding still after it", t.holding, kHoldBound);
    print_worst("moving under jpid", t.moving_jpid, kMovingBound);
    print_worst("moving under jpidg", t.moving_jpidg, kMovingBound);
}

int run(const Options& opt) {
    std::vector<std::string> notes;
    auto sbs = Subsystem::init(fig3_7::load_sbs(&notes, opt.name));
    for (const auto& n : notes) std::printf("note: %s\n", n.c_str());
    fig3_7::add_module_dirs(*sbs);

    std::printf("Figure 3.7: PID joint control of a simulated PUMA 560 (subsystem %s)\n", sbs->name().c_str());
    // The robot interface first: it produces the NDOF and DH in-consts the others configure from (§3.5).
    const TaskId robot = sbs->spawn(fig3_7::rmod(opt.robot), "robot");
    const TaskId traj = sbs->spawn(fig3_7::rmod("jtraj"), "ctrl");
    const TaskId jpid = sbs->spawn(fig3_7::rmod("jpid"), "ctrl");
    const TaskId grav = sbs->spawn(fig3_7::rmod("grav_comp"), "ctrl");
    const TaskId jpidg = sbs->spawn(fig3_7::rmod("jpidg"), "ctrl");
    std::printf("spawned %s, jtraj, jpid, grav_comp, jpidg (all OFF)\n", opt.robot.c_str());

    const auto turned_on = Clock::now();
    auto r = sbs->reconfig({{robot, Control::on}, {grav, Control::on}, {traj, Control::on}, {jpid, Control::on}});
    if (!r) throw chimera::sbs::Error("turning the subsystem on: " + r.message);
    std::printf("reconfig: on %s, grav_comp, jtraj, jpid -- ok\n\n", opt.robot.c_str());

    // Detached before finish(): the table is removed by its last user.
    auto watch_owner = std::make_unique<Watch>(sbs->name());
    Watch& watch = *watch_owner;
    double clock_s = 0;
    Tracking tracking;
    const double first = opt.seconds / 2, second = opt.seconds - first;
    run_phase(*sbs, watch, robot, "jpid", clock_s, first, opt.quiet, turned_on, tracking);
    print_status(*sbs, "before the reconfiguration:");
    print_status_legend();

    // The dynamic reconfiguration of §3.10: off one controller, on the other, one call.
    watch.look();
    const std::vector<double> torque_before = watch.torques();
    const auto before = sbs->status(robot);
    const auto t0 = Clock::now();
    r = sbs->reconfig({{jpid, Control::off}, {jpidg, Control::on}});
    const auto t1 = Clock::now();
    if (!r) throw chimera::sbs::Error("reconfiguration: " + r.message);
    const auto just_after = sbs->status(robot);
    // The first torques jpidg produced: wait for its first cycle.
    while (sbs->status(jpidg).cycles < 1 && Clock::now() - t1 < std::chrono::seconds(1))
        std::this_thread::sleep_for(std::chrono::microseconds(200));
    watch.look();
    const std::vector<double> torque_after = watch.torques();
    // The robot interface over 100 ms from just before the call: its releases
    // (cycles run + releases missed) follow the clock, nothing restarted it.
    std::this_thread::sleep_until(t0 + std::chrono::milliseconds(100));
    const auto later = sbs->status(robot);
    const double window = std::chrono::duration<double>(Clock::now() - t0).count();
    double jump = 0;
    for (std::size_t j = 0; j < torque_before.size(); ++j)
        jump = std::max(jump, std::fabs(torque_after[j] - torque_before[j]));

    std::printf("\nreconfig: off jpid, on jpidg in ONE call -- ok, took %.2f ms\n",
                std::chrono::duration<double, std::milli>(t1 - t0).count());
    std::printf("  robot interface: cycle %llu before the call, %llu when it returned, %llu %.0f ms after it began\n"
                "  (%llu cycles at %.0f Hz; expected about %.0f), missed releases %llu -> %llu, state %s\n",
                static_cast<unsigned long long>(before.cycles), static_cast<unsigned long long>(just_after.cycles),
                static_cast<unsigned long long>(later.cycles), window * 1e3,
                static_cast<unsigned long long>(later.cycles - before.cycles), later.ref_freq, window * later.ref_freq,
                static_cast<unsigned long long>(before.misses), static_cast<unsigned long long>(later.misses),
                std::string(chimera::to_string(later.state)).c_str());
    const auto missed = later.misses - before.misses;
    if (missed == 0 && later.state == chimera::State::ON)
        std::printf("  so the robot interface lost no cycle in those %.0f ms\n", window * 1e3);
    else
        std::printf("  so the robot interface missed %llu release(s) in those %.0f ms, state %s\n",
                    static_cast<unsigned long long>(missed), window * 1e3,
                    std::string(chimera::to_string(later.state)).c_str());
    std::printf("  T_REF last from jpid   %s Nm\n", vec_text(torque_before).c_str());
    std::printf("  T_REF first from jpidg %s Nm   (largest change %.2f Nm)\n\n", vec_text(torque_after).c_str(),
                jump);
    std::fflush(stdout);
    clock_s += window;

    run_phase(*sbs, watch, robot, "jpidg", clock_s, second, opt.quiet, turned_on, tracking);
    print_status(*sbs, "after the reconfiguration:");
    print_tracking(tracking);
    watch_owner.reset();
    sbs->finish();
    std::printf("\nfinished: every task off and killed, shared segments removed\n");
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    const Options opt = parse(argc, argv);
    try {
        return run(opt);
    } catch (const std::exception& e) {
        std::fprintf(stderr, "demo: %s\n", e.what());
        return 1;
    }
}
