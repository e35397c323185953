// bench_dds_producer — the publishing side of bench/dds/bench_dds.sh: a
// subsystem of one combined task, stamp then ddsbridge (publishing the 6-joint
// state as JointState.position), at 1 kHz, for DURATION seconds.
//   bench_dds_producer SBS SUBSYSTEM STAMP_RMOD BRIDGE_RMOD MODULE_DIR... DURATION
#include <chimera/sbs.hpp>
#include <chimera/sbs_files.hpp>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <thread>

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
        std::this_thread::sleep_for(std::chrono::duration<double>(std::atof(argv[argc - 1])));
        const auto st = sbs->status(task);
        std::printf("producer cycles %llu misses %llu policy %s\n", static_cast<unsigned long long>(st.cycles),
                    static_cast<unsigned long long>(st.misses), st.policy.c_str());
        sbs->finish();
    } catch (const std::exception& e) {
        std::fprintf(stderr, "bench_dds_producer: %s\n", e.what());
        return 1;
    }
    return 0;
}
