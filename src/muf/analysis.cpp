// Schedulability analysis: see include/chimera/muf/analysis.hpp.
#include "chimera/muf/analysis.hpp"

#include <algorithm>
#include <cmath>
#include <numeric>

namespace chimera::muf {

std::string_view to_string(Policy policy) noexcept {
    switch (policy) {
        case Policy::rm: return "rm";
        case Policy::edf: return "edf";
        case Policy::muf: return "muf";
    }
    return "?";
}

std::optional<Policy> parse_policy(std::string_view text) noexcept {
    if (text == "rm" || text == "RM") return Policy::rm;
    if (text == "edf" || text == "EDF") return Policy::edf;
    if (text == "muf" || text == "MUF") return Policy::muf;
    return std::nullopt;
}

std::string_view to_string(Server server) noexcept {
    switch (server) {
        case Server::rds: return "RDS";
        case Server::rss: return "RSS";
        case Server::mds: return "MDS";
        case Server::mss: return "MSS";
    }
    return "?";
}

double utilisation(std::span<const TaskSpec> tasks) noexcept {
    double u = 0;
    for (const auto& t : tasks) u += t.reserved() / t.period;
    return u;
}

double rm_bound(std::size_t n) noexcept {
    if (n == 0) return 1.0;
    const double nn = static_cast<double>(n);
    return nn * (std::pow(2.0, 1.0 / nn) - 1.0);
}

std::vector<std::size_t> rm_order(std::span<const TaskSpec> tasks) {
    std::vector<std::size_t> order(tasks.size());
    std::iota(order.begin(), order.end(), std::size_t{0});
    std::stable_sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) {
        if (tasks[a].period != tasks[b].period) return tasks[a].period < tasks[b].period;
        return tasks[a].relative_deadline() < tasks[b].relative_deadline();
    });
    return order;
}

namespace {

// C/min(D,T): the utilisation tests assume D = T; a shorter deadline is
// accounted as if it were the period (sufficient, never optimistic).
double density(const TaskSpec& t) noexcept {
    return t.reserved() / std::min(t.period, t.relative_deadline());
}

// Rounding must not throw a task out of a set that fits exactly (U = 1.0).
constexpr double slack = 1e-12;

}  // namespace

CriticalSet critical_set(std::span<const TaskSpec> tasks, Policy policy) {
    CriticalSet set;
    set.member.assign(tasks.size(), false);
    switch (policy) {
        case Policy::rm: {
            double u = 0;
            std::size_t s = 0;
            for (std::size_t i : rm_order(tasks)) {
                const double next = u + density(tasks[i]);
                if (next > rm_bound(s + 1) + slack) break;
                u = next;
                ++s;
                set.member[i] = true;
            }
            set.utilisation = u;
            set.bound = rm_bound(s);
            break;
        }
        case Policy::muf: {
            auto order = rm_order(tasks);
            std::stable_sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) {
                return tasks[a].crit.value_or(crit::critical) >
                       tasks[b].crit.value_or(crit::critical);
            });
            double u = 0;
            for (std::size_t i : order) {
                const double next = u + density(tasks[i]);
                if (next > 1.0 + slack) break;
                u = next;
                set.member[i] = true;
            }
            set.utilisation = u;
            set.bound = 1.0;
            break;
        }
        case Policy::edf: {
            double u = 0;
            for (const auto& t : tasks) u += density(t);
            if (u <= 1.0 + slack) {
                set.member.assign(tasks.size(), true);
                set.utilisation = u;
            }
            set.bound = 1.0;
            break;
        }
    }
    return set;
}

