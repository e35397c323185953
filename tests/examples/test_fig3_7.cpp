// The Figure 3.7 subsystem (examples/fig3_7_pid) driven through the master API:
// PID joint control of the simulated PUMA 560 follows its trajectory, the
// one-call reconfiguration jpid -> jpidg (§3.10) loses no cycle and keeps the
// command continuous, a .rmod naming an unknown module is refused by name,
// and the demo program runs to completion.
//
// One run of the subsystem (about 3.3 s) serves the tracking and the
// reconfiguration tests: jtraj holds the start configuration for 2 s (the
// approach to its first via point, which is where the arm starts) and then
// moves; jpid controls until 2.5 s, jpidg afterwards.
#include "fig3_7.hpp"

#include <chimera/ipc/segment.hpp>
#include <chimera/sbs.hpp>
#include <chimera/svar.hpp>

#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
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

// One look at the table (one consistent copy under the table lock) plus the
// robot interface's counters.
struct Sample {
    double t = 0;  // seconds since the subsystem was turned on
    std::array<double, kDof> q_ref{}, q_mez{}, t_ref{};
    std::uint64_t robot_cycles = 0, robot_misses = 0;
    chimera::State robot_state = chimera::State::NOT_CREATED;
    bool after_swap = false;

    double tracking_error() const {
        double e = 0;
        for (std::size_t j = 0; j < kDof; ++j) e = std::max(e, std::fabs(q_ref[j] - q_mez[j]));
        return e;
    }
};

double max_diff(const std::array<double, kDof>& a, const std::array<double, kDof>& b) {
    double d = 0;
    for (std::size_t j = 0; j < kDof; ++j) d = std::max(d, std::fabs(a[j] - b[j]));
    return d;
}

std::string unique_name(const char* what) { return "fig3_7_" + std::string(what) + std::to_string(::getpid()); }

class Fig37 : public ::testing::Test {
protected:
    struct Run {
        std::vector<Sample> samples;
        chimera::sbs::ReconfigResult swap;
        Sample just_before, first_jpidg;  // around the reconfiguration
        chimera::State jpid_after = chimera::State::NOT_CREATED, jpidg_after = chimera::State::NOT_CREATED;
        std::uint64_t jpidg_cycles = 0;
        double swap_ms = 0;
        bool swap_late = false;  // it outlasted a cycle and raised the illegal-configuration flag
        std::string failure;  // set-up failure, reported by every test
    };
    static std::unique_ptr<Run> run_;

    // §3.10 promises no lost cycle for a swap done within a cycle (2 ms); one
    // that outlasts it (the master, SCHED_OTHER, held up by other work) raises
    // the illegal-configuration flag, the robot holds and the trajectory
    // restarts its segment, by design. Such a run was disturbed: it is said,
    // and recorded again, at most twice.
    static void SetUpTestSuite() {
        for (int attempt = 1; attempt <= 3; ++attempt) {
            run_ = std::make_unique<Run>();
            try {
                record(*run_);
            } catch (const std::exception& e) {
                run_->failure = e.what();
            }
            if (!run_->swap_late) return;
            std::printf("run %d disturbed: the swap took %.2f ms, longer than the 2 ms cycle (flag raised)%s\n",
                        attempt, run_->swap_ms, attempt < 3 ? "; recording again" : "");
        }
    }
    static void TearDownTestSuite() { run_.reset(); }

    void SetUp() override { ASSERT_TRUE(run_->failure.empty()) << run_->failure; }

