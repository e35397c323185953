// fig3_15 — the thesis's Figures 3.15/3.16 subsystem run by an autonomous
// master program (§3.10, §4.4.4): visual servoing of a simulated PUMA 560 — a
// simulated camera on its hand sees a target, the visual servo moves the
// desired tool pose until the target's image is where it is wanted — first
// with the inverse-kinematics controller (Figure 3.15), then, in ONE
// reconfiguration, with the damped-least-squares controller and its time
// integrator (Figure 3.16), while the robot interface keeps cycling. At the
// swap the target moves, so the second configuration servos too.
//
//   build/examples/fig3_15_servo/fig3_15 [--seconds N] [--quiet]
//
// The tasks (all created at start-up, §3.10; rmod files from modules/):
//   puma_position  position-mode robot interface, simulated PUMA 560  RTPU robot
//   fwdkin         forward kinematics and Jacobian -> X_MEZ, J_MEZ     RTPU ctrl
//   camera         X_MEZ -> FEATURES, the target's corners, 30 Hz     RTPU ctrl
//   vservo         FEATURES -> X_REF, FEAT_ERR (visual servoing)       RTPU ctrl
//   invkin         X_REF -> Q_REF (Newton, pseudo-inverse)             RTPU ctrl
//   dlsik          X_REF, Q_REF -> Q^_REF (damped least squares)       RTPU ctrl, OFF until the swap
//   qrinteg        Q^_REF -> Q_REF (time integrator)                   RTPU ctrl, OFF until the swap
// qrinteg reads its out-var Q_REF on `on` (§3.5), so it continues from the
// last value invkin wrote: the commanded joint positions do not jump.
#include "fig3_15.hpp"

#include <chimera/ipc/segment.hpp>
#include <chimera/sbs.hpp>
#include <chimera/svar.hpp>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <memory>
#include <string>
#include <thread>
#include <vector>

namespace {

using chimera::sbs::Control;
using chimera::sbs::Subsystem;
using chimera::sbs::TaskId;
using Clock = std::chrono::steady_clock;

struct Options {
    double seconds = 6.0;
    bool quiet = false;
};

Options parse(int argc, char** argv) {
    Options o;
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        if (a == "--quiet") {
            o.quiet = true;
        } else if (a == "--seconds" && i + 1 < argc) {
            char* end = nullptr;
            o.seconds = std::strtod(argv[++i], &end);
            if (*end != '\0' || !(o.seconds >= 1) || o.seconds > 3600) {
                std::fprintf(stderr, "%s: --seconds takes a number from 1 to 3600, not '%s'\n", argv[0], argv[i]);
                std::exit(2);
            }
        } else {
            std::fprintf(stderr,
                         "usage: %s [--seconds N] [--quiet]\n"
                         "  Runs the thesis's Figures 3.15/3.16 subsystem (visual servoing of a simulated\n"
                         "  PUMA 560) for N seconds (default 6): half on invkin, then one reconfiguration\n"
                         "  {off invkin, on dlsik, on qrinteg} and the target moves, then the other half.\n"
                         "  --quiet  leave out the tracking line printed every 0.5 s\n",
                         argv[0]);
            std::exit(a == "--help" || a == "-h" ? 0 : 2);
        }
    }
    return o;
}

// The master's view: one consistent copy (one table lock) per look.
class Watch {
public:
    explicit Watch(const std::string& subsystem)
        : table_(chimera::svar::Table::attach(chimera::ipc::segment_name(subsystem, "svar"))),
          local_(table_, std::vector<std::string>{"X_REF", "X_MEZ", "Q_REF", "FEATURES"}),
          set_(local_.make_set({"X_REF", "X_MEZ", "Q_REF", "FEATURES"})),
          x_ref_(local_.translate<double>("X_REF")),
          x_mez_(local_.translate<double>("X_MEZ")),
          q_ref_(local_.translate<double>("Q_REF")),
          features_(local_.translate<double>("FEATURES")) {}
    ~Watch() { table_.detach(); }

    void look() {
        if (!chimera::svar::transferred(local_.copy_from_global(set_)))
            throw chimera::sbs::Error("reading the SVAR table failed");
    }
    /// |x_ref - x_mez| over the position (m).
    double position_error() const { return std::hypot(x_ref_[0] - x_mez_[0], x_ref_[1] - x_mez_[1], x_ref_[2] - x_mez_[2]); }
    std::array<double, 6> q_ref() const { return {q_ref_[0], q_ref_[1], q_ref_[2], q_ref_[3], q_ref_[4], q_ref_[5]}; }
    /// RMS distance of the target's corners from where they are wanted (pixels).
    double feature_error() const { return fig3_15::feature_error(features_); }

private:
    chimera::svar::Table table_;
    chimera::svar::LocalTable local_;
    chimera::svar::VarSet set_;
    const double *x_ref_, *x_mez_, *q_ref_, *features_;
};

double max_diff(const std::array<double, 6>& a, const std::array<double, 6>& b) {
    double d = 0;
    for (std::size_t j = 0; j < 6; ++j) d = std::max(d, std::fabs(a[j] - b[j]));
    return d;
}

