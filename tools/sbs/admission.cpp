#include "admission.hpp"

#include <chimera/cfg.hpp>

#include <cstdio>

namespace chimera::cli {

namespace {

std::string number(const char* format, double v) {
    char buf[64];
    std::snprintf(buf, sizeof buf, format, v);
    return buf;
}

muf::Policy policy_of(Scheduler s) {
    switch (s) {
        case Scheduler::RM: return muf::Policy::rm;
        case Scheduler::EDF: return muf::Policy::edf;
        case Scheduler::MUF: break;
    }
    return muf::Policy::muf;
}

// "jpid (U 0.230), puma (U 0.100)": the tasks the critical set would lose.
std::string lost_text(const std::vector<muf::TaskSpec>& tasks, const muf::CriticalSet& before,
                      const muf::CriticalSet& after) {
    std::string out;
    for (std::size_t i = 0; i < before.member.size(); ++i) {
        if (!before.member[i] || after.member[i]) continue;
        const double u = tasks[i].reserved() / tasks[i].period;
        out += (out.empty() ? "" : ", ") + tasks[i].name + " (U " + number("%.3f", u) + ")";
    }
    return out;
}

}  // namespace

// Measured with `status set rmod cycle miss avgC maxC cycP99` on samplers of
// 1 and 4 channels at 1 kHz for 3 s (Debian 12, x86-64, BACKEND other, two
// cores shared with a build at load 8): avgC 2.0 to 3.9 us, cycP99 4.9 to
// 5.4 us (maxC, 98 us to 5.6 ms, is preemption of a SCHED_OTHER thread, not
// work). The reservation is 4x the p99, to cover the release itself (the
// dispatcher's wake-up and two context switches) that the cycle time does not
// see. The per-channel part (a load and a store of a double) was not resolved
// by that measurement; 0.1 us is a margin over it.
double sampler_cycle_cost(std::size_t channels) noexcept {
    constexpr double kPerCycle = 20e-6;
    constexpr double kPerChannel = 0.1e-6;
    return kPerCycle + kPerChannel * static_cast<double>(channels);
}

std::string rate_problem(const RtpuSpec& rtpu, double hz) {
    if (hz >= rtpu.minfreq && hz <= rtpu.maxfreq) return {};
    return cfg::number_text(hz) + " Hz is " + (hz > rtpu.maxfreq ? "above" : "below") + " RTPU " + rtpu.name +
           "'s " + (hz > rtpu.maxfreq ? "MAXFREQ" : "MINFREQ") + " (it runs tasks at " +
           cfg::number_text(rtpu.minfreq) + " to " + cfg::number_text(rtpu.maxfreq) + " Hz)";
}

std::string analysis_problem(const RtpuSpec& rtpu, const std::vector<muf::TaskSpec>& running,
                             const muf::TaskSpec& candidate) {
    const muf::Policy policy = policy_of(rtpu.scheduler);
    std::vector<muf::TaskSpec> with = running;
    with.push_back(candidate);
    const muf::CriticalSet before = muf::critical_set(running, policy);
    const muf::CriticalSet after = muf::critical_set(with, policy);
    const std::string lost = lost_text(running, before, after);
    if (lost.empty() && after.member.back()) return {};
    const double u = candidate.reserved() / candidate.period;
    std::string why = "RTPU " + rtpu.name + " (" + std::string(to_string(rtpu.scheduler)) + ") cannot take " +
                      candidate.name + " at " + cfg::number_text(1.0 / candidate.period) + " Hz (C " +
                      number("%.0f", candidate.reserved() * 1e6) + " us, U " + number("%.3f", u) + "): ";
    why += lost.empty() ? "it would not be in the critical set itself"
                        : "the critical set would lose " + lost;
    double total = u;
    for (const auto& t : running) total += t.reserved() / t.period;
    return why + " (utilisation with it " + number("%.3f", total) + ", bound " + number("%.3f", after.bound) + ")";
}

std::string admission_problem(const RtpuSpec& rtpu, double hz, const std::vector<muf::TaskSpec>& running,
                              const muf::TaskSpec& candidate) {
    const std::string range = rate_problem(rtpu, hz);
    return range.empty() ? analysis_problem(rtpu, running, candidate) : range;
}

}  // namespace chimera::cli
