// fig6_10 — the thesis's Figure 6.10 subsystem run by an autonomous master
// program (§4.2, §4.4.4): joint teleoperation of a simulated PUMA 560 with a
// trackball on a serial line, as drawn.
//
//   build/examples/fig6_10_teleop/fig6_10 [--seconds N] [--quiet]
//
// The tasks (rmod files from modules/):
//   puma_pidg  the PUMA's PID servo with gravity feed-forward, arm simulated  RTPU robot
//   grav_comp  gravity compensation g(q_mez) -> T_GRAV                         RTPU ctrl
//   qrdiff     differentiator Q_REF -> Q^_REF                                  RTPU ctrl
//   jtball     the trackball on its serial line (SIO driver, §7.2) -> Q_REF    RTPU ctrl
// The trackball: trackball_sim, started here as a child process on a
// pseudo-terminal, pushing joints 1, 3 and 5 one after the other, out and back.
#include "fig6_10.hpp"

#include <chimera/ipc/segment.hpp>
#include <chimera/sbs.hpp>
#include <chimera/svar.hpp>

#include <unistd.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <filesystem>
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
    double seconds = 10.0;
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
                         "  Runs the thesis's Figure 6.10 subsystem (joint teleoperation of a simulated PUMA 560)\n"
                         "  for N seconds (default 10; the trackball's script takes 8.5) with a simulated trackball on a serial line.\n"
                         "  --quiet    leave out the tracking line printed every 0.5 s\n",
                         argv[0]);
            std::exit(a == "--help" || a == "-h" ? 0 : 2);
        }
    }
    return o;
}

// The operator's script (trackball_sim phases): joint 1 out and back, then
// joint 3, then joint 5, 1 s each way at 60 % deflection, ENABLE held; a pause
// with ENABLE released between them.
const std::vector<std::string> kOperator{
    "idle", "1",   "move", "1", "600", "0", "0", "0", "0",    "0", "move", "1", "-600", "0", "0", "0", "0", "0",
    "idle", "0.5", "move", "1", "0",   "0", "600", "0", "0",  "0", "move", "1", "0", "0", "-600", "0", "0", "0",
    "idle", "0.5", "move", "1", "0",   "0", "0", "0", "600",  "0", "move", "1", "0", "0", "0", "0", "-600", "0",
    "idle", "0.5"};

void print_status(const Subsystem& sbs, const char* when) {
    std::printf("\nstatus %s\n%s\n", when, chimera::sbs::format_status_header().c_str());
    for (const auto& s : sbs.status_all()) std::printf("%s\n", chimera::sbs::format_status(s).c_str());
}

int run(const Options& opt) {
    std::vector<std::string> notes;
    auto sbs = Subsystem::init(fig6_10::load_sbs(&notes));
    for (const auto& n : notes) std::printf("note: %s\n", n.c_str());
    fig6_10::add_module_dirs(*sbs);
    std::printf("Figure 6.10: joint teleoperation of a simulated PUMA 560 (subsystem %s)\n", sbs->name().c_str());

    // The trackball's line first: jtball opens it at init.
    const auto dir = std::filesystem::temp_directory_path() / ("fig6_10." + std::to_string(::getpid()));
    fig6_10::SimulatedTrackball trackball(dir, kOperator);
    std::printf("trackball: trackball_sim (pid %d) on %s/tball, database %s/trackball.iod\n",
                static_cast<int>(trackball.pid()), dir.c_str(), dir.c_str());
    // The robot interface first: it produces the NDOF and DH in-consts (§3.5).
    const TaskId robot = sbs->spawn(fig6_10::rmod("puma_pidg"), "robot");
    const TaskId grav = sbs->spawn(fig6_10::rmod("grav_comp"), "ctrl");
    const TaskId diff = sbs->spawn(fig6_10::rmod("qrdiff"), "ctrl");
    const TaskId jtball = sbs->spawn(trackball.rmod_path(), "ctrl");
    auto r = sbs->reconfig({{grav, Control::on}, {robot, Control::on}, {diff, Control::on}, {jtball, Control::on}});
    if (!r) throw chimera::sbs::Error("turning the subsystem on: " + r.message);
    trackball.start();
    std::printf("spawned and turned on puma_pidg, grav_comp, qrdiff, jtball; the operator starts\n\n");
    std::fflush(stdout);

    {
        auto table = chimera::svar::Table::attach(chimera::ipc::segment_name(sbs->name(), "svar"));
        chimera::svar::LocalTable local(table, std::vector<std::string>{"Q_REF", "Q_MEZ"});
        const auto set = local.make_set({"Q_REF", "Q_MEZ"});
        const double* q_ref = local.translate<double>("Q_REF");
        const double* q_mez = local.translate<double>("Q_MEZ");
        const std::size_t n = table.var("Q_REF").nelem();
        const auto start = Clock::now();
        double worst = 0;
        int line = 1;
        for (auto next = start; next < start + std::chrono::duration<double>(opt.seconds);
             next += std::chrono::milliseconds(10)) {
            std::this_thread::sleep_until(next);
            if (!chimera::svar::transferred(local.copy_from_global(set)))
                throw chimera::sbs::Error("reading the SVAR table failed");
            double err = 0;
            for (std::size_t j = 0; j < n; ++j) err = std::max(err, std::fabs(q_ref[j] - q_mez[j]));
            worst = std::max(worst, err);
            if (next - start < std::chrono::milliseconds(500) * line) continue;
            ++line;
            if (!opt.quiet) {
                std::printf("t=%4.1f s  q_ref [", std::chrono::duration<double>(next - start).count());
                for (std::size_t j = 0; j < n; ++j) std::printf("%s%6.3f", j ? " " : "", q_ref[j]);
                std::printf("] rad  max|q_ref - q_mez| %.3f deg, worst of last 0.5 s %.3f deg\n", err * kRadToDeg,
                            worst * kRadToDeg);
                std::fflush(stdout);
            }
            worst = 0;
        }
        table.detach();
    }
    std::printf("trackball process exited with %d\n", trackball.exit_status(true));
    print_status(*sbs, "at the end:");
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
        std::fprintf(stderr, "fig6_10: %s\n", e.what());
        return 1;
    }
}
