// Figure 3.13 (examples/fig3_13_ctc): the computed-torque controller, PID
// acceleration (pidacc) and inverse dynamics (invdyn) combined in ONE task,
// tracks Figure 3.7's trajectory on the simulated PUMA 560 better than
// Figure 3.7's PID controller (jpid) does, and its intermediate variable x_u
// (Q^^_U) never reaches the global table (§3.8.1).
//
// Both subsystems run on real threads, one after the other, for the same time:
// the robot interface, jtraj (the same .rmod, the same via points) and the
// controller. The tracking error is measured as test_fig3_7.cpp measures it:
// the master looks at the global table every millisecond and takes
// max over joints |Q_REF - Q_MEZ|, here over the first moving segment (2 s
// from via point 1 to via point 2, peak 1.3 rad/s).
#include "fig3_13.hpp"

#include <chimera/ipc/segment.hpp>
#include <chimera/sbs.hpp>
#include <chimera/svar.hpp>

#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <memory>
#include <string>
#include <thread>
#include <vector>

namespace {

using chimera::sbs::Control;
using chimera::sbs::Subsystem;
using chimera::sbs::TaskId;
using Clock = std::chrono::steady_clock;
constexpr std::size_t kDof = 6;

// jtraj holds the start for 2 s (its approach to via point 1, where the arm
// starts), then moves to via point 2 in 2 s. The window leaves out the first
// 50 ms of the move, as test_fig3_7.cpp does.
constexpr double kMoveFrom = 2.05, kMoveTo = 4.0;
// Stated factors: computed torque's RMS error is below a third of the PID's, its
// worst below two thirds. Measured (2 cores, load ~6): RMS 0.0014 against
// 0.0072 rad (5.2x), worst 0.003-0.004 against 0.010-0.0125 rad (2.9-4.1x).
// Computed torque's error is mostly jtraj's: Q_REF changes every 10 ms (100 Hz,
// as in Figure 3.7), up to 0.013 rad at peak speed, which no controller behind
// it can follow; with jtraj at 500 Hz the measured factors were 7x and 11x.
constexpr double kRmsFactor = 3.0, kWorstFactor = 1.5;

struct Tracking {
    double worst = 0;       // max over the window of max_j |q_ref - q_mez| (rad)
    double rms = 0;         // RMS over the window of the same
    double ref_travel = 0;  // how far Q_REF moved in the window (rad): the window is not idle
    std::vector<double> q_u;  // Q^^_U in the global table at the end (empty: no such variable)
    std::uint64_t controller_cycles = 0;
    std::string controller;
};

std::string unique_name(const char* what) { return "fig3_13_" + std::string(what) + std::to_string(::getpid()); }

// Spawns `tasks` (each one task: one rmod, or several combined) on `file`,
// turns them on in one reconfig, and watches the table until kMoveTo.
Tracking track(const chimera::SbsFile& file, const std::vector<chimera::TaskLine>& tasks) {
    auto sbs = Subsystem::init(file);
    fig3_13::add_module_dirs(*sbs);
    std::vector<chimera::sbs::ReconfigItem> on;
    for (const auto& t : tasks) {
        std::vector<std::string> paths;
        for (const auto& r : t.rmods) paths.push_back(fig3_13::rmod(r));
        on.emplace_back(sbs->spawn_combined(paths, t.rtpu), Control::on);
    }
    const auto started = sbs->reconfig(on);
    if (!started) throw chimera::sbs::Error("turning on: " + started.message);
    const auto t0 = Clock::now();

    Tracking out;
    const TaskId controller = on.back().task;
    out.controller = sbs->status(controller).rmod;
    auto table = chimera::svar::Table::attach(chimera::ipc::segment_name(sbs->name(), "svar"));
    {
        chimera::svar::LocalTable local(table, std::vector<std::string>{"Q_REF", "Q_MEZ"});
        const auto set = local.make_set({"Q_REF", "Q_MEZ"});
        const double* q_ref = local.translate<double>("Q_REF");
        const double* q_mez = local.translate<double>("Q_MEZ");
        std::array<double, kDof> first_ref{};
        double sum_sq = 0;
        std::size_t n = 0;
        for (auto next = Clock::now();; next += std::chrono::milliseconds(1)) {
            std::this_thread::sleep_until(next);
            const double t = std::chrono::duration<double>(Clock::now() - t0).count();
            if (t >= kMoveTo) break;
            if (t < kMoveFrom) continue;
            if (!chimera::svar::transferred(local.copy_from_global(set)))
                throw chimera::sbs::Error("reading the SVAR table failed");
            double e = 0;
            for (std::size_t j = 0; j < kDof; ++j) {
                e = std::max(e, std::fabs(q_ref[j] - q_mez[j]));
                if (n == 0) first_ref[j] = q_ref[j];
                out.ref_travel = std::max(out.ref_travel, std::fabs(q_ref[j] - first_ref[j]));
            }
            out.worst = std::max(out.worst, e);
            sum_sq += e * e;
            ++n;
        }
        out.rms = n ? std::sqrt(sum_sq / static_cast<double>(n)) : 0;
    }
    if (const auto ix = table.find("Q^^_U")) {
        out.q_u.resize(table.var(*ix).nelem());
        if (!chimera::svar::transferred(table.read(*ix, out.q_u.data())))
            throw chimera::sbs::Error("reading Q^^_U failed");
    }
    out.controller_cycles = sbs->status(controller).cycles;
    table.detach();
    sbs->finish();
    return out;
}

class Fig313 : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        try {
            // Figure 3.13 as its .sbs draws it: the TASK lines, the combined one last.
            const auto ctc_file = fig3_13::load_sbs("fig3_13", unique_name("ctc"));
            ctc_ = std::make_unique<Tracking>(track(ctc_file, ctc_file.tasks));
            // Figure 3.7's PID on the same trajectory: its .sbs, its tasks (test_fig3_7.cpp).
            const auto pid_file =
                fig3_13::load_sbs(fig3_13::example_dir() + "/../fig3_7_pid/fig3_7.sbs", unique_name("pid"));
            std::vector<chimera::TaskLine> pid_tasks(3);
            pid_tasks[0].rmods = {"puma_torque"}, pid_tasks[0].rtpu = "robot";
            pid_tasks[1].rmods = {"jtraj"}, pid_tasks[1].rtpu = "ctrl";
            pid_tasks[2].rmods = {"jpid"}, pid_tasks[2].rtpu = "ctrl";
            pid_ = std::make_unique<Tracking>(track(pid_file, pid_tasks));
        } catch (const std::exception& e) {
            failure_ = e.what();
        }
    }
    static void TearDownTestSuite() { ctc_.reset(), pid_.reset(); }
    void SetUp() override { ASSERT_TRUE(failure_.empty()) << failure_; }

    static std::unique_ptr<Tracking> ctc_, pid_;
    static std::string failure_;
};
std::unique_ptr<Tracking> Fig313::ctc_, Fig313::pid_;
std::string Fig313::failure_;

