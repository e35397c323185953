// The .rmod and .sbs readers (see include/chimera/sbs_files.hpp for the formats).
#include "chimera/sbs_files.hpp"

#include <sched.h>

#include <cstdio>
#include <algorithm>
#include <cctype>
#include <cmath>
#include <filesystem>
#include <set>
#include <stdexcept>

namespace chimera {

namespace {

std::string join(const std::vector<std::string>& v, std::string_view sep) {
    std::string out;
    for (std::size_t i = 0; i < v.size(); ++i) {
        if (i) out += sep;
        out += v[i];
    }
    return out;
}

// INCONST/OUTCONST/INVAR/OUTVAR: names, or the single word `none`.
std::vector<std::string> port_list(const cfg::Reader& r, const cfg::Line& l, std::set<std::string>& seen) {
    if (l.args.empty()) r.fail(l, l.keyword + " needs port names or 'none'");
    if (l.args.size() == 1 && l.args[0] == "none") return {};
    for (const auto& a : l.args) {
        if (a == "none") r.fail(l, l.keyword + ": 'none' cannot be mixed with port names");
        if (!seen.insert(a).second) r.fail(l, "port '" + a + "' is listed twice");
    }
    return l.args;
}

bool positive_finite(double v) { return std::isfinite(v) && v > 0.0; }

}  // namespace

std::string_view to_string(TaskType t) noexcept {
    switch (t) {
        case TaskType::periodic: return "periodic";
        case TaskType::synchronous: return "synchronous";
        case TaskType::sporadic: return "sporadic";
        case TaskType::deferrable: return "deferrable";
        case TaskType::background: return "background";
    }
    return "?";
}

char status_letter(TaskType t) noexcept {
    switch (t) {
        case TaskType::periodic: return 'P';
        case TaskType::synchronous: return 'Y';
        case TaskType::sporadic: return 'S';
        case TaskType::deferrable: return 'D';
        case TaskType::background: return 'B';
    }
    return '?';
}

std::string_view to_string(Scheduler s) noexcept {
    switch (s) {
        case Scheduler::RM: return "RM";
        case Scheduler::EDF: return "EDF";
        case Scheduler::MUF: return "MUF";
    }
    return "?";
}
std::string_view to_string(Usage u) noexcept { return u == Usage::exclusive ? "exclusive" : "shared"; }
std::string_view to_string(ErrPrint e) noexcept {
    switch (e) {
        case ErrPrint::errors: return "errors";
        case ErrPrint::warnings: return "warnings";
        case ErrPrint::none: return "none";
    }
    return "?";
}
std::string_view to_string(Backend b) noexcept {
    switch (b) {
        case Backend::fifo: return "fifo";
        case Backend::deadline: return "deadline";
        case Backend::other: return "other";
    }
    return "?";
}

// ---------------------------------------------------------------- LocalConfig

const LocalConfig::Entry* LocalConfig::find(std::string_view key) const noexcept {
    for (const auto& e : entries_)
        if (e.key == key) return &e;
    return nullptr;
}

std::optional<std::string> LocalConfig::text(std::string_view key) const {
    const Entry* e = find(key);
    if (!e) return std::nullopt;
    return join(e->values, " ");
}

namespace {
// Where a LOCAL entry came from: FILE:LINE, or FILE and "set at run time" for a
// value given by sbsSet (line 0), never a misleading FILE:0.
std::string where_of(const std::string& file, const LocalConfig::Entry& e) {
    const std::string f = file.empty() ? std::string("LOCAL") : file;
    return e.line > 0 ? f + ":" + std::to_string(e.line) + ": LOCAL " + e.key
                      : f + ": LOCAL " + e.key + " (set at run time)";
}
}  // namespace

std::vector<double> LocalConfig::numbers(std::string_view key) const {
    const Entry* e = find(key);
    const std::string where = file.empty() ? std::string("LOCAL") : file;
    if (!e) throw std::invalid_argument(where + ": LOCAL key '" + std::string(key) + "' is missing");
    std::vector<double> out;
    out.reserve(e->values.size());
    for (const auto& v : e->values) {
        auto d = cfg::parse_double(v);
        if (!d) throw std::invalid_argument(where_of(file, *e) + ": expected a number, found '" + v + "'");
        out.push_back(*d);
    }
    return out;
}

double LocalConfig::number(std::string_view key, double fallback) const {
    const Entry* e = find(key);
    if (!e) return fallback;
    auto v = numbers(key);
    if (v.size() != 1)
        throw std::invalid_argument(where_of(file, *e) + ": expected one number, found " + std::to_string(v.size()));
    return v[0];
}

void LocalConfig::erase(std::string_view key) {
    std::erase_if(entries_, [&](const Entry& e) { return e.key == key; });
}

void LocalConfig::set(std::string_view key, std::vector<std::string> values, int line) {
    for (auto& e : entries_) {
        if (e.key == key) {
            e.values = std::move(values);
            e.line = line;
            return;
        }
    }
    entries_.push_back(Entry{std::string(key), std::move(values), line});
}

// ---------------------------------------------------------------- .rmod

std::string RmodFile::global_name(std::string_view internal) const {
    for (const auto& [from, to] : aliases)
        if (from == internal) return to;
    return std::string(internal);
}

namespace {
std::vector<std::string> map_names(const RmodFile& r, const std::vector<std::string>& v) {
    std::vector<std::string> out;
    out.reserve(v.size());
    for (const auto& n : v) out.push_back(r.global_name(n));
    return out;
}
}  // namespace

std::vector<std::string> RmodFile::global_in_consts() const { return map_names(*this, in_consts); }
std::vector<std::string> RmodFile::global_out_consts() const { return map_names(*this, out_consts); }
std::vector<std::string> RmodFile::global_in_vars() const { return map_names(*this, in_vars); }
std::vector<std::string> RmodFile::global_out_vars() const { return map_names(*this, out_vars); }

RmodFile parse_rmod(cfg::Reader& r, const std::string& path) {
    RmodFile f;
    f.path = path;
    f.name = std::filesystem::path(path).stem().string();
    f.local.file = r.file();

    cfg::Line l = r.expect("MODULE");
    r.require_args(l, 1);
    f.module = l.args[0];
    for (char c : f.module)
        if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '_'))
            r.fail(l, "MODULE name '" + f.module + "' must be an identifier (letters, digits, _)");

    l = r.expect("DESC");
    f.desc = l.text;

    std::set<std::string> alias_from;
    while (auto a = r.accept("SVARALIAS")) {
        // Either `internal=GLOBAL` or `internal = GLOBAL`.
        std::string joined = join(a->args, "");
        auto eq = joined.find('=');
        if (eq == std::string::npos || eq == 0 || eq + 1 == joined.size() ||
            joined.find('=', eq + 1) != std::string::npos)
            r.fail(*a, "SVARALIAS expects internal=GLOBAL, found '" + a->text + "'");
        std::string from = joined.substr(0, eq), to = joined.substr(eq + 1);
        if (!alias_from.insert(from).second) r.fail(*a, "SVARALIAS: '" + from + "' is aliased twice");
        f.aliases.emplace_back(std::move(from), std::move(to));
    }

    std::set<std::string> seen_inputs, seen_outputs;
    if (auto x = r.accept("INCONST")) f.in_consts = port_list(r, *x, seen_inputs);
    if (auto x = r.accept("OUTCONST")) f.out_consts = port_list(r, *x, seen_outputs);
    if (auto x = r.accept("INVAR")) f.in_vars = port_list(r, *x, seen_inputs);
    if (auto x = r.accept("OUTVAR")) f.out_vars = port_list(r, *x, seen_outputs);

    l = r.expect("TASKTYPE");
    r.require_args(l, 1);
    static const std::pair<std::string_view, TaskType> types[] = {
        {"periodic", TaskType::periodic},     {"synchronous", TaskType::synchronous},
        {"sporadic", TaskType::sporadic},     {"deferrable", TaskType::deferrable},
        {"background", TaskType::background},
    };
    bool found = false;
    for (auto [n, t] : types) {
        if (l.args[0] == n) {
            f.type = t;
            found = true;
        }
    }
    if (!found)
        r.fail(l, "TASKTYPE must be periodic, synchronous, sporadic, deferrable or background, found '" +
                      l.args[0] + "'");

    const cfg::Line* next = r.peek();
    if (next && (next->keyword == "FREQ" || next->keyword == "PERIOD")) {
        cfg::Line t = *r.next();
        r.require_args(t, 1);
        double v = r.to_double(t, 0, t.keyword);
        if (!positive_finite(v)) r.fail(t, t.keyword + " must be a positive number");
        if (const std::string why = frequency_problem(t.keyword == "FREQ" ? v : 1.0 / v); !why.empty())
            r.fail(t, t.keyword + " " + t.args[0] + ": " + why);
        if (t.keyword == "FREQ") {
            f.freq = v;
            f.period = 1.0 / v;
        } else {
            f.period = v;
            f.freq = 1.0 / v;
        }
        const cfg::Line* again = r.peek();
        if (again && (again->keyword == "FREQ" || again->keyword == "PERIOD"))
            r.fail(*again, "FREQ and PERIOD are exclusive: " + t.keyword + " already given at line " +
                               std::to_string(t.number));
    } else if (!is_aperiodic(f.type)) {
        const int at = next ? next->number : r.end_line();
        r.fail(at, "a " + std::string(to_string(f.type)) + " task needs FREQ or PERIOD, found " +
                       (next ? next->keyword : std::string("EOF")));
    }

    // Scheduling parameters (thesis §6.4-6.5, docs/architecture.md §9), each at most once, in any order.
    std::set<std::string> timing;
    for (const cfg::Line* n = r.peek(); n && (n->keyword == "WCET" || n->keyword == "EFFECTIVE" ||
                                           n->keyword == "CRIT");
         n = r.peek()) {
        cfg::Line t = *r.next();
        if (!timing.insert(t.keyword).second) r.fail(t, t.keyword + " given twice");
        r.require_args(t, 1);
        if (t.keyword == "CRIT") {
            const std::int64_t c = r.to_int(t, 0, "CRIT");
            if (c < 1 || c > 62) r.fail(t, "CRIT must be 1..62 (0 and 63 are reserved), found " + t.args[0]);
            f.crit = static_cast<int>(c);
            continue;
        }
        const double v = r.to_double(t, 0, t.keyword);
        if (!positive_finite(v)) r.fail(t, t.keyword + " must be a positive number of seconds");
        (t.keyword == "WCET" ? f.wcet : f.effective) = v;
        if (f.period > 0 && v > f.period)
            r.fail(t, t.keyword + " " + t.args[0] + " s exceeds the period " + std::to_string(f.period) + " s");
        if (f.wcet > 0 && f.effective > f.wcet)
            r.fail(t, "EFFECTIVE (" + std::to_string(f.effective) + " s) exceeds WCET (" + std::to_string(f.wcet) +
                          " s): E is at most C (§6.4)");
    }
    if (f.effective > 0 && f.type != TaskType::periodic)
        r.fail(r.peek() ? r.peek()->number : r.end_line(),
               "EFFECTIVE makes a soft real-time task, which must be periodic (TASKTYPE " +
                   std::string(to_string(f.type)) + ")");
    if ((f.type == TaskType::deferrable || f.type == TaskType::sporadic) && (f.wcet > 0) != (f.period > 0))
        r.fail(r.peek() ? r.peek()->number : r.end_line(),
               "a " + std::string(to_string(f.type)) + " server needs both PERIOD (or FREQ) and WCET (its " +
                   "capacity), or neither (then it serves in the background)");

    if (r.accept("LOCAL")) {
        std::set<std::string> keys;
        while (r.peek() != nullptr) {
            cfg::Line entry = *r.next();
            if (!keys.insert(entry.keyword).second)
                r.fail(entry, "LOCAL key '" + entry.keyword + "' given twice");
            f.local.set(entry.keyword, entry.args, entry.number);
        }
    }
    r.expect_end();
    return f;
}

