// candrive — simulated CANopen joint drives of a simulated arm on a SocketCAN
// interface: the hardware end of the canrobot module (thesis §7.3, transparent
// simulation). It reads the same .rmod as the canrobot task, so nodes, units and
// limits match by construction, and answers the protocol of
// modules/canrobot/README.md until SIGINT/SIGTERM.
//
//   candrive --rmod puma_can.rmod [--interface vcan0] [--priority 80] [--cpu 1]
//            [--seconds N] [--quiet]
//
// A virtual bus for trying it: ip link add dev vcan0 type vcan && ip link set vcan0 up
#include "tool_cli.hpp"

#include <CLI/CLI.hpp>

#include <pthread.h>
#include <sched.h>
#include <sys/mman.h>

#include <atomic>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <cstring>
#include <exception>
#include <string>
#include <thread>

#include "canrobot/drive_sim.hpp"

namespace {

std::atomic<bool> g_stop{false};

extern "C" void on_signal(int) { g_stop.store(true); }

void status_line(const chimera::canrobot::DriveSim& sim) {
    std::string line = "candrive: " + std::to_string(sim.syncs()) + " SYNCs |";
    for (std::size_t j = 0; j < sim.ndof(); ++j) {
        char b[96];
        std::snprintf(b, sizeof b, " %d:%s%s q=%+.3f", sim.config().bus.nodes[j],
                      sim.state(j) == chimera::canrobot::cia402::DriveState::operation_enabled ? "EN"
                      : sim.state(j) == chimera::canrobot::cia402::DriveState::fault        ? "FLT"
                                                                                             : "off",
                      sim.nmt(j) == chimera::canrobot::cia402::NmtState::operational ? "" : "(nmt)",
                      sim.q()[static_cast<Eigen::Index>(j)]);
        line += b;
    }
    std::puts(line.c_str());
    std::fflush(stdout);
}

}  // namespace

int main(int argc, char** argv) {
    CLI::App app{"Simulated CANopen (CiA 402) joint drives of a simulated arm, on a SocketCAN interface"};
    std::string rmod_path, interface;
    int priority = 0, cpu = -1;
    double seconds = 0;
    bool quiet = false;
    app.add_option("--rmod", rmod_path, "the canrobot .rmod whose LOCAL section describes the arm and the bus")
        ->required()
        ->check(CLI::ExistingFile);
    app.add_option("--interface", interface, "SocketCAN interface (default: the .rmod's INTERFACE)");
    app.add_option("--priority", priority, "run SCHED_FIFO at this priority (1-99; 0: do not ask)")
        ->check(CLI::Range(0, 99));
    app.add_option("--cpu", cpu, "pin to this CPU");
    app.add_option("--seconds", seconds, "stop after this many seconds (0: until SIGINT/SIGTERM)")
        ->check(CLI::NonNegativeNumber);
    app.add_flag("--quiet", quiet, "no status line every second");
    chimera::tools::add_version(app, "candrive");
    if (const int status = chimera::tools::parse(app, argc, argv); status >= 0) return status;

    try {
        const chimera::RmodFile rmod = chimera::read_rmod(rmod_path);
        auto config = chimera::canrobot::DriveConfig::from_rmod(rmod);
        if (interface.empty()) interface = config.bus.interface;
        chimera::canrobot::DriveSim sim(std::move(config));

        if (cpu >= 0) {
            cpu_set_t set;
            CPU_ZERO(&set);
            CPU_SET(cpu, &set);
            if (pthread_setaffinity_np(pthread_self(), sizeof set, &set) != 0)
                std::fprintf(stderr, "candrive: cannot pin to CPU %d: %s\n", cpu, std::strerror(errno));
        }
        if (priority > 0) {
            // A drive answers within microseconds; as a best-effort process it
            // still works, with feedback that may come a cycle late.
            sched_param sp{};
            sp.sched_priority = priority;
            if (const int e = pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp); e != 0)
                std::fprintf(stderr, "candrive: no real-time priority (%s): running best effort\n", std::strerror(e));
            else if (mlockall(MCL_CURRENT | MCL_FUTURE) != 0)
                std::fprintf(stderr, "candrive: mlockall: %s\n", std::strerror(errno));
        }

        std::signal(SIGINT, on_signal);
        std::signal(SIGTERM, on_signal);
        std::thread timer;
        if (seconds > 0)
            timer = std::thread([seconds] {
                const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(seconds);
                while (!g_stop.load() && std::chrono::steady_clock::now() < end)
                    std::this_thread::sleep_for(std::chrono::milliseconds(20));
                g_stop.store(true);
            });
        std::printf("candrive: %zu drives (nodes", sim.ndof());
        for (int n : sim.config().bus.nodes) std::printf(" %d", n);
        std::printf(") of a simulated %s on %s\n", sim.config().model.name().c_str(), interface.c_str());
        std::fflush(stdout);
        try {
            chimera::canrobot::run_drive_bus(sim, interface, g_stop,
                                             quiet ? std::function<void(const chimera::canrobot::DriveSim&)>{}
                                                   : status_line);
        } catch (...) {
            g_stop.store(true);
            if (timer.joinable()) timer.join();
            throw;
        }
        if (timer.joinable()) timer.join();
        if (!quiet) status_line(sim);
        return 0;
    } catch (const std::exception& e) {
        std::fprintf(stderr, "candrive: %s\n", e.what());
        return 1;
    }
}
