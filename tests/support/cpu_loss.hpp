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
#include <cstdio>
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

/// For its life the calling thread runs on the CPUs other than `busy_cpu`
/// (where there are any), so that sampling never takes CPU time from the
/// threads it samples; the affinity before is restored at the end.
class OnOtherCpus {
public:
    explicit OnOtherCpus(int busy_cpu) {
        sched_getaffinity(0, sizeof before_, &before_);
        cpu_set_t others;
        CPU_ZERO(&others);
        for (int c = 0; c < get_nprocs(); ++c)
            if (c != busy_cpu) CPU_SET(static_cast<unsigned>(c), &others);
        if (CPU_COUNT(&others) > 0) sched_setaffinity(0, sizeof others, &others);
    }
    ~OnOtherCpus() { sched_setaffinity(0, sizeof before_, &before_); }
    OnOtherCpus(const OnOtherCpus&) = delete;
    OnOtherCpus& operator=(const OnOtherCpus&) = delete;

private:
    cpu_set_t before_;
};

/// Samples the summed CPU time of `tids` every `step` for `length`, from the
/// CPUs other than `busy_cpu` where there are any, and returns the most CPU
/// time any stretch of `window` gave neither to them nor to idle (ns).
inline std::int64_t worst_cpu_loss(const std::vector<long>& tids, int busy_cpu, std::chrono::nanoseconds length,
                                   std::chrono::nanoseconds step, std::chrono::nanoseconds window) {
    using clock = std::chrono::steady_clock;
    const auto sample = [&] {
        std::int64_t cpu = 0;
        for (long t : tids) cpu += cpu_time_of_thread(t);
        return std::pair(clock::now(), cpu + idle_time_of_cpu(busy_cpu));
    };
    std::vector<std::pair<clock::time_point, std::int64_t>> samples;
    {
        const OnOtherCpus elsewhere(busy_cpu);
        samples.push_back(sample());
        const auto start = samples.front().first;
        for (auto at = start + step; at <= start + length; at += step) {
            std::this_thread::sleep_until(at);
            samples.push_back(sample());
        }
    }
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

/// The overload tests' verdict on a run: disturbed when a stretch lost more
/// than the critical job's 1 ms margin to others. Prints the run's misses,
/// the loss and the verdict, so a run taken again says why.
inline bool overload_run_disturbed(int attempt, std::uint64_t a_missed, std::uint64_t b_missed,
                                   std::uint64_t c_missed, std::int64_t worst_lost_ns) {
    const bool disturbed = worst_lost_ns > 1'000'000;
    std::printf("run %d: critical a/b missed %llu/%llu, c missed %llu; a 20 ms stretch lost %.2f ms to others%s\n",
                attempt, static_cast<unsigned long long>(a_missed), static_cast<unsigned long long>(b_missed),
                static_cast<unsigned long long>(c_missed), static_cast<double>(worst_lost_ns) / 1e6,
                disturbed ? " (disturbed: the machine held the CPU)" : "");
    return disturbed;
}

}  // namespace chimera::test
