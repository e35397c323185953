// chimera/muf/sim.hpp — a deterministic discrete-event simulator of one RTPU.
//
// It runs RM, EDF or MUF on a periodic task set in integer ticks and records
// every job's release, start, preemptions, finish and miss. All three policies
// are run by one MUF selection rule (§6.2.3): highest criticality, then earliest
// deadline (when the policy uses it), then highest user priority, then
// first-come-first-served; RM and EDF are MUF with the criticalities that
// assign() gives them. It is the reference the Linux backends are tested against.
#pragma once

#include "chimera/export.hpp"

#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "chimera/muf/analysis.hpp"

namespace chimera::muf {

/// What happens to a job still running at its deadline.
enum class LateJob {
    abort,   ///< the job is dropped at its deadline (the cycle is aborted)
    finish,  ///< the job keeps running and finishes late
};

struct SimTask {
    std::string name;
    std::int64_t period = 0;
    std::int64_t wcet = 0;      ///< every job executes exactly this long
    std::int64_t deadline = 0;  ///< relative; 0 = period
    std::int64_t phase = 0;     ///< first release
    int crit = crit::critical;
    int uprio = 0;
};

struct SimOptions {
    LateJob late = LateJob::abort;
    bool use_deadline = true;   ///< false: the dynamic priority is ignored (RM)
    std::int64_t until = 0;     ///< simulate [0, until)
};

struct SimJob {
    std::size_t task = 0;
    std::size_t index = 0;       ///< 0-based cycle number of its task
    std::int64_t release = 0;
    std::int64_t deadline = 0;   ///< absolute
    std::int64_t start = -1;     ///< -1: never ran
    std::int64_t finish = -1;    ///< -1: did not complete (aborted or still pending)
    std::int64_t executed = 0;
    int preemptions = 0;
    bool missed = false;         ///< deadline passed before completion
    bool aborted = false;        ///< dropped at its deadline (LateJob::abort)
};

/// One stretch of execution of one job.
struct SimSlice {
    std::size_t task = 0;
    std::size_t job = 0;         ///< index into SimResult::jobs
    std::int64_t begin = 0;
    std::int64_t end = 0;
};

struct SimTaskStats {
    std::size_t released = 0;
    std::size_t completed = 0;
    std::size_t missed = 0;
    std::size_t aborted = 0;
    std::size_t preemptions = 0;
};

struct SimResult {
    std::vector<SimJob> jobs;        ///< in release order
    std::vector<SimSlice> timeline;  ///< in time order, contiguous runs merged
    std::vector<SimTaskStats> stats; ///< per task
    std::int64_t until = 0;
};

/// Runs the task set. Throws std::invalid_argument for a non-positive period,
/// a negative WCET or deadline, or until < 0.
CHIMERA_API SimResult simulate(std::span<const SimTask> tasks, const SimOptions& options);

/// Convenience: assigns `policy` with assign() and simulates. Task times must be
/// whole ticks (std::invalid_argument otherwise).
CHIMERA_API SimResult simulate(std::span<const TaskSpec> tasks, Policy policy, LateJob late,
                               std::int64_t until, std::span<const Flow> flows = {});

/// A text Gantt chart, one row per task, one column per `tick_per_column` ticks:
/// '#' running, '-' released and waiting, '!' the column of a missed deadline,
/// '.' nothing to do. A time ruler every 10 columns on top.
CHIMERA_API std::string gantt(std::span<const SimTask> tasks, const SimResult& result,
                              std::int64_t ticks_per_column = 1);

}  // namespace chimera::muf
