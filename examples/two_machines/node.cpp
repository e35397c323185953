// two_machines — one host of the two_machines example (README.md): the robot
// subsystem (robot interface + DDS bridge) or the controller subsystem
// (trajectory generator + PID + DDS bridge) of Figure 3.7, split across two
// machines over DDS. Runs until --seconds have passed or SIGINT/SIGTERM, and
// prints a status line every 0.1 s:
//
//   robot:      t=S robot_cycles=N bridge_cycles=N illegal=0|1 torques=fresh|stale max_speed=RAD/S
//               samples=N peak_speed=J1,..,J6 peak_torque=J1,..,J6 peak_trate=J1,..,J6
//   controller: t=S ctrl_cycles=N bridge_cycles=N measurements=fresh|stale error=RAD
//
// error: the largest |Q_REF - Q_MEZ| on the controller host, where Q_MEZ is
// what arrived from the robot host; max_speed: the largest |Q^_MEZ| of the arm
// now. samples: how many samples the peaks are of. The peaks, per joint, are over the 0.1 s since the previous line, from
// Q^_MEZ and T_MEZ (the torque the arm gets) sampled every millisecond:
// |speed| (rad/s), |torque| (N m), and the torque rate (N m/s) between two
// samples dt apart as |dT| / (dt + 2 cycles): a sampler or a cycle that runs
// late puts up to two of the arm's cycles (each at most TRATE x period) into
// one sample interval, so this never reads above TRATE while the limit holds.
#include "example_files.hpp"

#include <chimera/ipc/segment.hpp>
#include <chimera/sbs.hpp>
#include <chimera/svar.hpp>

#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <optional>
#include <string>
#include <mutex>
#include <thread>

namespace {

volatile std::sig_atomic_t g_stop = 0;
void on_signal(int) { g_stop = 1; }

struct Options {
    bool robot = true;
    double seconds = 0;  // 0: until a signal
    std::string name, bridge;
};

[[noreturn]] void usage() {
    std::fprintf(stderr,
                 "usage: two_machines robot|controller [--seconds S] [--name SUBSYSTEM] [--bridge FILE.rmod]\n"
                 "  The Cyclone DDS interface comes from CHIMERA_DDS_INTERFACE (cyclone.xml; default eth0).\n");
    std::exit(2);
}

Options parse(int argc, char** argv) {
    if (argc < 2) usage();
    Options o;
    const std::string side = argv[1];
    if (side != "robot" && side != "controller") usage();
    o.robot = side == "robot";
    for (int i = 2; i + 1 < argc; i += 2) {
        const std::string k = argv[i];
        if (k == "--seconds") o.seconds = std::atof(argv[i + 1]);
        else if (k == "--name") o.name = argv[i + 1];
        else if (k == "--bridge") o.bridge = argv[i + 1];
        else usage();
    }
    if (argc % 2 != 0) usage();
    return o;
}

template <std::size_t N>
std::array<double, N> read_var(chimera::svar::Table& table, const char* name) {
    std::array<double, N> v{};
    (void)table.read(table.index_of(name), v.data());
    return v;
}

// "stale yes" on the line of `port` in the bridge's `get STATUS` answer.
bool stale(chimera::sbs::Subsystem& sbs, chimera::sbs::TaskId bridge, const std::string& port) {
    const std::string status = sbs.get(bridge, "STATUS");
    const auto at = status.find(port + " counter ");
    if (at == std::string::npos) return true;
    const auto end = status.find('\n', at);
    return status.substr(at, end - at).find("stale yes") != std::string::npos;
}

// Samples the arm's Q^_MEZ and T_MEZ every millisecond on a thread of its own,
// through a table attachment of its own, and keeps the per-joint peaks until
// take() hands them over.
class PeakSampler {
public:
    static constexpr std::size_t kJoints = 6;
    using Peaks = std::array<double, kJoints>;
    struct Window { Peaks speed{}, torque{}, trate{}; int samples = 0; };

    PeakSampler(const std::string& table_segment, double cycle_period)
        : table_(chimera::svar::Table::attach(table_segment)), qd_(table_.index_of("Q^_MEZ")),
          tau_(table_.index_of("T_MEZ")), cycle_(cycle_period),
          thread_([this] { run(); }) {}
    ~PeakSampler() {
        stop_ = true;
        thread_.join();
    }
    Window take() {
        std::lock_guard lock(mutex_);
        const Window w = window_;
        window_ = {};
        return w;
    }

private:
    void run() {
        std::array<double, kJoints> qd{}, tau{}, last_tau{};
        auto last = std::chrono::steady_clock::now();
        bool first = true;
        while (!stop_) {
            std::this_thread::sleep_for(std::chrono::milliseconds(1));
            const auto now = std::chrono::steady_clock::now();
            (void)table_.read(qd_, qd.data());
            (void)table_.read(tau_, tau.data());
            const double dt = std::chrono::duration<double>(now - last).count();
            std::lock_guard lock(mutex_);
            ++window_.samples;
            for (std::size_t j = 0; j < kJoints; ++j) {
                window_.speed[j] = std::max(window_.speed[j], std::fabs(qd[j]));
                window_.torque[j] = std::max(window_.torque[j], std::fabs(tau[j]));
                if (!first)
                    window_.trate[j] = std::max(window_.trate[j], std::fabs(tau[j] - last_tau[j]) / (dt + 2 * cycle_));
            }
            last_tau = tau;
            last = now;
            first = false;
        }
    }

