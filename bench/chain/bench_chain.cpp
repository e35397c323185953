// The whole subsystem's CPU time per cycle for the like-for-like chain of
// issue 14 item 2, to set beside LinuxCNC HAL's chain6.hal (the peer in
// ../shared/peers/linuxcnc-hal; bench/chain/chain_vs_hal.sh alternates both).
//
// Per joint a trajectory generator, a PID, an integrator plant and a
// differentiator, 6 joints, 1 kHz, on one RTPU pinned to one CPU (HAL pins
// its thread to the last CPU: so do we by default):
//   combined   ONE task chain_traj+chain_pid+chain_plant+chain_diff (§3.8.1)
//   separate   four tasks of one rate on the RTPU (data-flow priorities
//              order them traj -> pid -> plant -> diff in each period)
//
// What is measured over the window (after a warm-up):
//   - on-CPU time of EVERY thread of this process (/proc/self/task/*/schedstat,
//     the kernel's own account: the master, the task threads, any helper),
//     divided by the cycles the chain's first task ran: the subsystem's cost
//     per cycle, wake-ups and scheduler work included — what schedstat gives
//     for HAL's rtapi_app too;
//   - the chain's own time per cycle (release to end of cycle, the status
//     cycle-time histogram): p50/p99 beside HAL's thread .time.
// One line of key=value results at the end, for the script.
//
//   build/bench/chain/bench_chain --mode combined --seconds 10 --warm 2 [--cpu 1]
#include <chimera/prof.hpp>
#include <chimera/sbs.hpp>
#include <chimera/sbs_files.hpp>

#include <dirent.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <map>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#ifndef BENCH_CHAIN_DIR
#error "BENCH_CHAIN_DIR (this folder) must be defined by the build"
#endif

namespace {

using namespace chimera;
using namespace chimera::sbs;

struct Options {
    std::string mode = "combined";
    double seconds = 10;
    double warm = 2;
    int cpu = -1;
};

[[noreturn]] void usage(const char* why) {
    std::fprintf(stderr,
                 "bench_chain: %s\nusage: bench_chain [--mode combined|separate] [--seconds S] [--warm S] [--cpu N]\n",
                 why);
    std::exit(2);
}

Options parse(int argc, char** argv) {
    Options o;
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        if (i + 1 >= argc) usage(("missing value after " + a).c_str());
        const char* v = argv[++i];
        if (a == "--mode") o.mode = v;
        else if (a == "--seconds") o.seconds = std::atof(v);
        else if (a == "--warm") o.warm = std::atof(v);
        else if (a == "--cpu") o.cpu = std::atoi(v);
        else usage(("unknown option " + a).c_str());
    }
    if (o.mode != "combined" && o.mode != "separate") usage("--mode must be combined or separate");
    if (!(o.seconds > 0) || o.warm < 0) usage("--seconds must be > 0 and --warm >= 0");
    if (o.cpu < 0) o.cpu = static_cast<int>(sysconf(_SC_NPROCESSORS_ONLN)) - 1;
    return o;
}

std::string here(const std::string& name) { return std::string(BENCH_CHAIN_DIR) + "/" + name; }

// On-CPU nanoseconds of each live thread of this process, by "tid comm".
std::map<std::string, std::uint64_t> thread_cpu_ns() {
    std::map<std::string, std::uint64_t> out;
    DIR* d = opendir("/proc/self/task");
    if (!d) return out;
    while (dirent* e = readdir(d)) {
        if (e->d_name[0] == '.') continue;
        const std::string base = std::string("/proc/self/task/") + e->d_name;
        std::uint64_t ns = 0;
        std::string comm;
        std::ifstream(base + "/schedstat") >> ns;
        std::getline(std::ifstream(base + "/comm"), comm);
        out[std::string(e->d_name) + " " + comm] = ns;
    }
    closedir(d);
    return out;
}

std::uint64_t cycles_of(const Subsystem& s, TaskId t) { return s.status(t).cycles; }

double us(std::optional<std::uint64_t> ns) { return ns ? static_cast<double>(*ns) / 1e3 : -1; }

}  // namespace

