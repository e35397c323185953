// chimera/muf/analysis.hpp — real-time schedulability analysis (thesis §6.2–6.5).
//
// Pure functions, no threads, no clocks: utilisation (eq. 8), the rate-monotonic
// bound (eq. 9), critical-set selection for RM and MUF (§6.2.1, §6.2.3), MUF
// criticality and user-priority assignment including data-flow order (§6.2.4),
// the urgency encoding of Figure 6.2, the MINFREQ/MAXFREQ logarithmic criticality
// scaling of §4.5.1, the aperiodic servers' sizes and bounds (eq. 10–26) and the
// effective execution time of a soft real-time task (§6.4).
//
// Times are in any consistent unit (the analysis only ever uses ratios).
#pragma once

#include "chimera/export.hpp"

#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

namespace chimera::muf {

/// The local scheduling policies of an RTPU (the .sbs SCHEDULER line).
enum class Policy { rm, edf, muf };

CHIMERA_API std::string_view to_string(Policy policy) noexcept;
/// "rm", "edf", "muf" (also upper case, as .sbs files write them).
[[nodiscard]] CHIMERA_API std::optional<Policy> parse_policy(std::string_view text) noexcept;

/// Criticality levels of §6.5.2 (1 lowest .. 6 highest).
namespace crit {
inline constexpr int non_real_time = 1;
inline constexpr int background_server = 2;
inline constexpr int non_critical = 3;
inline constexpr int server_exhausted = 4;
inline constexpr int critical = 5;
inline constexpr int server = 6;
}  // namespace crit

/// One periodic task as the analysis sees it.
struct TaskSpec {
    std::string name;
    double period = 0;       ///< T
    double wcet = 0;         ///< C, worst-case execution time
    double deadline = 0;     ///< relative deadline; 0 means "the start of the next cycle" (= T)
    double effective = 0;    ///< E of a soft task (§6.4); 0 means hard (E = C)
    std::optional<int> crit;   ///< explicit criticality (else assigned)
    std::optional<int> uprio;  ///< explicit user priority (else assigned)

    /// The execution time the analysis reserves: E for a soft task, C otherwise.
    double reserved() const noexcept { return effective > 0 ? effective : wcet; }
    double relative_deadline() const noexcept { return deadline > 0 ? deadline : period; }
};

/// Data flows from `producer` to `consumer` (indices into the task list), §6.2.4.
struct Flow {
    std::size_t producer = 0;
    std::size_t consumer = 0;
};

/// Eq. 8: U = sum of reserved()/T.
CHIMERA_API double utilisation(std::span<const TaskSpec> tasks) noexcept;

/// Eq. 9: W_n = n (2^(1/n) - 1); W_0 is taken as 1.
CHIMERA_API double rm_bound(std::size_t n) noexcept;

/// Indices from shortest to longest period (ties: shorter deadline, then file order).
CHIMERA_API std::vector<std::size_t> rm_order(std::span<const TaskSpec> tasks);

/// The critical set of a policy: the tasks guaranteed to meet every deadline,
/// even in a transient overload.
///  - RM: the longest prefix of rm_order with U_s <= W_s (§6.2.1).
///  - MUF: the first N tasks with total utilisation <= 1, in order of explicit
///    criticality (highest first; tasks without one count as crit::critical),
///    then rm_order (§6.2.3, assignment steps 1–2).
///  - EDF: every task when U <= 1, otherwise none: EDF cannot say which task fails.
/// A task whose deadline is shorter than its period is counted with C/D.
struct CriticalSet {
    std::vector<bool> member;   ///< per task, in file order
    double utilisation = 0;     ///< of the members
    double bound = 0;           ///< the bound they were checked against
};
CHIMERA_API CriticalSet critical_set(std::span<const TaskSpec> tasks, Policy policy);

/// Unique user priorities 1..n (n highest) following the data flow: a producer
/// ranks above its consumers; unrelated tasks in rm_order; a cycle is broken at
/// its shortest-period task. Explicit TaskSpec::uprio values override.
CHIMERA_API std::vector<int> data_flow_user_priorities(std::span<const TaskSpec> tasks,
                                                       std::span<const Flow> flows);

/// The static part of every task's urgency under a policy (the MUF a-priori step).
///  - MUF: criticality 5 for the critical set, 3 for the rest (explicit CRIT wins).
///  - RM: distinct criticalities by period, shortest highest (MUF as a static
///    priority scheduler, §6.2.3); equal periods share one.
///  - EDF: every task the same criticality (MUF as EDF).
struct Assignment {
    Policy policy = Policy::muf;
    std::vector<int> crit;        ///< per task
    std::vector<int> uprio;       ///< per task: data_flow_user_priorities() when flows are
                                  ///< given, else the explicit UPRIO or 0 (first come, first served)
    CriticalSet critical;
    bool uses_deadline = true;    ///< false for RM: the dynamic priority is not used
};
CHIMERA_API Assignment assign(std::span<const TaskSpec> tasks, Policy policy,
                              std::span<const Flow> flows = {});

/// Figure 6.2: an urgency of c criticality bits, d dynamic-priority bits and u
/// user-priority bits, criticality most significant. Defaults are Chimera's: 6
/// criticality bits (62 usable values), d = 20, 6 user-priority bits.
struct UrgencyEncoding {
    unsigned crit_bits = 6;
    unsigned dyn_bits = 20;
    unsigned user_bits = 6;