    chimera::svar::Table table_;
    const std::size_t qd_, tau_;
    const double cycle_;
    std::mutex mutex_;
    Window window_;
    std::atomic<bool> stop_{false};
    std::thread thread_;  // last: starts once everything it reads is made
};

std::string joined(const PeakSampler::Peaks& p) {
    std::string s;
    char b[32];
    for (double v : p) {
        std::snprintf(b, sizeof b, "%s%.3f", s.empty() ? "" : ",", v);
        s += b;
    }
    return s;
}

}  // namespace

int run(const Options& o);

int main(int argc, char** argv) {
    const Options o = parse(argc, argv);
    try {
        return run(o);
    } catch (const std::exception& e) {
        std::fprintf(stderr, "two_machines: %s\n", e.what());
        return 1;
    }
}

int run(const Options& o) {
    std::signal(SIGINT, on_signal);
    std::signal(SIGTERM, on_signal);
    using chimera::sbs::Control;
    const std::string dir = chimera_examples::split_path(TWO_MACHINES_RMOD_PATH).front();
    auto rmod = [](const char* n) { return chimera_examples::find_rmod(TWO_MACHINES_RMOD_PATH, n); };
    std::vector<std::string> notes;
    auto sbs = chimera::sbs::Subsystem::init(
        chimera_examples::load_sbs(dir + (o.robot ? "/robot.sbs" : "/controller.sbs"), &notes, o.name));
    for (const auto& n : notes) std::fprintf(stderr, "%s\n", n.c_str());
    chimera_examples::add_module_dirs(*sbs, TWO_MACHINES_MODULE_PATH);
    const std::string rtpu = o.robot ? "robot" : "ctrl";
    const std::string bridge_rmod = !o.bridge.empty() ? o.bridge : rmod(o.robot ? "robot_bridge" : "controller_bridge");
    std::vector<chimera::sbs::TaskId> tasks;
    if (o.robot) {
        tasks.push_back(sbs->spawn(rmod("puma_limited"), rtpu));
    } else {
        tasks.push_back(sbs->spawn(rmod("jtraj_hold"), rtpu));
        tasks.push_back(sbs->spawn(rmod("jpid_hold"), rtpu));
    }
    const chimera::sbs::TaskId bridge = sbs->spawn(bridge_rmod, rtpu);
    std::vector<chimera::sbs::ReconfigItem> on{{bridge, Control::on}};
    for (const auto id : tasks) on.push_back({id, Control::on});
    if (const auto r = sbs->reconfig(on); !r.message.empty()) {
        std::fprintf(stderr, "two_machines: %s\n", r.message.c_str());
        return 1;
    }
    const std::string table_segment = chimera::ipc::segment_name(sbs->name(), "svar");
    auto table = chimera::svar::Table::attach(table_segment);
    const auto start = std::chrono::steady_clock::now();
    const chimera::sbs::TaskId main_task = tasks.back();  // robotsim, or jpid
    std::optional<PeakSampler> sampler;
    if (o.robot) sampler.emplace(table_segment, 1.0 / 500);  // puma_limited.rmod's FREQ
    for (;;) {
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
        const double t = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
        const auto cycles = sbs->status(main_task).cycles, bridge_cycles = sbs->status(bridge).cycles;
        if (o.robot) {
            const auto qd = read_var<6>(table, "Q^_MEZ");
            double speed = 0;
            for (double v : qd) speed = std::max(speed, std::fabs(v));
            const PeakSampler::Window w = sampler->take();
            std::printf("t=%.2f robot_cycles=%llu bridge_cycles=%llu illegal=%d torques=%s max_speed=%.4f "
                        "samples=%d peak_speed=%s peak_torque=%s peak_trate=%s\n",
                        t, static_cast<unsigned long long>(cycles), static_cast<unsigned long long>(bridge_cycles),
                        sbs->illegal_configuration() ? 1 : 0, stale(*sbs, bridge, "T_REF") ? "stale" : "fresh", speed,
                        w.samples, joined(w.speed).c_str(), joined(w.torque).c_str(), joined(w.trate).c_str());
        } else {
            const auto q_ref = read_var<6>(table, "Q_REF"), q_mez = read_var<6>(table, "Q_MEZ");
            double error = 0;
            for (std::size_t j = 0; j < 6; ++j) error = std::max(error, std::fabs(q_ref[j] - q_mez[j]));
            std::printf("t=%.2f ctrl_cycles=%llu bridge_cycles=%llu measurements=%s error=%.4f\n", t,
                        static_cast<unsigned long long>(cycles), static_cast<unsigned long long>(bridge_cycles),
                        stale(*sbs, bridge, "Q_MEZ") ? "stale" : "fresh", error);
        }
        std::fflush(stdout);
        if (g_stop || (o.seconds > 0 && t >= o.seconds)) break;
    }
    sampler.reset();
    sbs->finish();
    return 0;
}