    static void record(Run& run) {
        auto sbs = Subsystem::init(fig3_7::load_sbs(nullptr, unique_name("run")));
        fig3_7::add_module_dirs(*sbs);
        const TaskId robot = sbs->spawn(fig3_7::rmod("puma_torque"), "robot");
        const TaskId traj = sbs->spawn(fig3_7::rmod("jtraj"), "ctrl");
        const TaskId jpid = sbs->spawn(fig3_7::rmod("jpid"), "ctrl");
        const TaskId grav = sbs->spawn(fig3_7::rmod("grav_comp"), "ctrl");
        const TaskId jpidg = sbs->spawn(fig3_7::rmod("jpidg"), "ctrl");
        auto on = sbs->reconfig({{robot, Control::on}, {grav, Control::on}, {traj, Control::on}, {jpid, Control::on}});
        if (!on) throw chimera::sbs::Error("turning on: " + on.message);
        const auto t0 = Clock::now();

        auto table = chimera::svar::Table::attach(chimera::ipc::segment_name(sbs->name(), "svar"));
        {
            chimera::svar::LocalTable local(table, std::vector<std::string>{"Q_REF", "Q_MEZ", "T_REF"});
            const auto set = local.make_set({"Q_REF", "Q_MEZ", "T_REF"});
            const double* q_ref = local.translate<double>("Q_REF");
            const double* q_mez = local.translate<double>("Q_MEZ");
            const double* t_ref = local.translate<double>("T_REF");
            bool swapped = false;
            auto look = [&] {
                Sample s;
                const auto st = sbs->status(robot);
                if (!chimera::svar::transferred(local.copy_from_global(set)))
                    throw chimera::sbs::Error("reading the SVAR table failed");
                s.t = std::chrono::duration<double>(Clock::now() - t0).count();
                std::copy(q_ref, q_ref + kDof, s.q_ref.begin());
                std::copy(q_mez, q_mez + kDof, s.q_mez.begin());
                std::copy(t_ref, t_ref + kDof, s.t_ref.begin());
                s.robot_cycles = st.cycles;
                s.robot_misses = st.misses;
                s.robot_state = st.state;
                s.after_swap = swapped;
                return s;
            };
            auto sample_until = [&](double t_end) {
                for (auto next = Clock::now(); std::chrono::duration<double>(next - t0).count() < t_end;
                     next += std::chrono::milliseconds(1)) {
                    std::this_thread::sleep_until(next);
                    run.samples.push_back(look());
                }
            };
            sample_until(2.5);
            run.just_before = look();
            run.samples.push_back(run.just_before);
            const auto late_before = sbs->late_reconfigs();
            const auto swap_start = Clock::now();
            run.swap = sbs->reconfig({{jpid, Control::off}, {jpidg, Control::on}});
            run.swap_ms = std::chrono::duration<double, std::milli>(Clock::now() - swap_start).count();
            run.swap_late = sbs->late_reconfigs() != late_before;
            swapped = true;
            // The first torques jpidg produced.
            while (sbs->status(jpidg).cycles < 1 && Clock::now() - t0 < std::chrono::seconds(4))
                std::this_thread::sleep_for(std::chrono::microseconds(100));
            run.first_jpidg = look();
            run.samples.push_back(run.first_jpidg);
            sample_until(3.3);
            run.jpid_after = sbs->status(jpid).state;
            run.jpidg_after = sbs->status(jpidg).state;
            run.jpidg_cycles = sbs->status(jpidg).cycles;
        }
        table.detach();
        sbs->finish();
    }

    static double worst_error(double from, double to) {
        double w = 0;
        for (const auto& s : run_->samples)
            if (s.t >= from && s.t < to) w = std::max(w, s.tracking_error());
        return w;
    }
};
std::unique_ptr<Fig37::Run> Fig37::run_;

