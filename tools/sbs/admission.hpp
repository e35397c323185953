// tools/sbs/admission.hpp — whether a task a client starts (a sampler, a
// spawned task turned on, a new freq) may join an RTPU (issue #29.2): its
// rate within the RTPU's MINFREQ..MAXFREQ, and the RTPU's own analysis
// (muf::critical_set under its SCHEDULER, the one its scheduler runs) still
// guaranteeing every task it guaranteed, and the newcomer too.
// Pure functions of the numbers, so every refusal can give them.
#pragma once

#include <chimera/muf/analysis.hpp>
#include <chimera/sbs_files.hpp>

#include <cstddef>
#include <string>
#include <vector>

namespace chimera::cli {

/// The execution time per cycle the analysis reserves for a sampler of
/// `channels` values (seconds): measured on the sampler task, with a margin
/// (admission.cpp says how).
double sampler_cycle_cost(std::size_t channels) noexcept;

/// "" when `hz` lies within the RTPU's MINFREQ..MAXFREQ, else why not, with both bounds.
std::string rate_problem(const RtpuSpec& rtpu, double hz);

/// "" when `candidate` may join `running` (the RTPU's tasks its analysis
/// counts), else why not: which task the critical set would lose, or that the
/// candidate itself would not be guaranteed, with the utilisations and the bound.
std::string analysis_problem(const RtpuSpec& rtpu, const std::vector<muf::TaskSpec>& running,
                             const muf::TaskSpec& candidate);

/// The whole admission of a task at `hz` (its period 1/hz): "" when both
/// rate_problem and analysis_problem are empty, else the first problem.
std::string admission_problem(const RtpuSpec& rtpu, double hz, const std::vector<muf::TaskSpec>& running,
                              const muf::TaskSpec& candidate);

}  // namespace chimera::cli