std::vector<int> data_flow_user_priorities(std::span<const TaskSpec> tasks,
                                           std::span<const Flow> flows) {
    const std::size_t n = tasks.size();
    const auto order = rm_order(tasks);
    std::vector<std::size_t> rank(n);
    for (std::size_t r = 0; r < n; ++r) rank[order[r]] = r;

    std::vector<int> indegree(n, 0);
    for (const auto& f : flows)
        if (f.producer < n && f.consumer < n && f.producer != f.consumer) ++indegree[f.consumer];

    std::vector<bool> done(n, false);
    std::vector<int> prio(n, 0);
    for (std::size_t placed = 0; placed < n; ++placed) {
        // Among the tasks whose producers are all placed, the first in rm_order.
        // If none (a cycle), the chain goes on from where data has arrived: the
        // task with most producers placed (PID, fed by the trajectory, before
        // the robot that feeds it back), then the first in rm_order.
        std::size_t pick = n;
        for (std::size_t i : order)
            if (!done[i] && indegree[i] == 0) { pick = i; break; }
        if (pick == n) {
            int best_fed = -1;
            for (std::size_t i : order) {
                if (done[i]) continue;
                int fed = 0;
                for (const auto& f : flows)
                    if (f.consumer == i && f.producer < n && f.producer != i && done[f.producer]) ++fed;
                if (fed > best_fed) {
                    best_fed = fed;
                    pick = i;
                }
            }
        }
        done[pick] = true;
        prio[pick] = static_cast<int>(n - placed);
        for (const auto& f : flows)
            if (f.producer == pick && f.consumer < n && f.consumer != pick && !done[f.consumer])
                --indegree[f.consumer];
    }
    for (std::size_t i = 0; i < n; ++i)
        if (tasks[i].uprio) prio[i] = *tasks[i].uprio;
    return prio;
}

Assignment assign(std::span<const TaskSpec> tasks, Policy policy, std::span<const Flow> flows) {
    Assignment a;
    a.policy = policy;
    a.critical = critical_set(tasks, policy);
    // Step 4 is optional: without data flow, ties are first-come-first-served
    // (rule 4), as in Figure 6.1; explicit user priorities always count.
    if (!flows.empty()) {
        a.uprio = data_flow_user_priorities(tasks, flows);
    } else {
        a.uprio.assign(tasks.size(), 0);
        for (std::size_t i = 0; i < tasks.size(); ++i) a.uprio[i] = tasks[i].uprio.value_or(0);
    }
    a.crit.assign(tasks.size(), crit::critical);
    a.uses_deadline = policy != Policy::rm;
    switch (policy) {
        case Policy::muf:
            for (std::size_t i = 0; i < tasks.size(); ++i)
                a.crit[i] = tasks[i].crit.value_or(a.critical.member[i] ? crit::critical
                                                                        : crit::non_critical);
            break;
        case Policy::rm: {
            // Distinct periods, shortest highest, counted down from 62.
            const auto order = rm_order(tasks);
            int level = 62;
            for (std::size_t r = 0; r < order.size(); ++r) {
                if (r > 0 && tasks[order[r]].period != tasks[order[r - 1]].period)
                    level = std::max(1, level - 1);
                a.crit[order[r]] = level;
            }
            break;
        }
        case Policy::edf:
            break;
    }
    return a;
}

std::uint64_t dynamic_priority(const UrgencyEncoding& enc,
                               std::optional<std::int64_t> ticks_to_deadline) noexcept {
    const std::int64_t inf = enc.infinity_ticks();
    if (!ticks_to_deadline) return 0;
    const std::int64_t r = std::clamp<std::int64_t>(*ticks_to_deadline, 0, inf);
    return static_cast<std::uint64_t>(inf - r);
}

std::uint64_t urgency(const UrgencyEncoding& enc, int crit, std::optional<std::int64_t> ticks,
                      int uprio) noexcept {
    const auto max_of = [](unsigned bits) { return (std::int64_t{1} << bits) - 1; };
    const auto c = static_cast<std::uint64_t>(std::clamp<std::int64_t>(crit, 0, max_of(enc.crit_bits)));
    const auto u = static_cast<std::uint64_t>(std::clamp<std::int64_t>(uprio, 0, max_of(enc.user_bits)));
    return (c << (enc.dyn_bits + enc.user_bits)) | (dynamic_priority(enc, ticks) << enc.user_bits) | u;
}

int criticality_from_frequency(double freq, double minfreq, double maxfreq) noexcept {
    constexpr int lowest = 1, highest = 62;
    if (freq <= minfreq) return lowest;
    if (freq > maxfreq || maxfreq <= minfreq) return highest;
    const double x = std::log(freq / minfreq) / std::log(maxfreq / minfreq);
    return std::clamp(lowest + static_cast<int>(std::floor((highest - lowest) * x + 1e-9)), lowest,
                      highest);
}