TEST_F(Fig37, ArmFollowsTheTrajectoryAfterSettling) {
    // The arm starts at rest where the trajectory starts, so the only early
    // error is the sag under gravity until jpid's integral term has built up
    // (it is about 1.5 deg at 0.2 s and decays); by 1 s it has settled.
    const double settled_hold = worst_error(1.0, 2.0);
    const double moving_jpid = worst_error(2.05, 2.5);
    const double moving_jpidg = worst_error(2.6, 3.3);
    std::printf("worst |q_ref - q_mez|: settled hold %.4f rad, moving under jpid %.4f rad, under jpidg %.4f rad\n",
                settled_hold, moving_jpid, moving_jpidg);
    // Stated bounds. Settled hold: 0.005 rad (0.29 deg). Measured runs show
    // at most 0.003 rad, at 1.0 s, falling to 0.0002 rad at 2 s; the margin
    // covers the simulated arm running up to ~0.2 s behind the wall clock when
    // its task misses releases on a loaded machine.
    EXPECT_LT(settled_hold, 0.005);
    // Moving (quintic segments of up to 1.4 rad in 2 s, peak 1.3 rad/s): 0.08
    // rad (4.6 deg). The simulated arm has the PUMA's Coulomb friction (24.7 N m
    // forward, 27.2 N m backward on joint 1), which a PID without a friction
    // model carries only once its integral has built it up, at every start and
    // reversal: tests/modules states 0.1 rad for PID + gravity at 1 kHz on such
    // a move. Measured runs: 0.043 (jpid) and 0.054 rad (jpidg); below 0.02 rad
    // before the arm had Coulomb friction.
    EXPECT_LT(moving_jpid, 0.08);
    EXPECT_LT(moving_jpidg, 0.08);
    // The trajectory did move in the window (the error bound is not vacuous).
    const auto& first_moving = *std::find_if(run_->samples.begin(), run_->samples.end(),
                                             [](const Sample& s) { return s.t >= 2.05; });
    EXPECT_GT(max_diff(first_moving.q_ref, run_->samples.back().q_ref), 0.1);
}

TEST_F(Fig37, ReconfigurationSwapsControllersWithNoLostCycle) {
    const Run& r = *run_;
    ASSERT_TRUE(r.swap.ok) << r.swap.message;
    ASSERT_FALSE(r.swap_late) << "three swaps in a row outlasted the 2 ms cycle (last " << r.swap_ms << " ms)";
    std::printf("the swap took %.2f ms\n", r.swap_ms);
    EXPECT_EQ(r.swap.processed, 2u);
    EXPECT_EQ(r.jpid_after, chimera::State::OFF);
    EXPECT_EQ(r.jpidg_after, chimera::State::ON);
    EXPECT_GT(r.jpidg_cycles, 0u);

    // The robot interface is untouched by the reconfiguration: ON at every
    // look, its cycle counter never restarts or goes back, and it keeps
    // counting after the swap.
    std::uint64_t prev = 0;
    for (const auto& s : r.samples) {
        ASSERT_EQ(s.robot_state, chimera::State::ON) << "at t=" << s.t;
        ASSERT_GE(s.robot_cycles, prev) << "robot cycle counter went back at t=" << s.t;
        prev = s.robot_cycles;
    }
    EXPECT_GT(r.samples.back().robot_cycles, r.just_before.robot_cycles);
    std::printf("robot interface: cycle %llu before the swap, %llu at jpidg's first cycle, %llu at the end; "
                "missed releases %llu -> %llu\n",
                static_cast<unsigned long long>(r.just_before.robot_cycles),
                static_cast<unsigned long long>(r.first_jpidg.robot_cycles),
                static_cast<unsigned long long>(r.samples.back().robot_cycles),
                static_cast<unsigned long long>(r.just_before.robot_misses),
                static_cast<unsigned long long>(r.samples.back().robot_misses));

    // Commanded torque across the handover: the last T_REF of jpid against the
    // first of jpidg. Both run the same gains; jpid carries gravity in its
    // integral, jpidg in the T_GRAV feed-forward, so the torque stays
    // continuous but for the Coulomb friction of the moving joints, which
    // jpid's integral carries and jpidg's starts without (up to 27 N m on joint
    // 1; measured changes 12-14 N m). Bound 20 N m: a handover that lost the
    // command (T_REF stale at zero) or the gravity term would jump by the
    // ~30 N m that joint 2 carries at this configuration, friction on top.
    const double torque_jump = max_diff(r.first_jpidg.t_ref, r.just_before.t_ref);
    std::printf("T_REF change across the swap %.3f N m (samples %.2f ms apart)\n", torque_jump,
                (r.first_jpidg.t - r.just_before.t) * 1e3);
    EXPECT_LT(torque_jump, 20.0);

    // Commanded and measured joint positions stay continuous through the swap:
    // between consecutive looks (about 1 ms apart) neither moves by more than
    // its speed allows. Q_REF: peak 1.3 rad/s, changed in steps every 10 ms;
    // Q_MEZ: the arm, below 2 rad/s. Bound |dq| <= v (dt + 10 ms) + 1e-6 rad.
    const double t_swap = r.just_before.t;
    for (std::size_t i = 1; i < r.samples.size(); ++i) {
        const Sample& a = r.samples[i - 1];
        const Sample& b = r.samples[i];
        if (b.t < t_swap - 0.05 || a.t > t_swap + 0.1) continue;
        const double dt = b.t - a.t;
        EXPECT_LE(max_diff(a.q_ref, b.q_ref), 1.4 * (dt + 0.010) + 1e-6) << "Q_REF jumped at t=" << b.t;
        EXPECT_LE(max_diff(a.q_mez, b.q_mez), 2.0 * (dt + 0.010) + 1e-6) << "Q_MEZ jumped at t=" << b.t;
    }
}