std::string frequency_problem(double hz) {
    if (!std::isfinite(hz) || !(hz > 0)) return "the frequency must be a positive number of Hz";
    if (hz > kMaxFrequencyHz)
        return cfg::number_text(hz) + " Hz is above the highest task frequency, " + cfg::number_text(kMaxFrequencyHz) +
               " Hz (a period of 1 us)";
    if (hz < kMinFrequencyHz)
        return cfg::number_text(hz) + " Hz is below the lowest task frequency, " + cfg::number_text(kMinFrequencyHz) +
               " Hz (a period of 10^6 s)";
    return {};
}

void check_rtpu_cpus(const SbsFile& f) {
    cpu_set_t allowed;
    CPU_ZERO(&allowed);
    if (sched_getaffinity(0, sizeof(allowed), &allowed) != 0) return;
    for (const auto& r : f.rtpus)
        if (r.cpu >= CPU_SETSIZE || !CPU_ISSET(r.cpu, &allowed))
            throw cfg::ParseError(f.path, r.line,
                                  "RTPU " + r.name + " names CPU " + std::to_string(r.cpu) +
                                      ", which this process may not use (it has " +
                                      std::to_string(CPU_COUNT(&allowed)) + " CPUs)");
}

std::string port_problem(const RmodFile& f, const std::function<bool(const std::string&)>& is_variable,
                         std::string_view svarfile) {
    const std::pair<const char*, const std::vector<std::string>*> lists[] = {
        {"INCONST", &f.in_consts}, {"OUTCONST", &f.out_consts}, {"INVAR", &f.in_vars}, {"OUTVAR", &f.out_vars}};
    for (auto [keyword, list] : lists) {
        for (const auto& port : *list) {
            const std::string g = f.global_name(port);
            if (!is_variable(g))
                return f.path + ": " + keyword + " " + port + (g != port ? " (SVARALIAS " + g + ")" : "") +
                       " is not a variable of the state variable table " + std::string(svarfile);
        }
    }
    return {};
}

