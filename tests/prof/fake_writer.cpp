// A stand-in subsystem for the chimtop tests: it publishes a status segment
// (and an SVAR table when the svar service is built) with the real writer API
// — StatusSegment, TaskSlot, TaskProfiler — from three task threads:
//   servo    periodic 100 Hz, RTPU 0 (ctrl), reads Q_REF, writes TAU
//   planner  periodic 20 Hz, RTPU 1 (plan), misses every other cycle, one warning
//   logger   sporadic, RTPU 0, in ERROR with a message
// Usage: fake_writer SUBSYSTEM [SECONDS]   (runs until SIGTERM or SECONDS)
#include <signal.h>
#include <time.h>
#include <unistd.h>

#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "chimera/ipc/clock.hpp"
#include "chimera/prof.hpp"
#if FAKE_WRITER_HAVE_SVAR
#include "chimera/svar.hpp"
#endif

using namespace chimera::prof;

namespace {

std::atomic<bool> g_stop{false};
void on_signal(int) { g_stop = true; }

void burn(std::int64_t ns) {
    timespec ts;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
    const std::int64_t end = ts.tv_sec * 1'000'000'000LL + ts.tv_nsec + ns;
    for (;;) {
        clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
        if (ts.tv_sec * 1'000'000'000LL + ts.tv_nsec >= end) return;
    }
}

void periodic(TaskSlot slot, double hz, std::int64_t work_ns, int miss_every) {
    TaskProfiler prof(slot);
    slot.set_policy("SCHED_OTHER (test)");
    slot.set_state(TaskState::on);
    prof.start();
    const std::int64_t period = static_cast<std::int64_t>(1e9 / hz);
    std::int64_t next = chimera::ipc::now_ns();
    for (std::uint64_t n = 1; !g_stop; ++n) {
        next += period;
        const timespec ts = chimera::ipc::to_timespec(next);
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr);
        prof.cycle_begin(next);  // the release instant: its lateness is measured
        burn(work_ns);
        prof.cycle_end();
        if (miss_every > 0 && n % static_cast<std::uint64_t>(miss_every) == 0) prof.missed(1);
    }
    slot.set_state(TaskState::off);
}

}  // namespace

int main(int argc, char** argv) {
    if (argc < 2) {
        std::fprintf(stderr, "usage: %s SUBSYSTEM [SECONDS]\n", argv[0]);
        return 2;
    }
    const std::string sub = argv[1];
    const double seconds = argc > 2 ? std::atof(argv[2]) : 1e9;
    signal(SIGTERM, on_signal);
    signal(SIGINT, on_signal);

#if FAKE_WRITER_HAVE_SVAR
    const auto spec = chimera::svar::parse_svar_string(
        "NAME Q_REF\nTYPE double\nDESC reference\nUNITS rad\nNELEM 3\nINIT 0.5 1.5 2.5\n"
        "NAME TAU\nTYPE float\nDESC torque\nUNITS Nm\nNELEM 2\nINIT 7 8\nEOF\n",
        "fake.svar");
    const std::string svar_name = chimera::ipc::segment_name(sub, "svar");
    chimera::ipc::Segment::unlink(svar_name);
    chimera::svar::TableOptions table_options;
    table_options.segment.mode = 0640;  // as a subsystem's: the watch group reads it
    auto table = chimera::svar::Table::create(svar_name, spec, table_options);
#endif

    StatusOptions opt;
    opt.rtpus = 2;
    opt.rtpu_names = {"ctrl", "plan"};
    opt.rtpu_cpus = {0, 1};
    StatusSegment seg = StatusSegment::create(sub, 8, opt);
    TaskSlot servo = seg.claim({"servo", 0, 0, TaskType::periodic, 100.0, 5, "Q_REF", "TAU"});
    TaskSlot planner = seg.claim({"planner", 1, 1, TaskType::periodic, 20.0, 3, "", ""});
    TaskSlot logger = seg.claim({"logger", 0, 0, TaskType::sporadic, 0.0, 1, "", ""});
    logger.set_policy("SCHED_OTHER (test)");
    logger.set_state(TaskState::error);
    logger.error("disk full");
    planner.warning("trajectory clipped");
    planner.warning("trajectory clipped again");

    std::vector<std::thread> threads;
    threads.emplace_back(periodic, servo, 100.0, 500'000, 0);
    threads.emplace_back(periodic, planner, 20.0, 2'000'000, 2);
    std::printf("ready\n");
    std::fflush(stdout);

    const std::int64_t end = chimera::ipc::now_ns() + static_cast<std::int64_t>(seconds * 1e9);
    while (!g_stop && chimera::ipc::now_ns() < end) usleep(20'000);
    g_stop = true;
    for (auto& t : threads) t.join();
#if FAKE_WRITER_HAVE_SVAR
    table.destroy();
#endif
    return 0;
}
