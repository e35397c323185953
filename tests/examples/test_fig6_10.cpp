// The Figure 6.10 subsystem (examples/fig6_10_teleop) driven through the master
// API, with the operator in ANOTHER process: teleop_feed is posix_spawn'ed and
// writes joint set-points into the teleop module's TBUF; the arm follows.
//
// One run (about 4.7 s) serves the tests: the subsystem is on for 1 s with no
// operator (the arm must hold its start pose under puma_pidg's PID + gravity
// compensation), then the feeder sweeps joints 1, 3 and 5 by
// +-0.3 rad with a 2 s period for 2.5 s, ending at base + amp, and exits.
#include "fig6_10.hpp"
#include "teleop/feed.hpp"

#include <chimera/ipc/segment.hpp>
#include <chimera/sbs.hpp>
#include <chimera/svar.hpp>
#include <chimera/tbuf.hpp>

#include <gtest/gtest.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <memory>
#include <regex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

extern char** environ;

namespace {

using chimera::sbs::Control;
using chimera::sbs::Subsystem;
using chimera::sbs::TaskId;
using Clock = std::chrono::steady_clock;
constexpr std::size_t kDof = 6;
using Joints = std::array<double, kDof>;

// Where the arm starts (fig6_10.svar INIT, the PUMA's qn) and the operator's sweep.
constexpr Joints kBase{0.0, 0.785398, 3.141593, 0.0, 0.785398, 0.0};
constexpr Joints kAmp{0.3, 0.0, -0.3, 0.0, 0.3, 0.0};
constexpr double kFeedStart = 1.0, kFeedSeconds = 2.5, kFeedPeriod = 2.0, kEnd = 4.7;

struct Sample {
    double t = 0;
    Joints q_ref{}, q_mez{};
};

double max_diff(const Joints& a, const Joints& b) {
    double d = 0;
    for (std::size_t j = 0; j < kDof; ++j) d = std::max(d, std::fabs(a[j] - b[j]));
    return d;
}

std::string unique_name(const char* what) { return "fig6_10_" + std::string(what) + std::to_string(::getpid()); }

// A copy of jteleop.rmod reading the feed `tbuf` (tests run side by side),
// with LOCAL lines replaced by key (`extra`: {"TIMEOUT", "0.3"}, ...).
std::filesystem::path teleop_rmod(const std::filesystem::path& dir, const std::string& tbuf,
                                  const std::vector<std::pair<std::string, std::string>>& extra = {}) {
    std::ifstream in(fig6_10::rmod("jteleop"));
    std::stringstream text;
    text << in.rdbuf();
    std::string rmod = std::regex_replace(text.str(), std::regex("\nTBUF +[^\n]*"), "\nTBUF      " + tbuf);
    for (const auto& [key, value] : extra)
        rmod = std::regex_replace(rmod, std::regex("\n" + key + " +[^\n]*"), "\n" + key + " " + value);
    std::filesystem::create_directories(dir);
    const auto path = dir / "jteleop.rmod";
    std::ofstream(path) << rmod;
    return path;
}

std::string joined(const Joints& v) {
    std::string s;
    for (double x : v) s += (s.empty() ? "" : " ") + std::to_string(x);
    return s;
}

pid_t spawn_feeder(const std::string& tbuf) {
    std::vector<std::string> args{fig6_10::feed_program(), tbuf, "--rate", "100", "--seconds",
                                  std::to_string(kFeedSeconds), "--period", std::to_string(kFeedPeriod), "--base"};
    for (double x : kBase) args.push_back(std::to_string(x));
    args.push_back("--amp");
    for (double x : kAmp) args.push_back(std::to_string(x));
    std::vector<char*> argv;
    for (auto& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    pid_t pid = -1;
    if (::posix_spawn(&pid, argv[0], nullptr, nullptr, argv.data(), environ) != 0) return -1;
    return pid;
}

class Fig610 : public ::testing::Test {
protected:
    struct Run {
        std::vector<Sample> samples;
        int feeder_status = -1;
        double feeder_exit_t = 0;  // when the master saw the feeder gone
        std::uint64_t teleop_cycles = 0, robot_misses = 0;
        std::string failure;
    };
    static std::unique_ptr<Run> run_;

    static void SetUpTestSuite() {
        run_ = std::make_unique<Run>();
        try {
            record(*run_);
        } catch (const std::exception& e) {
            run_->failure = e.what();
        }
    }
    static void TearDownTestSuite() { run_.reset(); }
    void SetUp() override { ASSERT_TRUE(run_->failure.empty()) << run_->failure; }

    static void record(Run& run) {
        const auto dir = std::filesystem::temp_directory_path() / unique_name("rmod");
        const std::string tbuf = unique_name("op");
        auto sbs = Subsystem::init(fig6_10::load_sbs(nullptr, unique_name("run")));
        fig6_10::add_module_dirs(*sbs);
        const TaskId robot = sbs->spawn(fig6_10::rmod("puma_pidg"), "robot");
        const TaskId grav = sbs->spawn(fig6_10::rmod("grav_comp"), "ctrl");
        const TaskId diff = sbs->spawn(fig6_10::rmod("qrdiff"), "ctrl");
        const TaskId teleop = sbs->spawn(teleop_rmod(dir, tbuf).string(), "ctrl");
        auto on = sbs->reconfig({{grav, Control::on}, {robot, Control::on}, {diff, Control::on}, {teleop, Control::on}});
        if (!on) throw chimera::sbs::Error("turning on: " + on.message);
        const auto t0 = Clock::now();

        auto table = chimera::svar::Table::attach(chimera::ipc::segment_name(sbs->name(), "svar"));
        {
            chimera::svar::LocalTable local(table, std::vector<std::string>{"Q_REF", "Q_MEZ"});
            const auto set = local.make_set({"Q_REF", "Q_MEZ"});
            const double* q_ref = local.translate<double>("Q_REF");
            const double* q_mez = local.translate<double>("Q_MEZ");
            pid_t feeder = -1;
            for (auto next = t0; next < t0 + std::chrono::duration<double>(kEnd); next += std::chrono::milliseconds(2)) {
                std::this_thread::sleep_until(next);
                const double t = std::chrono::duration<double>(Clock::now() - t0).count();
                if (feeder < 0 && t >= kFeedStart) {
                    feeder = spawn_feeder(tbuf);
                    if (feeder < 0) throw chimera::sbs::Error("could not start " + fig6_10::feed_program());
                }
                if (feeder > 0 && run.feeder_status < 0) {
                    int status = 0;
                    if (::waitpid(feeder, &status, WNOHANG) == feeder) {
                        run.feeder_status = WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
                        run.feeder_exit_t = t;
                    }
                }
                if (!chimera::svar::transferred(local.copy_from_global(set)))
                    throw chimera::sbs::Error("reading the SVAR table failed");
                Sample s;
                s.t = t;
                std::copy(q_ref, q_ref + kDof, s.q_ref.begin());
                std::copy(q_mez, q_mez + kDof, s.q_mez.begin());
                run.samples.push_back(s);
            }
            if (feeder > 0 && run.feeder_status < 0) {
                int status = 0;
                ::waitpid(feeder, &status, 0);
                run.feeder_status = WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
                run.feeder_exit_t = kEnd;
            }
            run.teleop_cycles = sbs->status(teleop).cycles;
            run.robot_misses = sbs->status(robot).misses;
        }
        table.detach();
        sbs->finish();
        std::filesystem::remove_all(dir);
    }

    template <typename F>
    static double worst(double from, double to, F f) {
        double w = 0;
        for (const auto& s : run_->samples)
            if (s.t >= from && s.t < to) w = std::max(w, f(s));
        return w;
    }
};
std::unique_ptr<Fig610::Run> Fig610::run_;

TEST_F(Fig610, ArmHoldsItsPoseUnderPidAndGravityCompensationWithoutAnOperator) {
    // No operator yet: the teleop module must not move Q_REF at all (exactly
    // the .svar's INIT), and the arm must stay there.
    const double q_ref_moved = worst(0.0, kFeedStart, [](const Sample& s) { return max_diff(s.q_ref, kBase); });
    EXPECT_EQ(q_ref_moved, 0.0);
    // Until T_GRAV's first values and the servo's integral have built up the
    // arm sags a little (measured: up to ~0.04 rad in the first 0.1 s); by
    // 0.5 s it is back. Bound 0.005 rad (0.29 deg) over [0.5 s, 1 s); measured
    // runs stay below 0.002 rad. Without gravity compensation joint 2 sags by
    // tenths of a radian (tests/modules ClosedLoop), so the bound has teeth.
    const double hold = worst(0.5, kFeedStart, [](const Sample& s) { return max_diff(s.q_mez, kBase); });
    std::printf("hold before the operator: worst |q_mez - q_start| %.5f rad\n", hold);
    EXPECT_LT(hold, 0.005);
}

TEST_F(Fig610, FeederInAnotherProcessDrivesTheArm) {
    const Run& r = *run_;
    EXPECT_EQ(r.feeder_status, 0) << "teleop_feed failed";
    EXPECT_GT(r.teleop_cycles, 300u);
    // The sweep went through both extremes of joints 1, 3 and 5 (base +- 0.3
    // rad): first in Q_REF (the operator's set-points reached the table),
    // then in the measured arm.
    for (std::size_t j : {0u, 2u, 4u}) {
        const double ref_hi = worst(0, kEnd, [j](const Sample& s) { return s.q_ref[j] - kBase[j]; });
        const double ref_lo = worst(0, kEnd, [j](const Sample& s) { return kBase[j] - s.q_ref[j]; });
        const double mez_hi = worst(0, kEnd, [j](const Sample& s) { return s.q_mez[j] - kBase[j]; });
        const double mez_lo = worst(0, kEnd, [j](const Sample& s) { return kBase[j] - s.q_mez[j]; });
        // 0.29: the sweep's +-0.3 rad less the step between two 100 Hz
        // set-points at the extremes (< 0.001 rad) and room for the feeder
        // being sampled a little off the peak.
        EXPECT_GT(ref_hi, 0.29) << "joint " << j + 1;
        EXPECT_GT(ref_lo, 0.29) << "joint " << j + 1;
        EXPECT_GT(mez_hi, 0.28) << "joint " << j + 1;
        EXPECT_GT(mez_lo, 0.28) << "joint " << j + 1;
    }
    // Joints 2, 4 and 6 were sent their start value all along.
    const double others = worst(0, kEnd, [](const Sample& s) {
        return std::max({std::fabs(s.q_ref[1] - kBase[1]), std::fabs(s.q_ref[3] - kBase[3]),
                         std::fabs(s.q_ref[5] - kBase[5])});
    });
    EXPECT_LT(others, 1e-6);
}

TEST_F(Fig610, ArmFollowsTheOperatorWithinAStatedError) {
    auto error = [](const Sample& s) { return max_diff(s.q_ref, s.q_mez); };
    // The sweep starts at full speed (0.3 * pi = 0.94 rad/s from rest): a
    // velocity step the servo takes ~0.2 s to absorb, the more so as Q^_REF
    // comes from a 40 Hz differentiator (qrdiff) and is up to 25 ms late.
    // Bound 0.06 rad over the first 0.2 s; measured runs reach ~0.045 rad.
    const double start = worst(kFeedStart, kFeedStart + 0.2, error);
    // Then the arm tracks within 0.04 rad (2.3 deg). puma_pidg has velocity
    // but no acceleration feed-forward, so at the sweep's extremes (3 rad/s^2)
    // the PID error carries the acceleration torque: measured runs peak at
    // ~0.028 rad there and fall below 0.01 rad at the zero crossings.
    const double sweep = worst(kFeedStart + 0.2, kFeedStart + kFeedSeconds, error);
    std::printf("tracking while the operator moves: worst |q_ref - q_mez| %.4f rad in the first 0.2 s, "
                "%.4f rad after\n", start, sweep);
    EXPECT_LT(start, 0.06);
    EXPECT_LT(sweep, 0.04);
}

TEST_F(Fig610, ArmStaysAtTheOperatorsLastSetPoint) {
    // The sweep ends at base + amp * sin(2 pi * 2.5 / 2) = base + amp; the
    // set-points are absolute, so after the operator has gone Q_REF is exactly
    // there and the arm settles onto it.
    const Run& r = *run_;
    ASSERT_LT(r.feeder_exit_t, kEnd - 0.5) << "the feeder ran late; no settled window";
    Joints last{};
    for (std::size_t j = 0; j < kDof; ++j) last[j] = kBase[j] + kAmp[j];
    const Sample& end = r.samples.back();
    std::printf("last set-point [%s], q_mez at the end max error %.5f rad\n", joined(last).c_str(),
                max_diff(end.q_mez, last));
    // 1e-6: the operator's values travel as doubles through the TBUF and the
    // table; only sin(2.5 pi) != 1 in the last bits and the argument's
    // rounding separate them.
    EXPECT_LT(max_diff(end.q_ref, last), 1e-6);
    // Settled, 0.5 s or more after the operator stopped (at zero velocity but
    // full deceleration): 0.005 rad; measured runs are below 0.002 rad.
    EXPECT_LT(max_diff(end.q_mez, last), 0.005);
}

TEST(Fig610Feed, ASilentOperatorStopsTheArmWhereItIsAndIsWarnedOf) {
    // Deadman: one far set-point, then silence. Q_REF moves towards it at
    // MAXSPEED; after TIMEOUT without a new item it stops where it is (not at
    // the set-point) with a warning; a new item moves it again.
    const auto dir = std::filesystem::temp_directory_path() / unique_name("deadman");
    const std::string tbuf = unique_name("quiet");
    auto sbs = Subsystem::init(fig6_10::load_sbs(nullptr, unique_name("deadman")));
    fig6_10::add_module_dirs(*sbs);
    const TaskId robot = sbs->spawn(fig6_10::rmod("puma_pidg"), "robot");
    const TaskId grav = sbs->spawn(fig6_10::rmod("grav_comp"), "ctrl");
    const TaskId diff = sbs->spawn(fig6_10::rmod("qrdiff"), "ctrl");
    const TaskId teleop =
        sbs->spawn(teleop_rmod(dir, tbuf, {{"MAXSPEED", "0.2"}, {"TIMEOUT", "0.3"}}).string(), "ctrl");
    const auto on = sbs->reconfig({{grav, Control::on}, {robot, Control::on}, {diff, Control::on}, {teleop, Control::on}});
    ASSERT_TRUE(on.ok) << on.message;
    auto feed = chimera::teleop::open_feed(tbuf, kDof);
    auto table = chimera::svar::Table::attach(chimera::ipc::segment_name(sbs->name(), "svar"));
    const auto q_ref0 = [&] {
        double q[kDof];
        EXPECT_EQ(table.read(table.index_of("Q_REF"), q), chimera::svar::Status::ok);
        return q[0];
    };
    Joints far = kBase;
    far[0] += 1.0;  // 5 s away at 0.2 rad/s
    ASSERT_NE(feed.write(far.data()), chimera::tbuf::kCorrupt);
    const auto t0 = Clock::now();
    std::this_thread::sleep_for(std::chrono::milliseconds(900));
    const double stopped = q_ref0();
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    const double later = q_ref0();
    const double elapsed = std::chrono::duration<double>(Clock::now() - t0).count();
    // It moved (~0.3 s x 0.2 rad/s), stopped short of the set-point, and stays.
    EXPECT_GT(stopped - kBase[0], 0.04);
    EXPECT_LT(stopped - kBase[0], 0.2 * elapsed);
    EXPECT_DOUBLE_EQ(later, stopped);
    const auto st = sbs->status(teleop);
    EXPECT_GE(st.warnings, 1u);
    EXPECT_NE(st.warning.find("operator feed silent"), std::string::npos) << st.warning;
    // The operator speaks again: it moves on.
    ASSERT_NE(feed.write(far.data()), chimera::tbuf::kCorrupt);
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    EXPECT_GT(q_ref0(), stopped + 0.01);
    table.detach();
    sbs->finish();
    feed.destroy();
    std::filesystem::remove_all(dir);
}

TEST(Fig610Feed, WrongJointCountIsRefusedByName) {
    // A feed made for a 2-joint robot: the 6-joint teleop module refuses it at
    // init, naming the segment, and leaves no task behind.
    const auto dir = std::filesystem::temp_directory_path() / unique_name("bad");
    const std::string tbuf = unique_name("two");
    auto feed = chimera::tbuf::Tbuf::create(chimera::ipc::segment_name("tbuf", tbuf), 2 * sizeof(double));
    auto sbs = Subsystem::init(fig6_10::load_sbs(nullptr, unique_name("bad")));
    fig6_10::add_module_dirs(*sbs);
    sbs->spawn(fig6_10::rmod("puma_pidg"), "robot");
    try {
        sbs->spawn(teleop_rmod(dir, tbuf).string(), "ctrl");
        ADD_FAILURE() << "teleop accepted a feed of 2 joints for a 6-joint robot";
    } catch (const chimera::sbs::Error& e) {
        std::printf("spawn refused: %s\n", e.what());
        const std::string what = e.what();
        EXPECT_NE(what.find("/chimera.tbuf." + tbuf), std::string::npos) << what;
        EXPECT_NE(what.find("expected 6 joints"), std::string::npos) << what;
    }
    EXPECT_EQ(sbs->status_all().size(), 1u);
    sbs->finish();
    feed.destroy();
    std::filesystem::remove_all(dir);
}

}  // namespace
