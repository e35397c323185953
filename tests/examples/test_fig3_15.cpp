// The Figures 3.15/3.16 subsystem (examples/fig3_15_servo) driven through the
// master API: visual servoing (a simulated hand camera at 30 Hz, vservo) on
// invkin, then ONE reconfiguration {off invkin, on dlsik, on qrinteg} (§3.10).
// qrinteg reads its out-var Q_REF on `on` (§3.5) and continues from invkin's
// last value, so the commanded joint positions do not jump and the robot
// interface loses no cycle. At the swap the target moves, so both
// configurations have a feature error to drive to zero.
//
// One run (about 6 s): invkin until 3 s, dlsik + qrinteg afterwards; the
// table is looked at every millisecond.
#include "fig3_15.hpp"

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
#include <filesystem>
#include <fstream>
#include <memory>
#include <regex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

namespace {

using chimera::sbs::Control;
using chimera::sbs::Subsystem;
using chimera::sbs::TaskId;
using Clock = std::chrono::steady_clock;
using Joints = std::array<double, 6>;

// Largest Q_REF change one controller cycle can make (both run at 200 Hz):
// invkin's LOCAL MAXSTEP (0.02 rad per cycle) and qrinteg integrating
// dlsik's Q^_REF, at most VMAX 2 rad/s * 5 ms = 0.01 rad per cycle.
constexpr double kMaxStep = 0.02, kControllerPeriod = 0.005;

constexpr double kSwapAt = 3.0, kEnd = 6.0;

struct Sample {
    double t = 0;
    Joints q_ref{};
    double x_err = 0;  // |x_ref - x_mez| position (m)
    double feature_err = 0;  // RMS of the corners' image distance from DESIRED (pixels)
    double servo_err = 0;    // the same, as vservo published it (FEAT_ERR)
    std::uint64_t robot_cycles = 0, robot_misses = 0;
    chimera::State robot_state = chimera::State::NOT_CREATED;
};

double max_diff(const Joints& a, const Joints& b) {
    double d = 0;
    for (std::size_t j = 0; j < 6; ++j) d = std::max(d, std::fabs(a[j] - b[j]));
    return d;
}

class Fig315 : public ::testing::Test {
protected:
    struct Run {
        std::vector<Sample> samples;
        chimera::sbs::ReconfigResult swap;
        Sample just_before, first_integ;
        double t_swap = 0;
        chimera::State invkin_after{}, dlsik_after{}, integ_after{};
        std::uint64_t invkin_cycles_at_swap = 0, invkin_cycles_end = 0, integ_cycles = 0, dlsik_cycles = 0;
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
        auto sbs = Subsystem::init(fig3_15::load_sbs(nullptr, "fig3_15_run" + std::to_string(::getpid())));
        fig3_15::add_module_dirs(*sbs);
        const TaskId robot = sbs->spawn(fig3_15::rmod("puma_position"), "robot");
        const TaskId fwd = sbs->spawn(fig3_15::rmod("fwdkin"), "ctrl");
        const TaskId camera = sbs->spawn(fig3_15::rmod("camera"), "ctrl");
        const TaskId servo = sbs->spawn(fig3_15::rmod("vservo"), "ctrl");
        const TaskId ik = sbs->spawn(fig3_15::rmod("invkin"), "ctrl");
        const TaskId dls = sbs->spawn(fig3_15::rmod("dlsik"), "ctrl");
        const TaskId integ = sbs->spawn(fig3_15::rmod("qrinteg"), "ctrl");
        auto on = sbs->reconfig(
            {{robot, Control::on}, {fwd, Control::on}, {camera, Control::on}, {ik, Control::on}, {servo, Control::on}});
        if (!on) throw chimera::sbs::Error("turning on: " + on.message);
        const auto t0 = Clock::now();
        auto table = chimera::svar::Table::attach(chimera::ipc::segment_name(sbs->name(), "svar"));
        {
            const std::vector<std::string> vars{"Q_REF", "X_REF", "X_MEZ", "FEATURES", "FEAT_ERR"};
            chimera::svar::LocalTable local(table, vars);
            const auto set = local.make_set(vars);
            const double* q_ref = local.translate<double>("Q_REF");
            const double* x_ref = local.translate<double>("X_REF");
            const double* x_mez = local.translate<double>("X_MEZ");
            const double* features = local.translate<double>("FEATURES");
            const double* feat_err = local.translate<double>("FEAT_ERR");
            auto look = [&] {
                Sample s;
                const auto st = sbs->status(robot);
                if (!chimera::svar::transferred(local.copy_from_global(set)))
                    throw chimera::sbs::Error("reading the SVAR table failed");
                s.t = std::chrono::duration<double>(Clock::now() - t0).count();
                std::copy(q_ref, q_ref + 6, s.q_ref.begin());
                s.x_err = std::hypot(x_ref[0] - x_mez[0], x_ref[1] - x_mez[1], x_ref[2] - x_mez[2]);
                s.feature_err = fig3_15::feature_error(features);
                s.servo_err = *feat_err;
                s.robot_cycles = st.cycles;
                s.robot_misses = st.misses;
                s.robot_state = st.state;
                return s;
            };
            auto sample_until = [&](double t_end) {
                for (auto next = Clock::now(); std::chrono::duration<double>(next - t0).count() < t_end;
                     next += std::chrono::milliseconds(1)) {
                    std::this_thread::sleep_until(next);
                    run.samples.push_back(look());
                }
            };
            sample_until(kSwapAt);
            run.just_before = look();
            run.samples.push_back(run.just_before);
            run.t_swap = run.just_before.t;
            run.swap = sbs->reconfig({{ik, Control::off}, {dls, Control::on}, {integ, Control::on}});
            run.invkin_cycles_at_swap = sbs->status(ik).cycles;
            sbs->set(camera, "TARGET", fig3_15::kMovedTarget);
            while (sbs->status(integ).cycles < 1 && Clock::now() - t0 < std::chrono::seconds(5))
                std::this_thread::sleep_for(std::chrono::microseconds(100));
            run.first_integ = look();
            run.samples.push_back(run.first_integ);
            sample_until(kEnd);
            run.invkin_after = sbs->status(ik).state;
            run.dlsik_after = sbs->status(dls).state;
            run.integ_after = sbs->status(integ).state;
            run.invkin_cycles_end = sbs->status(ik).cycles;
            run.integ_cycles = sbs->status(integ).cycles;
            run.dlsik_cycles = sbs->status(dls).cycles;
        }
        table.detach();
        sbs->finish();
    }
};
std::unique_ptr<Fig315::Run> Fig315::run_;

TEST_F(Fig315, OneReconfigurationSwapsTheControllers) {
    const Run& r = *run_;
    ASSERT_TRUE(r.swap.ok) << r.swap.message;
    EXPECT_EQ(r.swap.processed, 3u);
    EXPECT_EQ(r.invkin_after, chimera::State::OFF);
    EXPECT_EQ(r.dlsik_after, chimera::State::ON);
    EXPECT_EQ(r.integ_after, chimera::State::ON);
    // invkin stopped cycling at the swap; the new pair took over and cycled.
    EXPECT_EQ(r.invkin_cycles_end, r.invkin_cycles_at_swap);
    EXPECT_GT(r.integ_cycles, 200u);  // ~600 expected in 3 s at 200 Hz
    EXPECT_GT(r.dlsik_cycles, 200u);
}

TEST_F(Fig315, RobotInterfaceLosesNoCycle) {
    // The robot interface is not part of the reconfiguration: ON at every
    // look, its counter never restarts and keeps counting across the swap.
    const Run& r = *run_;
    std::uint64_t prev = 0;
    for (const auto& s : r.samples) {
        ASSERT_EQ(s.robot_state, chimera::State::ON) << "at t=" << s.t;
        ASSERT_GE(s.robot_cycles, prev) << "robot cycle counter went back at t=" << s.t;
        prev = s.robot_cycles;
    }
    EXPECT_GT(r.samples.back().robot_cycles, r.just_before.robot_cycles);
    // Releases missed around the swap are printed, not asserted: on this
    // shared, non-PREEMPT_RT machine a miss is the machine's, not the swap's.
    std::uint64_t misses_after = r.just_before.robot_misses;
    for (const auto& s : r.samples)
        if (s.t <= r.t_swap + 0.1) misses_after = s.robot_misses;
    std::printf("robot interface: cycle %llu before the swap, %llu at qrinteg's first cycle; missed releases "
                "%llu before, %llu 100 ms after\n",
                static_cast<unsigned long long>(r.just_before.robot_cycles),
                static_cast<unsigned long long>(r.first_integ.robot_cycles),
                static_cast<unsigned long long>(r.just_before.robot_misses),
                static_cast<unsigned long long>(misses_after));
}

TEST_F(Fig315, CommandedJointPositionsAreContinuousAcrossTheSwap) {
    const Run& r = *run_;
    // invkin's last Q_REF against qrinteg's first: at most one invkin cycle
    // that may have run between the look and the `off`, plus one qrinteg step:
    // 0.02 + 0.01 rad. A controller starting from anything but the table's
    // Q_REF (zero, its INIT, a stale copy) would jump by tenths of a radian
    // or more: Q_REF holds values up to 3.1 rad.
    const double jump = max_diff(r.first_integ.q_ref, r.just_before.q_ref);
    std::printf("Q_REF change from invkin's last look to qrinteg's first cycle: %.5f rad (%.2f ms apart)\n", jump,
                (r.first_integ.t - r.just_before.t) * 1e3);
    EXPECT_LE(jump, 0.03);
    // Between any two consecutive looks in the whole run, Q_REF moves by no
    // more than kMaxStep per controller cycle that can fit between them.
    double worst_ratio = 0;
    for (std::size_t i = 1; i < r.samples.size(); ++i) {
        const Sample& a = r.samples[i - 1];
        const Sample& b = r.samples[i];
        const double cycles = std::floor((b.t - a.t) / kControllerPeriod) + 1;
        const double d = max_diff(a.q_ref, b.q_ref);
        worst_ratio = std::max(worst_ratio, d / (kMaxStep * cycles));
        EXPECT_LE(d, kMaxStep * cycles + 1e-9) << "Q_REF jumped at t=" << b.t;
    }
    std::printf("largest Q_REF step between looks: %.2f of the per-cycle bound\n", worst_ratio);
    // And it did move after the swap (the bound is not vacuous).
    EXPECT_GT(max_diff(r.just_before.q_ref, r.samples.back().q_ref), 0.05);
}

TEST_F(Fig315, ToolFollowsTheDesiredPoseUnderBothControllers) {
    // Tool position error |x_ref - x_mez|, after fwdkin's first values (X_MEZ
    // is zero before) and the start transient. vservo moves X_REF at up to
    // 0.2 m/s (MAXSPEED); the robot interface's servo lags its Q_REF by some
    // 20-40 ms, and dlsik closes the Cartesian loop with GAIN 20/s (a 50 ms
    // time constant); bound 60 mm.
    double ik = 0, dls = 0;
    for (const auto& s : run_->samples) {
        if (s.t >= 0.5 && s.t < run_->t_swap) ik = std::max(ik, s.x_err);
        if (s.t >= run_->t_swap) dls = std::max(dls, s.x_err);
    }
    std::printf("worst tool position error: invkin %.1f mm, dlsik + qrinteg %.1f mm\n", ik * 1e3, dls * 1e3);
    EXPECT_LT(ik, 0.06);
    EXPECT_LT(dls, 0.06);
}

// Visual servoing converges in both configurations: the target's corners end
// where vservo wants them in the image. vservo's GAIN 1.5/s makes the error
// decay about as exp(-1.5 t) while the arm keeps up (the arm's servo lag and
// the camera's 33 ms frames are small against that 0.67 s time constant):
// from about a hundred pixels to one or two in 3 s.
TEST_F(Fig315, FeatureErrorConvergesUnderBothControllers) {
    const Run& r = *run_;
    // Feature error at a time (the last sample before it).
    const auto at = [&r](double t) {
        const Sample* last = &r.samples.front();
        for (const auto& s : r.samples)
            if (s.t <= t) last = &s;
        return *last;
    };
    // The error each configuration starts from: at 0.1 s (FEATURES are zero
    // until the camera's first frame, which comes after fwdkin's first X_MEZ),
    // and the largest in the first 0.2 s after the swap (the moved target is
    // seen within one frame of the `set`).
    const double start1 = at(0.1).feature_err;
    double start2 = 0;
    for (const auto& s : r.samples)
        if (s.t >= r.t_swap && s.t < r.t_swap + 0.2) start2 = std::max(start2, s.feature_err);
    const Sample mid1 = at(1.5), end1 = at(r.t_swap), mid2 = at(r.t_swap + 1.5), end2 = r.samples.back();
    std::printf("feature error (RMS over 4 corners, px): invkin %.1f -> %.2f (1.5 s) -> %.3f (3 s); "
                "dlsik + qrinteg %.1f -> %.2f (1.5 s) -> %.3f (3 s)\n",
                start1, mid1.feature_err, end1.feature_err, start2, mid2.feature_err, end2.feature_err);
    // A real error to remove in each (the scene's: ~100 px, then ~90 px).
    EXPECT_GT(start1, 30.0);
    EXPECT_GT(start2, 30.0);
    // Decaying: below a quarter after 1.5 s (exp(-2.25) = 0.11 expected;
    // measured 0.08-0.09), below 5 % and 4 px after 3 s (exp(-4.5) = 0.011
    // expected; measured 0.013-0.022: the arm's lag behind X_REF and its
    // joints' friction slow the last pixels).
    EXPECT_LT(mid1.feature_err, 0.25 * start1);
    EXPECT_LT(end1.feature_err, std::min(0.05 * start1, 4.0));
    EXPECT_LT(mid2.feature_err, 0.25 * start2);
    EXPECT_LT(end2.feature_err, std::min(0.05 * start2, 4.0));
    // vservo's FEAT_ERR is the same measure, of a frame at most one camera
    // period and one servo period old.
    EXPECT_NEAR(end2.servo_err, end2.feature_err, 0.5);
}

// Desired features that cannot fix the camera's 6 degrees of freedom (the four
// corners wanted on one line) are refused at spawn, by name.
TEST(Fig315Vservo, DesiredFeaturesOnALineAreRefused) {
    const auto dir = std::filesystem::temp_directory_path() / ("fig3_15_line" + std::to_string(::getpid()));
    std::filesystem::create_directories(dir);
    std::ifstream in(fig3_15::rmod("vservo"));
    std::stringstream text;
    text << in.rdbuf();
    const std::string rmod =
        std::regex_replace(text.str(), std::regex("\nDESIRED +[^\n]*"), "\nDESIRED 100 240 200 240 300 240 400 240");
    std::ofstream(dir / "vservo.rmod") << rmod;
    auto sbs = Subsystem::init(fig3_15::load_sbs(nullptr, "fig3_15_line" + std::to_string(::getpid())));
    fig3_15::add_module_dirs(*sbs);
    try {
        sbs->spawn((dir / "vservo.rmod").string(), "ctrl");
        ADD_FAILURE() << "vservo accepted four desired features on one line";
    } catch (const chimera::sbs::Error& e) {
        std::printf("spawn refused: %s\n", e.what());
        EXPECT_NE(std::string(e.what()).find("do not fix all 6 degrees of freedom"), std::string::npos) << e.what();
    }
    EXPECT_TRUE(sbs->status_all().empty());
    sbs->finish();
    std::filesystem::remove_all(dir);
}

}  // namespace
