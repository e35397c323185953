// Cycle cost of each control module at 6 DOF (issue 8), and of a combined
// 6-joint control task compared with LinuxCNC HAL's 1 kHz thread
// (PERFORMANCE.md: ~700 ns p50 for 6 x 5 = 31 functions).
//
// No thread and no scheduler: each task is built by the runtime's own
// TaskCore (src/sbs/internal.hpp: module loaded from its .so, local table,
// transfer sets, the Task view), taken through in-consts -> init ->
// out-consts -> on exactly as spawn/on do, and then its methods are called
// directly in the benchmark loop:
//   <rmod>/cycle      the module's cycle() alone, on the local table
//   <rmod>/task       in-vars copy (one table lock) + cycle() + out-vars copy:
//                     what one release of the task costs minus the wake-up
// The robot interface (robotsim, PUMA 560) is made first: it produces the NDOF
// and DH in-consts the others configure from (§3.5).
//
// Table 1 (table1/<module>/in, /out, /task) measures the modules of Figure 6.10
// as examples/fig6_10_teleop runs them: puma_pidg, grav_comp, qrdiff and
// jtball, which reads trackball_sim on a pseudo-terminal through the SIO
// driver (the example's SimulatedTrackball, idle: the operator not touching it).
//
//   build/bench/modules/bench_modules --benchmark_repetitions=5
//       --benchmark_report_aggregates_only=true   (one command line)
#include "fig6_10.hpp"
#include "internal.hpp"

#include <chimera/sbs_files.hpp>
#include <chimera/svar.hpp>

#include <benchmark/benchmark.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <exception>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#ifndef BENCH_MODULES_DIR
#error "BENCH_MODULES_DIR (this folder) must be defined by the build"
#endif
#ifndef BENCH_MODULE_PATH
#error "BENCH_MODULE_PATH (module build folders) must be defined by the build"
#endif
#ifndef BENCH_SOURCE_ROOT
#error "BENCH_SOURCE_ROOT must be defined by the build"
#endif

namespace {

using namespace chimera;
using sbs::detail::SubsystemCore;
using sbs::detail::TaskCore;

std::string rmod_path(const std::string& rel) { return std::string(BENCH_SOURCE_ROOT) + "/modules/" + rel; }
// The combined task's objects: the library's .rmod files at one rate, 1 kHz (§3.8.1).
std::string here(const std::string& name) { return std::string(BENCH_MODULES_DIR) + "/" + name; }

// One subsystem for the whole run: the table, the robot, the tasks.
class Bench {
public:
    Bench() {
        SbsFile f;
        f.path = "bench_modules";
        f.subsystem = "bench_modules" + std::to_string(::getpid());
        f.svarfile = std::string(BENCH_MODULES_DIR) + "/bench_modules.svar";
        RtpuSpec r;
        r.name = "cpu0";
        r.cpu = 0;
        r.backend = Backend::other;
        f.rtpus.push_back(r);
        f.master = "cpu0";
        core_ = std::make_unique<SubsystemCore>(f);
        std::string path = BENCH_MODULE_PATH;
        for (std::size_t pos = 0; pos <= path.size();) {
            const std::size_t colon = std::min(path.find(':', pos), path.size());
            if (colon > pos) core_->module_dirs.push_back(path.substr(pos, colon - pos));
            pos = colon + 1;
        }
        make({rmod_path("robotsim/puma_torque.rmod")});
    }
    ~Bench() {
        for (auto& t : tasks_)
            for (auto& o : t->objects)
                if (o.module->kill(*o.view) != Result::OK) std::fprintf(stderr, "%s: kill failed\n", o.rmod.name.c_str());
        tasks_.clear();
        core_->table.destroy();
    }

