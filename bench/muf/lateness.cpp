// Release lateness of a periodic task, measured the way cyclictest measures a
// thread's wake-up: every release of the timeline is a sample, late by however
// much (a release late by more than a period is a sample too, not folded back
// by a modulo, and a release the runtime skipped because the previous cycle
// overran is counted with how late it was when the task woke).
//
//   lateness [--cycles N] [--period-us P] [--cpu C] [--priority 80] [--histogram FILE]
//
// The task runs under the muf fifo backend on RTPU CPU C at SCHED_FIFO
// PRIORITY, like `cyclictest -m -p PRIORITY -i P -a C`. Prints one JSON line
// with p50/p99/p99.9/max lateness in µs, the count of samples and of skipped
// releases. bench/muf/lateness_vs_cyclictest.sh alternates it with cyclictest.
#include <sys/mman.h>

#include <algorithm>
#include <cinttypes>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include "chimera/muf.hpp"

namespace {

using namespace chimera::muf;

struct Options {
    long cycles = 60000;
    long period_us = 1000;
    int cpu = 1;
    int priority = 80;
};

Options parse(int argc, char** argv) {
    Options o;
    for (int i = 1; i + 1 < argc; i += 2) {
        const std::string k = argv[i];
        const long v = std::strtol(argv[i + 1], nullptr, 10);
        if (k == "--cycles") o.cycles = v;
        else if (k == "--period-us") o.period_us = v;
        else if (k == "--cpu") o.cpu = static_cast<int>(v);
        else if (k == "--priority") o.priority = static_cast<int>(v);
        else {
            std::fprintf(stderr, "lateness: unknown option %s\n", k.c_str());
            std::exit(2);
        }
    }
    return o;
}

double percentile(std::vector<std::int64_t>& v, double q) {
    if (v.empty()) return 0;
    const auto k = static_cast<std::size_t>(q * static_cast<double>(v.size() - 1));
    std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(k), v.end());
    return static_cast<double>(v[k]) / 1000.0;
}

}  // namespace

int main(int argc, char** argv) {
    const Options o = parse(argc, argv);
    mlockall(MCL_CURRENT | MCL_FUTURE);
    RtpuOptions ro;
    ro.name = "lateness";
    ro.cpu = o.cpu;
    ro.backend = Backend::fifo;
    // The only task of the band takes its top priority: fifo_high - 1.
    ro.fifo_low = o.priority - 1;
    ro.fifo_high = o.priority + 1;
    RtpuScheduler sch(ro);
    if (!sch.privileged()) {
        std::fprintf(stderr, "lateness: SCHED_FIFO refused (run as root)\n");
        return 1;
    }
    const std::int64_t period = o.period_us * 1000;
    RtTaskParams p;
    p.name = "lateness";
    p.period_ns = period;
    p.first_release_ns = clock_ns() + 50'000'000;
    const TaskHandle h = sch.add_task(p);
    std::vector<std::int64_t> late, woken;  // every release; the one each wake-up was for
    late.reserve(static_cast<std::size_t>(o.cycles) + 1024);
    woken.reserve(static_cast<std::size_t>(o.cycles) + 1024);
    std::int64_t skipped = 0;
    std::thread task([&] {
        sch.attach_current_thread(h);
        std::int64_t next = 0;  // index of the release this wake-up is for
        while (static_cast<long>(late.size()) < o.cycles) {
            if (sch.wait_release(h) != Wake::release) continue;
            const std::int64_t now = clock_ns();
            // The runtime starts the job at the latest release due; the ones
            // before it since the last job were skipped: each is a sample.
            const std::int64_t due = (now - p.first_release_ns) / period;
            woken.push_back(now - (p.first_release_ns + due * period));
            for (; next <= due && static_cast<long>(late.size()) < o.cycles; ++next) {
                late.push_back(now - (p.first_release_ns + next * period));
                if (next < due) ++skipped;
            }
            sch.cycle_complete(h);
        }
        sch.detach_current_thread(h);
    });
    task.join();
    const std::string policy = sch.policy_of(h);
    const bool static_ranking = sch.static_ranking();
    sch.remove_task(h);
    std::vector<std::int64_t> v = late;
    const double p50 = percentile(v, 0.50), p99 = percentile(v, 0.99), p999 = percentile(v, 0.999);
    const double mx = static_cast<double>(*std::max_element(late.begin(), late.end())) / 1000.0;
    // As cyclictest counts: one sample per wake-up, for the latest release due
    // (cyclictest steps over the periods it slept through without a sample).
    const double w99 = percentile(woken, 0.99), w999 = percentile(woken, 0.999);
    std::printf("{\"tool\":\"chimera\",\"samples\":%zu,\"skipped\":%" PRId64
                ",\"p50_us\":%.1f,\"p99_us\":%.1f,\"p999_us\":%.1f,\"max_us\":%.1f,"
                "\"woken_p99_us\":%.1f,\"woken_p999_us\":%.1f,\"static_ranking\":%s,"
                "\"reschedules\":%" PRIu64 ",\"policy\":\"%s\"}\n",
                late.size(), skipped, p50, p99, p999, mx, w99, w999, static_ranking ? "true" : "false",
                sch.reschedules(), policy.c_str());
    return 0;
}