TEST(Fig37Spawn, UnknownModuleIsNamed) {
    const auto dir = std::filesystem::temp_directory_path() / unique_name("rmod");
    std::filesystem::create_directories(dir);
    const auto path = dir / "jfancy.rmod";
    {
        std::ofstream f(path);
        f << "# a controller whose module does not exist\n"
             "MODULE    no_such_controller\n"
             "DESC      controller that is not in the library\n"
             "INCONST   NDOF\n"
             "INVAR     Q_REF Q_MEZ\n"
             "OUTVAR    T_REF\n"
             "TASKTYPE  periodic\n"
             "FREQ      500\n"
             "EOF\n";
    }
    auto sbs = Subsystem::init(fig3_7::load_sbs(nullptr, unique_name("unknown")));
    fig3_7::add_module_dirs(*sbs);
    sbs->spawn(fig3_7::rmod("puma_torque"), "robot");
    try {
        sbs->spawn(path.string(), "ctrl");
        ADD_FAILURE() << "spawned a task whose module does not exist";
    } catch (const chimera::sbs::Error& e) {
        std::printf("spawn refused: %s\n", e.what());
        EXPECT_NE(std::string(e.what()).find("no_such_controller"), std::string::npos) << e.what();
    }
    // Nothing of it is left running: only the robot interface is alive.
    const auto all = sbs->status_all();
    ASSERT_EQ(all.size(), 1u);
    EXPECT_EQ(all[0].rmod, "puma_torque");
    sbs->finish();
    std::filesystem::remove_all(dir);
}