double server_max_size(Server server, double u_p) noexcept {
    const double e = std::exp(-u_p);
    switch (server) {
        case Server::rds: return (2 * e - 1) / (2 - e);           // eq. 12
        case Server::rss: return 2 * e - 1;                       // eq. 15
        case Server::mds: return (1 - u_p) / (2 * u_p + 1);       // eq. 22
        case Server::mss: return 2 / (u_p + 1) - 1;               // eq. 25
    }
    return 0;
}

double server_periodic_bound(Server server, double u_s) noexcept {
    switch (server) {
        case Server::rds: return std::log((u_s + 2) / (2 * u_s + 1));  // eq. 11
        case Server::rss: return std::log(2 / (u_s + 1));              // eq. 14
        case Server::mds: return (u_s + 2) / (2 * u_s + 1) - 1;        // eq. 21
        case Server::mss: return 2 / (u_s + 1) - 1;                    // eq. 24
    }
    return 0;
}

double server_schedulable_bound(Server server, double u_s) noexcept {
    return server_periodic_bound(server, u_s) + u_s;  // W_rds, W_rss, eq. 23, eq. 26
}

double rm_server_periodic_bound(Server server, double u_s, std::size_t m) noexcept {
    if (m < 2) return 0;
    const double k = server == Server::rds ? (u_s + 2) / (2 * u_s + 1) : 2 / (u_s + 1);
    const double mm = static_cast<double>(m - 1);
    return mm * (std::pow(k, 1.0 / mm) - 1);  // eq. 10 (RDS), eq. 13 (RSS)
}

double rm_server_max_size(Server server, double u_p, std::size_t m) noexcept {
    if (m < 2) return 1;
    const double mm = static_cast<double>(m - 1);
    const double k = std::pow(u_p / mm + 1, mm);
    return server == Server::rds ? (2 - k) / (2 * k - 1) : 2 / k - 1;
}

std::uint64_t ExecutionProfile::total() const noexcept {
    return std::accumulate(counts.begin(), counts.end(), std::uint64_t{0});
}

double ExecutionProfile::psi(double t) const noexcept {
    const std::uint64_t n = total();
    if (n == 0) return 0;
    std::uint64_t done = 0;
    for (std::size_t k = 0; k < counts.size(); ++k) {
        if (static_cast<double>(k + 1) * bin_width > t + 1e-12 * bin_width) break;
        done += counts[k];
    }
    return static_cast<double>(done) / static_cast<double>(n);
}

double ExecutionProfile::worst_case() const noexcept {
    for (std::size_t k = counts.size(); k-- > 0;)
        if (counts[k] != 0) return static_cast<double>(k + 1) * bin_width;
    return 0;
}

double ExecutionProfile::effective(double hardness) const noexcept {
    const std::uint64_t n = total();
    if (n == 0) return 0;
    std::uint64_t done = 0;
    for (std::size_t k = 0; k < counts.size(); ++k) {
        done += counts[k];
        // done/n >= hardness, compared without dividing so 0.9 of 10 is exactly 9.
        if (static_cast<double>(done) >= hardness * static_cast<double>(n) - 1e-9)
            return static_cast<double>(k + 1) * bin_width;
    }
    return worst_case();
}

double effective_execution_time(std::span<const double> samples, double hardness) {
    if (samples.empty()) return 0;
    std::vector<double> sorted(samples.begin(), samples.end());
    std::sort(sorted.begin(), sorted.end());
    const double need = hardness * static_cast<double>(sorted.size()) - 1e-9;
    auto k = static_cast<std::size_t>(std::max(0.0, std::ceil(need)));
    k = std::clamp<std::size_t>(k, 1, sorted.size());
    return sorted[k - 1];
}

unsigned guaranteed_one_in(double wcet, double effective) noexcept {
    if (effective <= 0) return 0;
    return static_cast<unsigned>(std::max(1.0, std::ceil(wcet / effective - 1e-9)));
}

}  // namespace chimera::muf