    /// A task of these objects, initialised and turned on.
    TaskCore& make(const std::vector<std::string>& rmods) {
        std::vector<RmodFile> files;
        for (const auto& p : rmods) files.push_back(read_rmod(p));
        auto t = std::make_unique<TaskCore>(*core_, static_cast<int>(tasks_.size()), core_->file.rtpus[0],
                                            std::move(files));
        auto copied = [](svar::Status s, const char* what) {
            if (!svar::transferred(s)) throw std::runtime_error(std::string(what) + ": " + svar::to_string(s));
        };
        copied(t->local->copy_from_global(t->set_in_consts), "in-consts");
        for (auto& o : t->objects)
            if (o.module->init(*o.view) != Result::OK) throw std::runtime_error(o.rmod.name + ": init failed");
        copied(t->local->copy_to_global(t->set_out_consts), "out-consts");
        copied(t->local->copy_from_global(t->set_on), "on-vars");
        for (auto& o : t->objects)
            if (o.module->on(*o.view) != Result::OK) throw std::runtime_error(o.rmod.name + ": on failed");
        copied(t->local->copy_to_global(t->set_out_vars), "out-vars");
        tasks_.push_back(std::move(t));
        return *tasks_.back();
    }

private:
    std::unique_ptr<SubsystemCore> core_;
    std::vector<std::unique_ptr<TaskCore>> tasks_;
};

Bench& bench() {
    static Bench b;
    return b;
}

void run_cycle(benchmark::State& state, TaskCore& t, bool with_transfer) {
    for (auto _ : state) {
        if (with_transfer && !svar::transferred(t.local->copy_from_global(t.set_in_vars))) [[unlikely]] {
            state.SkipWithError("in-vars copy failed");
            break;
        }
        for (auto& o : t.objects) benchmark::DoNotOptimize(o.module->cycle(*o.view));
        if (with_transfer && !svar::transferred(t.local->copy_to_global(t.set_out_vars))) [[unlikely]] {
            state.SkipWithError("out-vars copy failed");
            break;
        }
        benchmark::ClobberMemory();
    }
}

// One direction of a task's transfer alone (Table 1's "CPU time for
// transferring in-vars / out-vars"): the copy with its table lock.
void run_transfer(benchmark::State& state, TaskCore& t, bool in) {
    for (auto _ : state) {
        const svar::Status st = in ? t.local->copy_from_global(t.set_in_vars) : t.local->copy_to_global(t.set_out_vars);
        if (!svar::transferred(st)) [[unlikely]] {
            state.SkipWithError("transfer failed");
            break;
        }
        benchmark::ClobberMemory();
    }
}

// Figure 6.10's trackball for the whole run, made before the first task so that
// it outlives them (jtball's line is closed at kill, in ~Bench). Never started,
// it sends idle packets at 50 Hz until the process ends (its one phase, required
// by trackball_sim, never runs).
fig6_10::SimulatedTrackball& trackball() {
    static fig6_10::SimulatedTrackball t(std::filesystem::temp_directory_path() /
                                             ("bench_modules." + std::to_string(::getpid())),
                                         {"idle", "1"});
    return t;
}

TaskCore* make_or_exit(const std::string& label, const std::vector<std::string>& rmods) {
    try {
        return &bench().make(rmods);
    } catch (const std::exception& e) {
        std::fprintf(stderr, "bench_modules: %s: %s\n", label.c_str(), e.what());
        std::exit(1);
    }
}

void register_module(const std::string& label, std::vector<std::string> rmods) {
    TaskCore* task = make_or_exit(label, rmods);
    benchmark::RegisterBenchmark((label + "/cycle").c_str(), [task](benchmark::State& s) { run_cycle(s, *task, false); });
    benchmark::RegisterBenchmark((label + "/task").c_str(), [task](benchmark::State& s) { run_cycle(s, *task, true); });
}

// Table 1 (§6.6.1): a module of Figure 6.10 with its in-vars and out-vars
// transfers apart and the whole task; the counters say how many variables
// each direction moves (the table's N in-var, N out-var).
void register_table1(const std::string& label, const std::string& rmod) {
    TaskCore* task = make_or_exit(label, {rmod});
    const auto with_counts = [task](auto body) {
        return [task, body](benchmark::State& s) {
            body(s, *task);
            s.counters["n_in"] = static_cast<double>(task->objects.front().rmod.in_vars.size());
            s.counters["n_out"] = static_cast<double>(task->objects.front().rmod.out_vars.size());
        };
    };
    const std::string l = "table1/" + label;
    benchmark::RegisterBenchmark((l + "/in").c_str(), with_counts([](auto& s, TaskCore& t) { run_transfer(s, t, true); }));
    benchmark::RegisterBenchmark((l + "/out").c_str(), with_counts([](auto& s, TaskCore& t) { run_transfer(s, t, false); }));
    benchmark::RegisterBenchmark((l + "/task").c_str(), with_counts([](auto& s, TaskCore& t) { run_cycle(s, t, true); }));
}

}  // namespace

int main(int argc, char** argv) {
    try {
        trackball();
    } catch (const std::exception& e) {
        std::fprintf(stderr, "bench_modules: Figure 6.10's trackball: %s\n", e.what());
        return 1;
    }
    // Each module on its own, with its library .rmod.
    register_module("robotsim_puma_torque", {rmod_path("robotsim/puma_torque.rmod")});
    register_module("trajgen_jtraj", {rmod_path("trajgen/jtraj.rmod")});
    register_module("pid_jpidg", {rmod_path("pid/jpidg.rmod")});
    register_module("diff_qmdiff", {rmod_path("diff/qmdiff.rmod")});
    register_module("integ_qrinteg", {rmod_path("integ/qrinteg.rmod")});
    register_module("gravcomp", {rmod_path("dyn/grav_comp.rmod")});
    register_module("invdyn", {rmod_path("dyn/invdyn.rmod")});
    register_module("fwdkin", {rmod_path("kin/fwdkin.rmod")});
    register_module("invkin", {rmod_path("kin/invkin.rmod")});
    register_module("dlsik", {rmod_path("kin/dlsik.rmod")});
    register_module("join_tjoin", {rmod_path("join/tjoin.rmod")});
    register_module("ctc_pidacc+invdyn", {rmod_path("ctc/ctc_pid.rmod"), rmod_path("ctc/ctc_invdyn.rmod")});
    // The combined 6-joint control task against HAL's thread: trajectory
    // (position, velocity, acceleration), differentiator of the measured
    // positions, gravity compensation and PID with gravity feed-forward, as
    // ONE task with one in-vars and one out-vars transfer.
    register_module("combined_6joint",
                    {here("c_traj.rmod"), here("c_diff.rmod"), here("c_grav.rmod"), here("c_pid.rmod")});
    // The same without gravity compensation: the closest match to HAL's five
    // simple functions per joint (signal generator, differentiator, PID with
    // its limiter), no rigid-body dynamics.
    register_module("combined_6joint_nograv", {here("c_traj.rmod"), here("c_diff.rmod"), here("c_pid_nograv.rmod")});
    // Table 1: the modules of Figure 6.10, the .rmod files examples/fig6_10_teleop
    // spawns (jtball's copy reads the trackball's line).
    register_table1("puma_pidg", fig6_10::rmod("puma_pidg"));
    register_table1("grav_comp", fig6_10::rmod("grav_comp"));
    register_table1("diff", fig6_10::rmod("qrdiff"));
    register_table1("jtball", trackball().rmod_path());
    benchmark::Initialize(&argc, argv);
    benchmark::RunSpecifiedBenchmarks();
    benchmark::Shutdown();
    return 0;
}