// Issue #16.2: `set` takes only the LOCAL keys a module declares, with values
// of the declared type and range, and only keys the module applies without a
// respawn; every refusal names the key and why, and LOCAL keeps what the
// module runs with.
TEST(Fig37Set, RefusesWhatTheModuleWouldIgnore) {
    auto sbs = Subsystem::init(fig3_7::load_sbs(nullptr, unique_name("set")));
    fig3_7::add_module_dirs(*sbs);
    const TaskId robot = sbs->spawn(fig3_7::rmod("puma_torque"), "robot");
    const TaskId jpid = sbs->spawn(fig3_7::rmod("jpid"), "ctrl");
    const auto modules_src = std::filesystem::path(fig3_7::rmod("jpid")).parent_path().parent_path();
    // qlog.rmod's output folder ($XDG_STATE_HOME/chimera/SUBSYSTEM): a temporary one, not the real home's.
    const auto state = std::filesystem::temp_directory_path() / unique_name("state");
    ::setenv("XDG_STATE_HOME", state.c_str(), 1);
    const TaskId qlog = sbs->spawn((modules_src / "logger" / "qlog.rmod").string(), "ctrl");
    const auto refusal = [&](TaskId id, const char* key, const char* value) {
        try {
            sbs->set(id, key, value);
        } catch (const chimera::sbs::Refused& e) {
            return std::string(e.what());
        }
        ADD_FAILURE() << "set " << key << " " << value << " was accepted";
        return std::string();
    };
    const auto has = [](const std::string& s, const char* part) { return s.find(part) != std::string::npos; };

    const std::string nokey = refusal(jpid, "NOKEY", "1");
    EXPECT_TRUE(has(nokey, "no LOCAL key NOKEY in module pid (it takes KP KI KD ILIMIT ULIMIT STALE SLEW)")) << nokey;
    const std::string banana = refusal(jpid, "KP", "banana");
    EXPECT_TRUE(has(banana, "LOCAL KP: 'banana' is not a number")) << banana;
    EXPECT_FALSE(has(banana, ":0:")) << banana;
    const std::string negative = refusal(jpid, "KD", "-5");
    EXPECT_TRUE(has(negative, "LOCAL KD: -5 is out of range [0, inf]")) << negative;
    EXPECT_EQ(sbs->get(jpid, "KP"), "400 800 400 40 40 20");  // unchanged by the refusals

    // A live key takes effect (pid rebuilds its gains in set()).
    sbs->set(jpid, "KP", "300 600 300 30 30 15");
    EXPECT_EQ(sbs->get(jpid, "KP"), "300 600 300 30 30 15");

    // Keys read only in init(): refused, not silently stored.
    const std::string file = refusal(qlog, "FILE", "q.csv");
    EXPECT_TRUE(has(file, "LOCAL FILE of module logger is read only at spawn")) << file;
    EXPECT_EQ(sbs->get(qlog, "FILE"), "qlog.csv");
    const std::string substeps = refusal(robot, "SUBSTEPS", "5");
    EXPECT_TRUE(has(substeps, "SUBSTEPS")) << substeps;
    EXPECT_EQ(sbs->get(robot, "SUBSTEPS"), "10");

    // A declared key absent from the .rmod: get answers the default it runs with.
    EXPECT_EQ(sbs->get(robot, "STABILITY"), "hold");
    EXPECT_EQ(sbs->get(qlog, "DECIMATE"), "1");
    sbs->finish();
    std::filesystem::remove_all(state);
}

TEST(Fig37Demo, RunsAndPrintsTheStatus) {
    const std::string cmd = std::string(FIG3_7_DEMO) + " --seconds 1 --name " + unique_name("demo") + " 2>&1";
    FILE* p = ::popen(cmd.c_str(), "r");
    ASSERT_NE(p, nullptr);
    std::string out;
    std::array<char, 4096> buf{};
    while (std::size_t n = std::fread(buf.data(), 1, buf.size(), p)) out.append(buf.data(), n);
    const int status = ::pclose(p);
    ASSERT_TRUE(WIFEXITED(status)) << out;
    EXPECT_EQ(WEXITSTATUS(status), 0) << out;
    // The status table (twice: before and after the reconfiguration), the
    // tracking-error lines and the reconfiguration's report.
    const std::string header = chimera::sbs::format_status_header();
    const auto first = out.find(header);
    ASSERT_NE(first, std::string::npos) << out;
    EXPECT_NE(out.find(header, first + 1), std::string::npos) << out;
    EXPECT_NE(out.find("max|q_ref - q_mez|"), std::string::npos) << out;
    EXPECT_NE(out.find("reconfig: off jpid, on jpidg in ONE call -- ok"), std::string::npos) << out;
    EXPECT_NE(out.find("so the robot interface "), std::string::npos) << out;
    EXPECT_NE(out.find("tracking error, the run's worst"), std::string::npos) << out;
    EXPECT_NE(out.find("finished"), std::string::npos) << out;
}

}  // namespace
