// chimsched — schedulability analysis and simulation of a task-set file (thesis ch. 6).
//
//   chimsched analyze FILE [--policy rm|edf|muf] [--json]
//   chimsched simulate FILE [--policy rm|edf|muf] [--until T] [--late abort|finish]
//                          [--columns N] [--json]
//
// simulate's defaults reproduce Figure 6.1 (§6.2.2): without --policy the three
// schedules RM, EDF and MUF one after another, as the figure's (a), (b), (c);
// without --until one hyperperiod (the least common multiple of the periods);
// a job still running at its deadline is aborted there (--late abort), as the
// figure draws it: its task's next job starts fresh. With --late finish the
// late job runs on, and under EDF's overload the lateness then spreads to every
// task after the first 30 time units (a domino the figure does not show).
#include "tool_cli.hpp"

#include <chimera/cfg.hpp>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include <cmath>
#include <cstdint>
#include <iterator>
#include <numeric>
#include <cstdio>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

#include "chimera/cfg.hpp"
#include "chimera/muf.hpp"

namespace muf = chimera::muf;
using nlohmann::json;

namespace {

std::string fmt(double v, int prec = 4) {
    char buf[64];
    std::snprintf(buf, sizeof buf, "%.*f", prec, v);
    return buf;
}

std::vector<std::string> names_of(const muf::TaskSet& set, const std::vector<bool>& member) {
    std::vector<std::string> out;
    for (std::size_t i = 0; i < set.tasks.size(); ++i)
        if (member[i]) out.push_back(set.tasks[i].name);
    return out;
}

std::string join(const std::vector<std::string>& v) {
    if (v.empty()) return "(none)";
    std::string s;
    for (const auto& x : v) s += (s.empty() ? "" : " ") + x;
    return s;
}

int analyze(const muf::TaskSet& set, muf::Policy policy, bool as_json) {
    const double u = muf::utilisation(set.tasks);
    const std::size_t n = set.tasks.size();
    const muf::Policy all[] = {muf::Policy::rm, muf::Policy::edf, muf::Policy::muf};
    muf::CriticalSet sets[3];
    for (int p = 0; p < 3; ++p) sets[p] = muf::critical_set(set.tasks, all[p]);
    const muf::Assignment chosen = muf::assign(set.tasks, policy, set.flows);
    const muf::CriticalSet& mine = sets[static_cast<int>(policy)];
    // Servers are sized against the periodic load if it leaves room for one.
    const bool servers = u < 1.0;

    if (as_json) {
        json j;
        j["file"] = set.file;
        j["policy"] = muf::to_string(policy);
        j["utilisation"] = u;
        j["rm_bound"] = muf::rm_bound(n);
        j["tasks"] = json::array();
        for (std::size_t i = 0; i < n; ++i) {
            const auto& t = set.tasks[i];
            json jt = {{"name", t.name},
                       {"period", t.period},
                       {"wcet", t.wcet},
                       {"deadline", t.relative_deadline()},
                       {"utilisation", t.reserved() / t.period},
                       {"critical", mine.member[i]},
                       {"critical_rm", sets[0].member[i]},
                       {"critical_edf", sets[1].member[i]},
                       {"critical_muf", sets[2].member[i]},
                       {"crit", chosen.crit[i]},
                       {"uprio", chosen.uprio[i]}};
            if (t.effective > 0) {
                jt["effective"] = t.effective;
                jt["one_in"] = muf::guaranteed_one_in(t.wcet, t.effective);
            }
            j["tasks"].push_back(jt);
        }
        for (int p = 0; p < 3; ++p)
            j["critical_sets"][std::string(muf::to_string(all[p]))] = {
                {"tasks", names_of(set, sets[p].member)},
                {"utilisation", sets[p].utilisation},
                {"bound", sets[p].bound}};
        if (servers)
            for (auto s : {muf::Server::rds, muf::Server::rss, muf::Server::mds, muf::Server::mss}) {
                const double size = muf::server_max_size(s, u);
                j["servers"][std::string(muf::to_string(s))] = {
                    {"max_size", std::max(0.0, size)},
                    {"schedulable_bound", size > 0 ? u + size : u}};
            }
        std::cout << j.dump(2) << "\n";
        return 0;
    }

    std::cout << "task set " << set.file << ": " << n << " tasks, U = " << fmt(u)
              << ", RM bound W_" << n << " = " << fmt(muf::rm_bound(n)) << "\n\n";
    std::size_t w = 4;
    for (const auto& t : set.tasks) w = std::max(w, t.name.size());
    char line[256];
    std::snprintf(line, sizeof line, "%-*s %10s %10s %10s %8s  %-3s %-3s %-3s  %4s %5s\n",
                  static_cast<int>(w), "task", "period", "wcet", "deadline", "U", "rm", "edf",
                  "muf", "crit", "uprio");
    std::cout << line;
    for (std::size_t i = 0; i < n; ++i) {
        const auto& t = set.tasks[i];
        const auto yes = [](bool b) { return b ? "yes" : "-"; };
        std::snprintf(line, sizeof line, "%-*s %10s %10s %10s %8s  %-3s %-3s %-3s  %4d %5d\n",
                      static_cast<int>(w), t.name.c_str(), chimera::cfg::number_text(t.period).c_str(),
                      chimera::cfg::number_text(t.wcet).c_str(), chimera::cfg::number_text(t.relative_deadline()).c_str(),
                      fmt(t.reserved() / t.period).c_str(), yes(sets[0].member[i]),
                      yes(sets[1].member[i]), yes(sets[2].member[i]), chosen.crit[i],
                      chosen.uprio[i]);
        std::cout << line;
    }
    std::cout << "\ncritical set RM:  " << join(names_of(set, sets[0].member)) << "  (U = "
              << fmt(sets[0].utilisation) << " <= W = " << fmt(sets[0].bound) << ")\n";
    std::cout << "critical set EDF: " << join(names_of(set, sets[1].member))
              << (u > 1.0 ? "  (overload: EDF cannot say which task fails)" : "  (U <= 1)")
              << "\n";
    std::cout << "critical set MUF: " << join(names_of(set, sets[2].member)) << "  (U = "
              << fmt(sets[2].utilisation) << " <= 1)\n";
    std::cout << "\n" << muf::to_string(policy) << " assignment (crit, uprio):";
    for (std::size_t i = 0; i < n; ++i)
        std::cout << " " << set.tasks[i].name << "=" << chosen.crit[i] << "/" << chosen.uprio[i];
    std::cout << "\n";
    for (std::size_t i = 0; i < n; ++i) {
        const auto& t = set.tasks[i];
        if (t.effective > 0)
            std::cout << "soft task " << t.name << ": E = " << chimera::cfg::number_text(t.effective)
                      << ", completes at least one cycle in every "
                      << muf::guaranteed_one_in(t.wcet, t.effective) << "\n";
    }
    if (servers) {
        std::cout << "\naperiodic server for U_p = " << fmt(u) << ":  max size / schedulable bound\n";
        for (auto s : {muf::Server::rds, muf::Server::rss, muf::Server::mds, muf::Server::mss}) {
            const double size = std::max(0.0, muf::server_max_size(s, u));
            std::cout << "  " << muf::to_string(s) << "  " << fmt(size) << " / " << fmt(u + size)
                      << "\n";
        }
    }
    return 0;
}

// Simulation runs in integer ticks: the smallest power of ten that makes every
// time in the file (and --until) whole.
double tick_scale(const muf::TaskSet& set, double until) {
    const auto whole = [](double v, double s) { return std::abs(v * s - std::round(v * s)) < 1e-9 * std::max(1.0, v * s); };
    for (double s = 1; s <= 1e6; s *= 10) {
        bool ok = whole(until, s);
        for (const auto& t : set.tasks)
            ok = ok && whole(t.period, s) && whole(t.wcet, s) && whole(t.deadline, s);
        if (ok) return s;
    }
    return 0;
}

// The least common multiple of the periods, in the file's time unit; 0 when it
// is not a whole number of ticks or above a million of them (give --until).
double hyperperiod(const muf::TaskSet& set) {
    const double scale = tick_scale(set, 0);
    if (scale == 0 || set.tasks.empty()) return 0;
    std::int64_t lcm = 1;
    for (const auto& t : set.tasks) {
        const auto p = static_cast<std::int64_t>(std::llround(t.period * scale));
        if (p <= 0) return 0;
        lcm = std::lcm(lcm, p);
        if (lcm > 1'000'000) return 0;
    }
    return static_cast<double>(lcm) / scale;
}

int simulate(const muf::TaskSet& set, muf::Policy policy, double until, muf::LateJob late,
             std::size_t columns, bool as_json) {
    const double scale = tick_scale(set, until);
    if (scale == 0) {
        std::cerr << "chimsched: " << set.file
                  << ": times need more than 6 decimal places to simulate\n";
        return 1;
    }
    std::vector<muf::TaskSpec> ticks = set.tasks;
    for (auto& t : ticks) {
        t.period = std::round(t.period * scale);
        t.wcet = std::round(t.wcet * scale);
        t.deadline = std::round(t.deadline * scale);
        t.effective = t.effective > 0 ? std::round(t.effective * scale) : 0;
    }
    const muf::Assignment a = muf::assign(set.tasks, policy, set.flows);
    std::vector<muf::SimTask> sim(ticks.size());
    for (std::size_t i = 0; i < ticks.size(); ++i)
        sim[i] = {ticks[i].name, static_cast<std::int64_t>(ticks[i].period),
                  static_cast<std::int64_t>(ticks[i].wcet), static_cast<std::int64_t>(ticks[i].deadline),
                  0, a.crit[i], a.uprio[i]};
    muf::SimOptions o;
    o.late = late;
    o.use_deadline = a.uses_deadline;
    o.until = static_cast<std::int64_t>(std::round(until * scale));
    const muf::SimResult r = muf::simulate(sim, o);
    const auto t_of = [&](std::int64_t t) { return static_cast<double>(t) / scale; };

    if (as_json) {
        json j;
        j["file"] = set.file;
        j["policy"] = muf::to_string(policy);
        j["late"] = late == muf::LateJob::abort ? "abort" : "finish";
        j["until"] = until;
        j["tasks"] = json::array();
        for (std::size_t i = 0; i < sim.size(); ++i) {
            const auto& s = r.stats[i];
            j["tasks"].push_back({{"name", sim[i].name},
                                  {"crit", a.crit[i]},
                                  {"uprio", a.uprio[i]},
                                  {"released", s.released},
                                  {"completed", s.completed},
                                  {"misses", s.missed},
                                  {"aborted", s.aborted},
                                  {"preemptions", s.preemptions}});
        }
        j["jobs"] = json::array();
        for (const auto& job : r.jobs) {
            json jj = {{"task", sim[job.task].name},
                       {"cycle", job.index},
                       {"release", t_of(job.release)},
                       {"deadline", t_of(job.deadline)},
                       {"preemptions", job.preemptions},
                       {"missed", job.missed},
                       {"aborted", job.aborted}};
            jj["start"] = job.start >= 0 ? json(t_of(job.start)) : json(nullptr);
            jj["finish"] = job.finish >= 0 ? json(t_of(job.finish)) : json(nullptr);
            j["jobs"].push_back(jj);
        }
        std::cout << j.dump(2) << "\n";
        return 0;
    }

    const std::int64_t per_column =
        columns == 0 ? 1 : std::max<std::int64_t>(1, (o.until + static_cast<std::int64_t>(columns) - 1) /
                                                         static_cast<std::int64_t>(columns));
    std::cout << muf::to_string(policy) << " schedule of " << set.file << " over [0, "
              << chimera::cfg::number_text(until) << "), late jobs "
              << (late == muf::LateJob::abort ? "aborted at their deadline (as Figure 6.1; --late finish: run on)"
                                              : "finish late (--late finish; Figure 6.1 aborts them: --late abort)")
              << "; one column = " << chimera::cfg::number_text(t_of(per_column))
              << "  (# running, - waiting, ! missed deadline)\n";
    std::cout << muf::gantt(sim, r, per_column) << "\n";
    std::size_t w = 4;
    for (const auto& t : sim) w = std::max(w, t.name.size());
    char line[256];
    std::snprintf(line, sizeof line, "%-*s %4s %5s %8s %9s %7s %7s %11s\n", static_cast<int>(w),
                  "task", "crit", "uprio", "released", "completed", "misses", "aborted", "preemptions");
    std::cout << line;
    for (std::size_t i = 0; i < sim.size(); ++i) {
        const auto& s = r.stats[i];
        std::snprintf(line, sizeof line, "%-*s %4d %5d %8zu %9zu %7zu %7zu %11zu\n",
                      static_cast<int>(w), sim[i].name.c_str(), a.crit[i], a.uprio[i], s.released,
                      s.completed, s.missed, s.aborted, s.preemptions);
        std::cout << line;
    }
    return 0;
}

// Figure 6.1's three schedules: text one after the other, JSON as one array.
int simulate_all(const muf::TaskSet& set, double until, muf::LateJob late, std::size_t columns, bool as_json) {
    const muf::Policy all[] = {muf::Policy::rm, muf::Policy::edf, muf::Policy::muf};
    if (!as_json) {
        for (std::size_t i = 0; i < std::size(all); ++i) {
            if (i) std::cout << "\n";
            if (const int status = simulate(set, all[i], until, late, columns, false)) return status;
        }
        return 0;
    }
    json out = json::array();
    for (const muf::Policy p : all) {
        std::ostringstream one;
        std::streambuf* saved = std::cout.rdbuf(one.rdbuf());
        const int status = simulate(set, p, until, late, columns, true);
        std::cout.rdbuf(saved);
        if (status) return status;
        out.push_back(json::parse(one.str()));
    }
    std::cout << out.dump(2) << "\n";
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    CLI::App app{"chimsched: real-time schedulability analysis and simulation (RM, EDF, MUF)"};
    app.require_subcommand(1);

    std::string file;
    std::string policy_name = "muf";
    bool as_json = false;
    double until = 0;
    std::string late_name = "abort";
    std::size_t columns = 100;

    const auto policy_check = CLI::IsMember({"rm", "edf", "muf", "RM", "EDF", "MUF"});
    auto* an = app.add_subcommand("analyze", "utilisation, bounds, critical sets, MUF assignment, servers");
    an->add_option("FILE", file, "task-set file")->required();
    an->add_option("--policy", policy_name, "policy whose critical set is reported as `critical`")
        ->check(policy_check);
    an->add_flag("--json", as_json, "machine-readable output");

    auto* sim = app.add_subcommand("simulate", "simulate the task set and print a Gantt chart");
    sim->add_option("FILE", file, "task-set file")->required();
    auto* sim_policy = sim->add_option("--policy", policy_name, "rm, edf or muf (default: all three, as Figure 6.1)")
                           ->check(policy_check);
    sim->add_option("--until", until, "simulate [0, T) (default: one hyperperiod)")->check(CLI::PositiveNumber);
    sim->add_option("--late", late_name,
                    "a job at its deadline: abort (default, as Figure 6.1 draws it) or finish (run on late)")
        ->check(CLI::IsMember({"finish", "abort"}));
    sim->add_option("--columns", columns, "widest Gantt chart (0: one column per tick)");
    sim->add_flag("--json", as_json, "machine-readable output");

    chimera::tools::add_version(app, "chimsched");
    if (const int status = chimera::tools::parse(app, argc, argv); status >= 0) return status;

    try {
        const muf::TaskSet set = muf::read_task_set(file);
        const muf::Policy policy = *muf::parse_policy(policy_name);
        if (app.got_subcommand(an)) return analyze(set, policy, as_json);
        if (until == 0) until = hyperperiod(set);
        if (until == 0) {
            std::cerr << "chimsched: " << set.file
                      << ": the periods have no hyperperiod of at most a million ticks; give --until\n";
            return 1;
        }
        const muf::LateJob late = late_name == "abort" ? muf::LateJob::abort : muf::LateJob::finish;
        if (sim_policy->count() > 0) return simulate(set, policy, until, late, columns, as_json);
        return simulate_all(set, until, late, columns, as_json);
    } catch (const chimera::cfg::ParseError& e) {
        std::cerr << e.what() << "\n";
        return 1;
    } catch (const std::exception& e) {
        std::cerr << "chimsched: " << e.what() << "\n";
        return 1;
    }
}
