// bench_dds_producer — the publishing side of bench/dds/bench_dds.sh: a
// subsystem of one combined task, stamp then ddsbridge (publishing the 6-joint
// state as JointState.position), at 1 kHz, for DURATION seconds; prints the
// task's cycles and misses and the bridge thread's CPU time.
//   bench_dds_producer SBS SUBSYSTEM STAMP_RMOD BRIDGE_RMOD MODULE_DIR... DURATION
#include <chimera/sbs.hpp>
#include <chimera/sbs_files.hpp>

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>
#include <thread>

namespace {

// CPU time of this process's bridge threads (ns on a CPU, from schedstat).
std::uint64_t bridge_cpu_ns() {
    std::uint64_t total = 0;
    for (const auto& e : std::filesystem::directory_iterator("/proc/self/task")) {
        std::string name;
        std::getline(std::ifstream(e.path() / "comm"), name);
        std::uint64_t ns = 0;
        if (name == "ddsbridge" && (std::ifstream(e.path() / "schedstat") >> ns)) total += ns;
    }
    return total;
}

}  // namespace

int main(int argc, char** argv) {
    if (argc < 7) {
        std::fprintf(stderr, "usage: bench_dds_producer SBS SUBSYSTEM STAMP_RMOD BRIDGE_RMOD MODULE_DIR... DURATION\n");
        return 2;
    }
    try {
        chimera::SbsFile file = chimera::read_sbs(argv[1]);
        file.subsystem = argv[2];
        auto sbs = chimera::sbs::Subsystem::init(file);
        for (int i = 5; i < argc - 1; ++i) sbs->add_module_path(argv[i]);
        const auto task = sbs->spawn_combined({argv[3], argv[4]}, "rt");
        sbs->control(task, chimera::sbs::Control::on);
        const double seconds = std::atof(argv[argc - 1]);
        const std::uint64_t cpu0 = bridge_cpu_ns();
        std::this_thread::sleep_for(std::chrono::duration<double>(seconds));
        const double cpu = 1e-9 * static_cast<double>(bridge_cpu_ns() - cpu0) / seconds;
        const auto st = sbs->status(task);
        std::printf("producer cycles %llu misses %llu policy %s, bridge thread %.1f %% of a CPU\n",
                    static_cast<unsigned long long>(st.cycles), static_cast<unsigned long long>(st.misses),
                    st.policy.c_str(), 100 * cpu);
        sbs->finish();
    } catch (const std::exception& e) {
        std::fprintf(stderr, "bench_dds_producer: %s\n", e.what());
        return 1;
    }
    return 0;
}
