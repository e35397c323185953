// The stall detector of the overload tests: threads that are runnable on one
// CPU should have all of it that is not idle. Sampled from another CPU, the
// time in a stretch that was neither theirs nor idle is the machine's (vCPU
// steal, another thread, a kernel that does not preempt, a sanitizer's
// background thread), not the scheduler's: a failed run with such a stretch
// may be run again, saying so.
#pragma once

#include <sched.h>
#include <sys/sysinfo.h>

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <fstream>
#include <string>
#include <thread>
#include <utility>
#include <vector>

namespace chimera::test {

/// The CPU time thread `tid` (of any process) has run, in ns; -1 if gone.
inline std::int64_t cpu_time_of_thread(long tid) {
    std::ifstream in("/proc/" + std::to_string(tid) + "/schedstat");
    std::int64_t ns = -1;
    in >> ns;
    return ns;
}

/// The time CPU `cpu` has been idle, in ns, from its cpuidle states (0 where
/// there are none: then an idle stretch counts as lost). Updated as the CPU
/// leaves idle, so a sample taken while it idles lags by that idle period.
inline std::int64_t idle_time_of_cpu(int cpu) {
    std::int64_t ns = 0;
    for (int state = 0;; ++state) {
        std::ifstream in("/sys/devices/system/cpu/cpu" + std::to_string(cpu) + "/cpuidle/state" +
                         std::to_string(state) + "/time");
        std::int64_t us = 0;
        if (!(in >> us)) return ns;
        ns += us * 1000;
    }
}

/// Samples the summed CPU time of `tids` every `step` for `length`, from the
/// CPUs other than `busy_cpu` where there are any, and returns the most CPU
/// time any stretch of `window` gave neither to them nor to idle (ns).
inline std::int64_t worst_cpu_loss(const std::vector<long>& tids, int busy_cpu, std::chrono::nanoseconds length,
                                   std::chrono::nanoseconds step, std::chrono::nanoseconds window) {
    cpu_set_t before, others;
    sched_getaffinity(0, sizeof before, &before);
    CPU_ZERO(&others);
    for (int c = 0; c < get_nprocs(); ++c)
        if (c != busy_cpu) CPU_SET(static_cast<unsigned>(c), &others);
    if (CPU_COUNT(&others) > 0) sched_setaffinity(0, sizeof others, &others);
    using clock = std::chrono::steady_clock;
    const auto sample = [&] {
        std::int64_t cpu = 0;
        for (long t : tids) cpu += cpu_time_of_thread(t);
        return std::pair(clock::now(), cpu + idle_time_of_cpu(busy_cpu));
    };
    std::vector<std::pair<clock::time_point, std::int64_t>> samples{sample()};
    const auto start = samples.front().first;
    for (auto at = start + step; at <= start + length; at += step) {
        std::this_thread::sleep_until(at);
        samples.push_back(sample());
    }
    sched_setaffinity(0, sizeof before, &before);
    std::int64_t worst = 0;
    for (std::size_t j = 1, i = 0; j < samples.size(); ++j) {
        while (samples[j].first - samples[i].first > window) ++i;
        if (i == j) continue;
        const std::int64_t wall = std::chrono::duration_cast<std::chrono::nanoseconds>(samples[j].first -
                                                                                       samples[i].first).count();
        worst = std::max(worst, wall - (samples[j].second - samples[i].second));
    }
    return worst;
}

}  // namespace chimera::test