std::string combined_problem(const std::vector<RmodFile>& rmods) {
    if (rmods.empty()) return {};
    std::string name;
    for (const auto& f : rmods) name += (name.empty() ? "" : "+") + f.name;
    const RmodFile& first = rmods.front();
    for (const auto& f : rmods)
        if (f.type != first.type || std::fabs(f.freq - first.freq) > 1e-9 * std::max(1.0, first.freq))
            return "combined task " + name + ": " + f.name + " has TASKTYPE " + std::string(to_string(f.type)) +
                   " at " + std::to_string(f.freq) + " Hz, " + first.name + " has " +
                   std::string(to_string(first.type)) + " at " + std::to_string(first.freq) +
                   " Hz; combined objects must run at one rate (§3.8.1)";
    return {};
}

RmodFile read_rmod(const std::string& path) {
    cfg::Reader r = cfg::Reader::from_file(path);
    return parse_rmod(r, path);
}

// ---------------------------------------------------------------- .sbs

const RtpuSpec* SbsFile::find_rtpu(std::string_view name) const noexcept {
    for (const auto& r : rtpus)
        if (r.name == name) return &r;
    return nullptr;
}

namespace {

// TASK RMOD[+RMOD...] [RTPU] [ON|OFF], then its SET KEY VALUE... lines.
TaskLine parse_task_line(cfg::Reader& r, const SbsFile& f) {
    const cfg::Line l = r.expect_one_of({"TASK"});
    r.require_args(l, 1, 3);
    TaskLine t;
    t.line = l.number;
    for (std::size_t at = 0;;) {
        const auto plus = l.args[0].find('+', at);
        t.rmods.push_back(l.args[0].substr(at, plus == std::string::npos ? std::string::npos : plus - at));
        if (t.rmods.back().empty()) r.fail(l, "TASK " + l.args[0] + ": an empty rmod name");
        if (std::find(t.rmods.begin(), t.rmods.end() - 1, t.rmods.back()) != t.rmods.end() - 1)
            r.fail(l, "TASK " + l.args[0] + ": rmod " + t.rmods.back() + " is named twice");
        if (plus == std::string::npos) break;
        at = plus + 1;
    }
    std::size_t next = 1;
    if (next < l.args.size() && l.args[next] != "ON" && l.args[next] != "OFF") {
        t.rtpu = l.args[next++];
        if (!f.find_rtpu(t.rtpu)) r.fail(l, "TASK " + l.args[0] + ": no RTPU " + t.rtpu + " in this file");
    }
    if (next < l.args.size()) t.on = l.args[next++] == "ON";
    if (next < l.args.size()) r.fail(l, "TASK takes RMOD[+RMOD...] [RTPU] [ON|OFF], found '" + l.args[next] + "'");
    for (const TaskLine& other : f.tasks)
        for (const std::string& a : t.rmods)
            if (std::find(other.rmods.begin(), other.rmods.end(), a) != other.rmods.end())
                r.fail(l, "TASK: rmod " + a + " is already a task of line " + std::to_string(other.line));
    while (const cfg::Line* p = r.peek()) {
        if (p->keyword != "SET") break;
        const cfg::Line set = r.expect("SET");
        if (set.args.size() < 2) r.fail(set, "SET takes KEY VALUE... (a LOCAL key of the task above)");
        t.local.push_back({set.args[0], std::vector<std::string>(set.args.begin() + 1, set.args.end()), set.number});
    }
    return t;
}

}  // namespace

