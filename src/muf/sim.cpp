// Discrete-event simulator: see include/chimera/muf/sim.hpp.
#include "chimera/muf/sim.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

namespace chimera::muf {

namespace {

constexpr std::int64_t never = std::numeric_limits<std::int64_t>::max();

std::int64_t rel_deadline(const SimTask& t) { return t.deadline > 0 ? t.deadline : t.period; }

}  // namespace

SimResult simulate(std::span<const SimTask> tasks, const SimOptions& options) {
    for (const auto& t : tasks) {
        if (t.period <= 0) throw std::invalid_argument("task " + t.name + ": period must be > 0");
        if (t.wcet < 0 || t.deadline < 0 || t.phase < 0)
            throw std::invalid_argument("task " + t.name + ": negative time");
    }
    if (options.until < 0) throw std::invalid_argument("simulate: until must be >= 0");

    SimResult r;
    r.until = options.until;
    r.stats.resize(tasks.size());
    std::vector<std::int64_t> next_release(tasks.size());
    std::vector<std::size_t> cycles(tasks.size(), 0);
    for (std::size_t i = 0; i < tasks.size(); ++i) next_release[i] = tasks[i].phase;
    std::vector<std::size_t> active;  // job indices released, not finished, not aborted

    // MUF selection: criticality, earliest deadline, user priority, FCFS.
    const auto before = [&](std::size_t a, std::size_t b) {
        const SimJob& ja = r.jobs[a];
        const SimJob& jb = r.jobs[b];
        const SimTask& ta = tasks[ja.task];
        const SimTask& tb = tasks[jb.task];
        if (ta.crit != tb.crit) return ta.crit > tb.crit;
        if (options.use_deadline && ja.deadline != jb.deadline) return ja.deadline < jb.deadline;
        if (ta.uprio != tb.uprio) return ta.uprio > tb.uprio;
        if (ja.release != jb.release) return ja.release < jb.release;
        return ja.task < jb.task;
    };

    // Deadlines that fall at `t`: mark missed; abort if asked.
    const auto check_deadlines = [&](std::int64_t t) {
        for (std::size_t k = 0; k < active.size();) {
            SimJob& j = r.jobs[active[k]];
            if (!j.missed && j.deadline <= t) {
                j.missed = true;
                ++r.stats[j.task].missed;
                if (options.late == LateJob::abort) {
                    j.aborted = true;
                    ++r.stats[j.task].aborted;
                    active.erase(active.begin() + static_cast<std::ptrdiff_t>(k));
                    continue;
                }
            }
            ++k;
        }
    };

    std::int64_t t = 0;
    constexpr std::size_t none = std::numeric_limits<std::size_t>::max();
    std::size_t running = none;  // job that ran in the previous slice
    while (t < options.until) {
        check_deadlines(t);
        for (std::size_t i = 0; i < tasks.size(); ++i) {
            if (next_release[i] != t) continue;
            SimJob j;
            j.task = i;
            j.index = cycles[i]++;
            j.release = t;
            j.deadline = t + rel_deadline(tasks[i]);
            r.jobs.push_back(j);
            ++r.stats[i].released;
            next_release[i] += tasks[i].period;
            if (tasks[i].wcet == 0) {  // nothing to run: done at release
                r.jobs.back().start = r.jobs.back().finish = t;
                ++r.stats[i].completed;
            } else {
                active.push_back(r.jobs.size() - 1);
            }
        }

        std::int64_t next = options.until;
        for (std::int64_t nr : next_release) next = std::min(next, nr);
        for (std::size_t k : active)
            if (!r.jobs[k].missed) next = std::min(next, r.jobs[k].deadline);

        if (active.empty()) {
            running = none;
            t = next;
            continue;
        }
        const std::size_t pick = *std::min_element(active.begin(), active.end(), before);
        SimJob& j = r.jobs[pick];
        if (running != none && running != pick) {
            // The previous job was displaced while it still had work: a preemption.
            const auto it = std::find(active.begin(), active.end(), running);
            if (it != active.end()) {
                ++r.jobs[running].preemptions;
                ++r.stats[r.jobs[running].task].preemptions;
            }
        }
        if (j.start < 0) j.start = t;
        const std::int64_t end = std::min(next, t + (tasks[j.task].wcet - j.executed));
        j.executed += end - t;
        if (!r.timeline.empty() && r.timeline.back().job == pick && r.timeline.back().end == t)
            r.timeline.back().end = end;
        else
            r.timeline.push_back({j.task, pick, t, end});
        running = pick;
        if (j.executed == tasks[j.task].wcet) {
            j.finish = end;
            ++r.stats[j.task].completed;
            active.erase(std::find(active.begin(), active.end(), pick));
            running = none;
        }
        t = end;
    }
    check_deadlines(options.until);
    return r;
}

SimResult simulate(std::span<const TaskSpec> tasks, Policy policy, LateJob late,
                   std::int64_t until, std::span<const Flow> flows) {
    const Assignment a = assign(tasks, policy, flows);
    std::vector<SimTask> sim(tasks.size());
    const auto whole = [](double v, const std::string& name, const char* what) {
        const double r = std::round(v);
        if (std::abs(v - r) > 1e-9)
            throw std::invalid_argument("task " + name + ": " + what + " is not a whole tick");
        return static_cast<std::int64_t>(r);
    };
    for (std::size_t i = 0; i < tasks.size(); ++i) {
        sim[i].name = tasks[i].name;
        sim[i].period = whole(tasks[i].period, tasks[i].name, "PERIOD");
        sim[i].wcet = whole(tasks[i].wcet, tasks[i].name, "WCET");
        sim[i].deadline = whole(tasks[i].deadline, tasks[i].name, "DEADLINE");
        sim[i].crit = a.crit[i];
        sim[i].uprio = a.uprio[i];
    }
    SimOptions o;
    o.late = late;
    o.use_deadline = a.uses_deadline;
    o.until = until;
    return simulate(sim, o);
}

std::string gantt(std::span<const SimTask> tasks, const SimResult& result,
                  std::int64_t ticks_per_column) {
    if (ticks_per_column < 1) ticks_per_column = 1;
    const auto columns = static_cast<std::size_t>((result.until + ticks_per_column - 1) / ticks_per_column);
    std::size_t width = 4;
    for (const auto& t : tasks) width = std::max(width, t.name.size());

    std::string out(width + 1, ' ');
    std::string ruler(columns, ' ');
    for (std::size_t c = 0; c < columns; c += 10) {
        const std::string label = std::to_string(static_cast<std::int64_t>(c) * ticks_per_column);
        if (c + label.size() <= columns) ruler.replace(c, label.size(), label);
    }
    out += "|" + ruler + "\n";

    for (std::size_t i = 0; i < tasks.size(); ++i) {
        std::string row(columns, '.');
        const auto col = [&](std::int64_t t) { return static_cast<std::size_t>(t / ticks_per_column); };
        for (const auto& j : result.jobs) {
            if (j.task != i) continue;
            std::int64_t end = j.finish >= 0 ? j.finish : (j.aborted ? j.deadline : result.until);
            end = std::min(end, result.until);
            for (std::int64_t t = j.release; t < end; t += 1)
                if (row[col(t)] == '.') row[col(t)] = '-';
        }
        for (const auto& s : result.timeline)
            if (s.task == i)
                for (std::int64_t t = s.begin; t < s.end; ++t) row[col(t)] = '#';
        for (const auto& j : result.jobs)
            if (j.task == i && j.missed && j.deadline <= result.until && j.deadline > 0)
                row[col(j.deadline - 1)] = '!';  // the last tick the job had
        std::string name = tasks[i].name;
        name.resize(width, ' ');
        out += name + " |" + row + "\n";
    }
    return out;
}

}  // namespace chimera::muf
