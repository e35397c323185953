// fig6_10 — the thesis's Figure 6.10 subsystem run by an autonomous master
// program (§4.2, §4.4.4): joint teleoperation of a simulated PUMA 560, the
// operator in ANOTHER process writing set-points through a TBUF (§5.6).
//
//   build/examples/fig6_10_teleop/fig6_10 [--seconds N] [--quiet] [--no-feed]
//
// The tasks (rmod files from modules/):
//   puma_pidg  the PUMA's PID servo with gravity feed-forward, arm simulated  RTPU robot
//   grav_comp  gravity compensation g(q_mez) -> T_GRAV                         RTPU ctrl
//   qrdiff     differentiator Q_REF -> Q^_REF                                  RTPU ctrl
//   jteleop    teleoperation input: operator feed (TBUF "operator") -> Q_REF   RTPU ctrl
// The operator: teleop_feed, started here as a child process sweeping the
// joints (unless --no-feed: then run `teleop_feed operator ...` yourself).
#include "fig6_10.hpp"

#include <chimera/ipc/segment.hpp>
#include <chimera/sbs.hpp>
#include <chimera/svar.hpp>

#include "teleop/feed.hpp"

#include <spawn.h>
#include <sys/wait.h>

#include <algorithm>
#include <array>
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

extern char** environ;

namespace {

using chimera::sbs::Control;
using chimera::sbs::Subsystem;
using chimera::sbs::TaskId;
using Clock = std::chrono::steady_clock;
constexpr double kRadToDeg = 180.0 / std::numbers::pi;

struct Options {
    double seconds = 5.0;
    bool quiet = false;
    bool feed = true;
};

Options parse(int argc, char** argv) {
    Options o;
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        if (a == "--quiet") {
            o.quiet = true;
        } else if (a == "--no-feed") {
            o.feed = false;
        } else if (a == "--seconds" && i + 1 < argc) {
            char* end = nullptr;
            o.seconds = std::strtod(argv[++i], &end);
            if (*end != '\0' || !(o.seconds >= 1) || o.seconds > 3600) {
                std::fprintf(stderr, "%s: --seconds takes a number from 1 to 3600, not '%s'\n", argv[0], argv[i]);
                std::exit(2);
            }
        } else {
            std::fprintf(stderr,
                         "usage: %s [--seconds N] [--quiet] [--no-feed]\n"
                         "  Runs the thesis's Figure 6.10 subsystem (joint teleoperation of a simulated PUMA 560)\n"
                         "  for N seconds (default 5) with teleop_feed as the operator in another process.\n"
                         "  --no-feed  start no operator: run `teleop_feed operator ...` yourself\n"
                         "  --quiet    leave out the tracking line printed every 0.5 s\n",
                         argv[0]);
            std::exit(a == "--help" || a == "-h" ? 0 : 2);
        }
    }
    return o;
}

// The operator process: teleop_feed NAME --seconds S (its default sweep).
pid_t start_feed(const std::string& tbuf, double seconds) {
    const std::string prog = fig6_10::feed_program(), secs = std::to_string(seconds);
    const char* argv[] = {prog.c_str(), tbuf.c_str(), "--seconds", secs.c_str(), nullptr};
    pid_t pid = -1;
    const int rc = ::posix_spawn(&pid, prog.c_str(), nullptr, nullptr, const_cast<char* const*>(argv), environ);
    if (rc != 0) throw chimera::sbs::Error("starting " + prog + ": " + std::strerror(rc));
    return pid;
}

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

    // The robot interface first: it produces the NDOF and DH in-consts (§3.5).
    const TaskId robot = sbs->spawn(fig6_10::rmod("puma_pidg"), "robot");
    const TaskId grav = sbs->spawn(fig6_10::rmod("grav_comp"), "ctrl");
    const TaskId diff = sbs->spawn(fig6_10::rmod("qrdiff"), "ctrl");
    const TaskId teleop = sbs->spawn(fig6_10::rmod("jteleop"), "ctrl");
    const std::string tbuf = sbs->get(teleop, "TBUF");
    auto r = sbs->reconfig({{grav, Control::on}, {robot, Control::on}, {diff, Control::on}, {teleop, Control::on}});
    if (!r) throw chimera::sbs::Error("turning the subsystem on: " + r.message);
    std::printf("spawned and turned on puma_pidg, grav_comp, qrdiff, jteleop (operator feed %s)\n",
                chimera::teleop::feed_segment(tbuf).c_str());

    pid_t feeder = -1;
    if (opt.feed) {
        feeder = start_feed(tbuf, std::max(0.5, opt.seconds - 1.0));
        std::printf("operator: teleop_feed %s (pid %d)\n\n", tbuf.c_str(), static_cast<int>(feeder));
    } else {
        std::printf("waiting for an operator: %s %s --seconds 10\n\n", fig6_10::feed_program().c_str(), tbuf.c_str());
    }
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
    if (feeder > 0) {
        int status = 0;
        ::waitpid(feeder, &status, 0);
        std::printf("operator process exited with %d\n",
                    WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status));
    }
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