void run_phase(Watch& watch, const char* controller, double& clock_s, double seconds, bool quiet) {
    const auto start = Clock::now();
    double worst = 0;
    int line = 1;
    for (auto next = start; next < start + std::chrono::duration<double>(seconds); next += std::chrono::milliseconds(10)) {
        std::this_thread::sleep_until(next);
        watch.look();
        worst = std::max(worst, watch.position_error());
        if (next - start < std::chrono::milliseconds(500) * line) continue;
        ++line;
        if (!quiet)
            std::printf("t=%5.1f s  %-13s feature error %7.2f px  |x_ref - x_mez| %6.2f mm, worst of last 0.5 s %6.2f mm\n",
                        clock_s + std::chrono::duration<double>(next - start).count(), controller,
                        watch.feature_error(), watch.position_error() * 1e3, worst * 1e3);
        worst = 0;
    }
    clock_s += seconds;
    std::fflush(stdout);
}

void print_status(const Subsystem& sbs, const char* when) {
    std::printf("\nstatus %s\n%s\n", when, chimera::sbs::format_status_header().c_str());
    for (const auto& s : sbs.status_all()) std::printf("%s\n", chimera::sbs::format_status(s).c_str());
}

int run(const Options& opt) {
    std::vector<std::string> notes;
    auto sbs = Subsystem::init(fig3_15::load_sbs(&notes));
    for (const auto& n : notes) std::printf("note: %s\n", n.c_str());
    fig3_15::add_module_dirs(*sbs);
    std::printf("Figures 3.15/3.16: visual servoing of a simulated PUMA 560 (subsystem %s)\n", sbs->name().c_str());

    const TaskId robot = sbs->spawn(fig3_15::rmod("puma_position"), "robot");
    const TaskId fwd = sbs->spawn(fig3_15::rmod("fwdkin"), "ctrl");
    const TaskId camera = sbs->spawn(fig3_15::rmod("camera"), "ctrl");
    const TaskId servo = sbs->spawn(fig3_15::rmod("vservo"), "ctrl");
    const TaskId ik = sbs->spawn(fig3_15::rmod("invkin"), "ctrl");
    const TaskId dls = sbs->spawn(fig3_15::rmod("dlsik"), "ctrl");
    const TaskId integ = sbs->spawn(fig3_15::rmod("qrinteg"), "ctrl");
    std::printf("spawned puma_position, fwdkin, camera, vservo, invkin, dlsik, qrinteg (all OFF)\n");
    auto r = sbs->reconfig(
        {{robot, Control::on}, {fwd, Control::on}, {camera, Control::on}, {ik, Control::on}, {servo, Control::on}});
    if (!r) throw chimera::sbs::Error("turning the subsystem on: " + r.message);
    std::printf("reconfig: on puma_position, fwdkin, camera, invkin, vservo -- ok (Figure 3.15)\n\n");

    auto watch = std::make_unique<Watch>(sbs->name());
    double clock_s = 0;
    const double first = opt.seconds / 2;
    run_phase(*watch, "invkin", clock_s, first, opt.quiet);
    print_status(*sbs, "before the reconfiguration (Figure 3.15):");

    watch->look();
    const auto q_before = watch->q_ref();
    const auto before = sbs->status(robot);
    const auto t0 = Clock::now();
    r = sbs->reconfig({{ik, Control::off}, {dls, Control::on}, {integ, Control::on}});
    const auto t1 = Clock::now();
    if (!r) throw chimera::sbs::Error("reconfiguration: " + r.message);
    while (sbs->status(integ).cycles < 1 && Clock::now() - t1 < std::chrono::seconds(1))
        std::this_thread::sleep_for(std::chrono::microseconds(200));
    watch->look();
    const auto q_after = watch->q_ref();
    std::this_thread::sleep_until(t0 + std::chrono::milliseconds(100));
    const auto later = sbs->status(robot);
    const double window = std::chrono::duration<double>(Clock::now() - t0).count();
    std::printf("\nreconfig: off invkin, on dlsik, on qrinteg in ONE call -- ok, took %.2f ms (Figure 3.16)\n",
                std::chrono::duration<double, std::milli>(t1 - t0).count());
    std::printf("  robot interface: %llu cycles in the %.0f ms from the call (expected about %.0f), "
                "missed releases %llu -> %llu\n",
                static_cast<unsigned long long>(later.cycles - before.cycles), window * 1e3, window * later.ref_freq,
                static_cast<unsigned long long>(before.misses), static_cast<unsigned long long>(later.misses));
    std::printf("  Q_REF: largest joint change from invkin's last to qrinteg's first value %.4f rad\n",
                max_diff(q_before, q_after));
    sbs->set(camera, "TARGET", fig3_15::kMovedTarget);
    std::printf("the target moves: camera TARGET %s\n\n", fig3_15::kMovedTarget);
    clock_s += window;
    run_phase(*watch, "dlsik+qrinteg", clock_s, opt.seconds - first, opt.quiet);
    print_status(*sbs, "after the reconfiguration (Figure 3.16):");
    watch.reset();
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
        std::fprintf(stderr, "fig3_15: %s\n", e.what());
        return 1;
    }
}