TEST_F(Fig313, ComputedTorqueTracksBetterThanFigure37Pid) {
    std::printf("moving segment %.2f-%.2f s, max_j |q_ref - q_mez|: %s worst %.4f rad rms %.4f rad; "
                "%s worst %.4f rad rms %.4f rad; ratio worst %.1f rms %.1f\n",
                kMoveFrom, kMoveTo, pid_->controller.c_str(), pid_->worst, pid_->rms, ctc_->controller.c_str(),
                ctc_->worst, ctc_->rms, pid_->worst / ctc_->worst, pid_->rms / ctc_->rms);
    EXPECT_EQ(ctc_->controller, "ctc_pid+ctc_invdyn");
    EXPECT_EQ(pid_->controller, "jpid");
    // Both followed a moving reference (the bound is not vacuous).
    EXPECT_GT(ctc_->ref_travel, 0.5);
    EXPECT_GT(pid_->ref_travel, 0.5);
    EXPECT_GT(ctc_->controller_cycles, 0u);
    EXPECT_LT(ctc_->rms, pid_->rms / kRmsFactor);
    EXPECT_LT(ctc_->worst, pid_->worst / kWorstFactor);
}

TEST_F(Fig313, IntermediateVariableStaysInTheCombinedTask) {
    // pidacc wrote Q^^_U every cycle into the task's local table; invdyn read
    // it there. The global table still holds its initial zeros (§3.8.1).
    ASSERT_EQ(ctc_->q_u.size(), kDof);
    for (double v : ctc_->q_u) EXPECT_EQ(v, 0.0);
}

}  // namespace