    /// Deadlines this many ticks away or further count as infinity (2^d - 1).
    std::int64_t infinity_ticks() const noexcept {
        return (std::int64_t{1} << dyn_bits) - 1;
    }
};

/// The dynamic priority: (2^d - 1) - ticks to the deadline, so the earliest
/// deadline is the highest; no deadline, or one 2^d - 1 ticks or more away, is 0
/// (infinity); a deadline already past is the maximum.
CHIMERA_API std::uint64_t dynamic_priority(const UrgencyEncoding& enc,
                                           std::optional<std::int64_t> ticks_to_deadline) noexcept;

/// The encoded urgency; crit and uprio are clamped into their bit ranges.
CHIMERA_API std::uint64_t urgency(const UrgencyEncoding& enc, int crit,
                                  std::optional<std::int64_t> ticks_to_deadline, int uprio) noexcept;

/// §4.5.1: criticality from frequency, logarithmic between MINFREQ and MAXFREQ
/// over the 62 values 1..62 (0 and 63 reserved). f <= minfreq -> 1,
/// f > maxfreq -> 62; otherwise 1 + floor(61 log(f/minfreq) / log(maxfreq/minfreq)).
CHIMERA_API int criticality_from_frequency(double freq, double minfreq, double maxfreq) noexcept;

// --- Aperiodic servers (§6.5, eq. 10–26) ------------------------------------

enum class Server { rds, rss, mds, mss };
CHIMERA_API std::string_view to_string(Server server) noexcept;

/// Maximum server size U_s for a periodic critical set of utilisation u_p:
/// RDS eq. 12, RSS eq. 15, MDS eq. 22, MSS eq. 25 (RM servers in the limit m -> inf).
CHIMERA_API double server_max_size(Server server, double u_p) noexcept;
/// Highest periodic utilisation U_p that still meets all deadlines with a server
/// of size u_s: RDS eq. 11, RSS eq. 14, MDS eq. 21, MSS eq. 24.
CHIMERA_API double server_periodic_bound(Server server, double u_s) noexcept;
/// Worst-case schedulable bound W = U_p + U_s as a function of the server size:
/// W_rds, W_rss, eq. 23 (MDS), eq. 26 (MSS).
CHIMERA_API double server_schedulable_bound(Server server, double u_s) noexcept;
/// The RM servers for m tasks in the critical set (server included), eq. 10 and 13.
CHIMERA_API double rm_server_periodic_bound(Server server, double u_s, std::size_t m) noexcept;
/// Inverse of rm_server_periodic_bound: the largest server for u_p and m tasks.
CHIMERA_API double rm_server_max_size(Server server, double u_p, std::size_t m) noexcept;

// --- Soft real-time tasks (§6.4) --------------------------------------------

/// A task execution profile as a histogram: counts[k] cycles took a time in
/// (k * bin_width, (k + 1) * bin_width]. Psi(t) is the fraction of cycles done by t.
struct CHIMERA_API ExecutionProfile {
    double bin_width = 1;
    std::vector<std::uint64_t> counts;

    std::uint64_t total() const noexcept;
    /// Psi at the upper edge of bin k, i.e. the fraction of cycles finished by (k+1)w.
    double psi(double t) const noexcept;
    /// C: the smallest t with Psi(t) = 1 (upper edge of the last non-empty bin).
    double worst_case() const noexcept;
    /// E: the smallest t with Psi(t) >= hardness (§6.4); hardness 1 gives C.
    double effective(double hardness) const noexcept;
};

/// E from raw per-cycle execution times: the smallest sample s with at least a
/// fraction `hardness` of the samples <= s. 0 for no samples.
CHIMERA_API double effective_execution_time(std::span<const double> samples, double hardness);

/// The one-in-n guarantee: the smallest n with C <= n E; a soft task reserved E
/// completes at least one cycle in every n. 0 when E <= 0.
CHIMERA_API unsigned guaranteed_one_in(double wcet, double effective) noexcept;

}  // namespace chimera::muf