SbsFile parse_sbs(cfg::Reader& r, const std::string& base_dir) {
    SbsFile f;
    f.path = r.file();

    cfg::Line l = r.expect("SUBSYSTEM");
    r.require_args(l, 1);
    f.subsystem = l.args[0];
    for (char c : f.subsystem)
        if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '-'))
            r.fail(l, "SUBSYSTEM name '" + f.subsystem + "' may hold only letters, digits, _ and -");

    l = r.expect("SVARFILE");
    r.require_args(l, 1);
    std::filesystem::path svar(l.args[0]);
    if (svar.is_relative() && !base_dir.empty()) svar = std::filesystem::path(base_dir) / svar;
    f.svarfile = svar.lexically_normal().string();

    std::optional<cfg::Line> master = r.accept("MASTER");
    if (master) r.require_args(*master, 1);

    do {
        cfg::Line rl = r.expect("RTPU");
        r.require_args(rl, 1, 2);
        RtpuSpec spec;
        spec.name = rl.args[0];
        spec.line = rl.number;
        if (f.find_rtpu(spec.name)) r.fail(rl, "RTPU '" + spec.name + "' is defined twice");
        // A CPU number is bounded like the kernel's CPU sets (4096), whether given or read from cpuN.
        const bool named_cpu = rl.args.size() == 1;
        auto cpu = !named_cpu ? cfg::parse_int(rl.args[1])
                   : spec.name.rfind("cpu", 0) == 0 ? cfg::parse_int(spec.name.substr(3)) : std::nullopt;
        if (!cpu || *cpu < 0 || *cpu > 4095)
            r.fail(rl, named_cpu ? "RTPU " + spec.name + ": give the CPU it runs on (RTPU name CPU), or name it cpuN"
                                 : "RTPU " + spec.name + ": expected a CPU number 0..4095, found '" + rl.args[1] + "'");
        spec.cpu = static_cast<int>(*cpu);

        std::set<std::string> given;
        while (const cfg::Line* p = r.peek()) {
            if (p->keyword == "RTPU" || p->keyword == "TASK") break;
            cfg::Line o = r.expect_one_of(
                {"SCHEDULER", "USAGE", "ERRPRINT", "MINFREQ", "MAXFREQ", "BACKEND", "ACCOUNTING"});
            if (!given.insert(o.keyword).second)
                r.fail(o, o.keyword + " given twice for RTPU " + spec.name);
            if (o.keyword == "ACCOUNTING") {
                const std::string mode = o.args.empty() ? "" : o.args[0];
                if (mode == "nanoseconds") {
                    r.require_args(o, 1);
                    spec.half_tick = false;
                } else if (mode == "halftick") {
                    if (o.args.size() != 2) r.fail(o, "ACCOUNTING halftick takes the tick in seconds, e.g. halftick 0.001");
                    const double tick = r.to_double(o, 1, "the tick");
                    if (!positive_finite(tick) || tick > 1.0)
                        r.fail(o, "ACCOUNTING halftick: the tick must be more than 0 and at most 1 second");
                    spec.half_tick = true;
                    spec.tick = tick;
                } else {
                    r.fail(o, "ACCOUNTING must be nanoseconds or halftick TICK, found '" + mode + "'");
                }
                continue;
            }
            r.require_args(o, 1);
            const std::string& v = o.args[0];
            if (o.keyword == "SCHEDULER") {
                if (v == "RM") spec.scheduler = Scheduler::RM;
                else if (v == "EDF") spec.scheduler = Scheduler::EDF;
                else if (v == "MUF") spec.scheduler = Scheduler::MUF;
                else r.fail(o, "SCHEDULER must be RM, EDF or MUF, found '" + v + "'");
            } else if (o.keyword == "USAGE") {
                if (v == "exclusive") spec.usage = Usage::exclusive;
                else if (v == "shared") spec.usage = Usage::shared;
                else r.fail(o, "USAGE must be exclusive or shared, found '" + v + "'");
            } else if (o.keyword == "ERRPRINT") {
                if (v == "errors") spec.errprint = ErrPrint::errors;
                else if (v == "warnings") spec.errprint = ErrPrint::warnings;
                else if (v == "none") spec.errprint = ErrPrint::none;
                else r.fail(o, "ERRPRINT must be errors, warnings or none, found '" + v + "'");
            } else if (o.keyword == "BACKEND") {
                if (v == "fifo") spec.backend = Backend::fifo;
                else if (v == "deadline") spec.backend = Backend::deadline;
                else if (v == "other") spec.backend = Backend::other;
                else r.fail(o, "BACKEND must be fifo, deadline or other, found '" + v + "'");
            } else {
                double hz = r.to_double(o, 0, o.keyword);
                if (const std::string why = frequency_problem(hz); !why.empty()) r.fail(o, o.keyword + ": " + why);
                (o.keyword == "MINFREQ" ? spec.minfreq : spec.maxfreq) = hz;
            }
        }
        if (!(spec.minfreq < spec.maxfreq))
            r.fail(rl, "RTPU " + spec.name + ": MINFREQ must be below MAXFREQ");
        f.rtpus.push_back(std::move(spec));
    } while (r.peek() != nullptr && r.peek()->keyword == "RTPU");
    while (r.peek() != nullptr) f.tasks.push_back(parse_task_line(r, f));
    r.expect_end();

    if (master) {
        if (!f.find_rtpu(master->args[0]))
            r.fail(*master, "MASTER names RTPU '" + master->args[0] + "', which is not defined in this file");
        f.master = master->args[0];
    } else {
        f.master = f.rtpus.front().name;
    }
    return f;
}

SbsFile read_sbs(const std::string& path) {
    cfg::Reader r = cfg::Reader::from_file(path);
    return parse_sbs(r, std::filesystem::path(path).parent_path().string());
}

}  // namespace chimera