int main(int argc, char** argv) {
    const Options opt = parse(argc, argv);
    SbsFile f;
    f.path = "bench_chain";
    f.subsystem = "bench_chain" + std::to_string(::getpid());
    f.svarfile = here("chain.svar");
    RtpuSpec r;
    r.name = "chain";
    r.cpu = opt.cpu;
    f.rtpus.push_back(r);
    f.master = "chain";
    try {
        auto sbs = Subsystem::init(std::move(f));
        const std::vector<std::string> rmods = {here("chain_traj.rmod"), here("chain_pid.rmod"),
                                                here("chain_plant.rmod"), here("chain_diff.rmod")};
        std::vector<TaskId> tasks;
        if (opt.mode == "combined") tasks.push_back(sbs->spawn_combined(rmods, "chain"));
        else
            for (const auto& p : rmods) tasks.push_back(sbs->spawn(p, "chain"));
        std::vector<ReconfigItem> on;
        for (TaskId t : tasks) on.push_back({t, Control::on});
        if (auto res = sbs->reconfig(on); !res) {
            std::fprintf(stderr, "bench_chain: %s\n", res.message.c_str());
            return 1;
        }
        std::this_thread::sleep_for(std::chrono::duration<double>(opt.warm));

        std::vector<prof::TaskStatus> base;
        for (TaskId t : tasks) base.push_back(sbs->status(t).profile);
        const std::uint64_t c0 = cycles_of(*sbs, tasks[0]);
        const auto cpu0 = thread_cpu_ns();
        std::this_thread::sleep_for(std::chrono::duration<double>(opt.seconds));
        const auto cpu1 = thread_cpu_ns();
        const std::uint64_t cycles = cycles_of(*sbs, tasks[0]) - c0;

        std::uint64_t total = 0;
        std::printf("bench_chain: %s, %zu task(s) on CPU %d, %.0f s window, %llu cycles\n", opt.mode.c_str(),
                    tasks.size(), opt.cpu, opt.seconds, static_cast<unsigned long long>(cycles));
        std::printf("  %-28s %14s\n", "thread", "CPU ns/cycle");
        for (const auto& [name, ns1] : cpu1) {
            const auto it = cpu0.find(name);
            const std::uint64_t d = ns1 - (it == cpu0.end() ? 0 : it->second);
            total += d;
            if (cycles && d) std::printf("  %-28s %14.0f\n", name.c_str(), static_cast<double>(d) / static_cast<double>(cycles));
        }
        std::uint64_t misses = 0;
        double chain_p50 = 0, chain_p99 = 0;
        for (std::size_t i = 0; i < tasks.size(); ++i) {
            const auto st = sbs->status(tasks[i]);
            misses += st.misses;
            const auto h = prof::TimeHistogram::since(st.profile.cycle_time, base[i].cycle_time);
            // Separate tasks: the chain's time is the sum of its tasks' (an upper
            // bound for the percentiles, as each task's p50 is summed).
            chain_p50 += us(h.percentile_ns(500000));
            chain_p99 += us(h.percentile_ns(990000));
            std::printf("  task %-22s cycle time p50 %.2f us, p99 %.2f us, misses %llu, policy %s\n",
                        st.rmod.c_str(), us(h.percentile_ns(500000)), us(h.percentile_ns(990000)),
                        static_cast<unsigned long long>(st.misses), st.policy.c_str());
        }
        const double per_cycle = cycles ? static_cast<double>(total) / static_cast<double>(cycles) : 0;
        std::printf("RESULT mode=%s tasks=%zu cycles=%llu misses=%llu process_cpu_ns_per_cycle=%.0f "
                    "chain_p50_us=%.2f chain_p99_us=%.2f\n",
                    opt.mode.c_str(), tasks.size(), static_cast<unsigned long long>(cycles),
                    static_cast<unsigned long long>(misses), per_cycle, chain_p50, chain_p99);
        sbs->finish();
    } catch (const std::exception& e) {
        std::fprintf(stderr, "bench_chain: %s\n", e.what());
        return 1;
    }
    return 0;
}
