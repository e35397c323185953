#include "fields.hpp"

#include <algorithm>
#include <cstdio>
#include <stdexcept>

namespace chimtop {

using chimera::prof::TaskStatus;

namespace {

std::string fmt(const char* f, double v) {
    char buf[64];
    std::snprintf(buf, sizeof buf, f, v);
    return buf;
}

std::string pad(const std::string& s, int width, bool right) {
    if (static_cast<int>(s.size()) >= width) return s;
    const std::string fill(static_cast<std::size_t>(width) - s.size(), ' ');
    return right ? fill + s : s + fill;
}

}  // namespace

const std::vector<Field>& all_fields() {
    static const std::vector<Field> fields = {
        {"rmod", 12, false, "RMOD name of the task"},
        {"rtpu", 4, true, "RTPU the task runs on"},
        {"tid", 7, true, "thread id"},
        {"S", 1, false, "type: P periodic, Y synchronous, S sporadic, D deferrable, B background"},
        {"crit", 4, true, "criticality"},
        {"state", 11, false, "task state"},
        {"cycle", 8, true, "cycles since the last status reset"},
        {"miss", 6, true, "missed cycles since the last status reset"},
        {"refF", 9, true, "reference frequency (Hz)"},
        {"refT", 9, true, "reference period (s)"},
        {"mezF", 9, true, "measured frequency (Hz)"},
        {"mezT", 9, true, "measured period (s), rounded to the tick"},
        {"ptime", 8, true, "profiling time (s)"},
        {"totC", 9, true, "total CPU time in ptime (s)"},
        {"tick", 9, true, "resolution of the profile (s)"},
        {"minU", 6, true, "minimum CPU utilisation in one cycle (%)"},
        {"maxU", 6, true, "maximum CPU utilisation in one cycle (%)"},
        {"avgU", 6, true, "average CPU utilisation per cycle (%)"},
        {"minC", 9, true, "minimum CPU time of one cycle (s)"},
        {"maxC", 9, true, "maximum CPU time of one cycle (s)"},
        {"avgC", 9, true, "average CPU time of one cycle (s)"},
        {"warn", 4, true, "warnings since the last status reset"},
        {"policy", 22, false, "scheduling policy in force"},
        {"clock", 14, false, "source of the CPU times"},
        {"cpu", 3, true, "CPU the task is pinned to"},
    };
    return fields;
}

std::vector<std::string> default_fields() {
    return {"rmod", "rtpu", "tid",  "S",    "crit", "state", "cycle", "miss", "refF", "mezF",
            "mezT", "ptime", "minC", "maxC", "avgC", "avgU", "warn", "policy"};
}

const Field* find_field(std::string_view name) {
    for (const auto& f : all_fields())
        if (name == f.name) return &f;
    return nullptr;
}

std::vector<std::string> parse_fields(std::string_view list) {
    std::vector<std::string> out;
    std::size_t pos = 0;
    while (pos <= list.size()) {
        std::size_t end = list.find_first_of(", ", pos);
        if (end == std::string_view::npos) end = list.size();
        const std::string_view name = list.substr(pos, end - pos);
        if (!name.empty()) {
            if (!find_field(name)) {
                std::string known;
                for (const auto& f : all_fields()) known += std::string(known.empty() ? "" : " ") + f.name;
                throw std::invalid_argument("unknown status field '" + std::string(name) +
                                            "' (fields: " + known + ")");
            }
            out.emplace_back(name);
        }
        pos = end + 1;
    }
    if (out.empty()) throw std::invalid_argument("no status field chosen");
    return out;
}

std::string field_text(const TaskStatus& t, std::string_view f) {
    if (f == "rmod") return t.rmod;
    if (f == "rtpu") return std::to_string(t.rtpu);
    if (f == "tid") return std::to_string(t.tid);
    if (f == "S") return std::string(1, t.type);
    if (f == "crit") return std::to_string(t.crit);
    if (f == "state") return chimera::prof::to_string(t.state);
    if (f == "cycle") return std::to_string(t.cycle);
    if (f == "miss") return std::to_string(t.miss);
    if (f == "refF") return fmt("%.2f", t.ref_f);
    if (f == "refT") return fmt("%.6f", t.ref_t);
    if (f == "mezF") return fmt("%.2f", t.mez_f);
    if (f == "mezT") return fmt("%.6f", t.mez_t);
    if (f == "ptime") return fmt("%.3f", t.ptime);
    if (f == "totC") return fmt("%.6f", t.tot_c);
    if (f == "tick") return fmt("%.0e", t.tick);
    if (f == "minU") return fmt("%.2f", t.min_u);
    if (f == "maxU") return fmt("%.2f", t.max_u);
    if (f == "avgU") return fmt("%.2f", t.avg_u);
    if (f == "minC") return fmt("%.6f", t.min_c);
    if (f == "maxC") return fmt("%.6f", t.max_c);
    if (f == "avgC") return fmt("%.6f", t.avg_c);
    if (f == "warn") return std::to_string(t.warn);
    if (f == "policy") return t.policy.empty() ? "-" : t.policy;
    if (f == "clock") return chimera::prof::to_string(t.cpu_clock);
    if (f == "cpu") return std::to_string(t.cpu);
    return "?";
}

double field_number(const TaskStatus& t, std::string_view f) {
    if (f == "rtpu") return t.rtpu;
    if (f == "tid") return t.tid;
    if (f == "crit") return t.crit;
    if (f == "cycle") return static_cast<double>(t.cycle);
    if (f == "miss") return static_cast<double>(t.miss);
    if (f == "refF") return t.ref_f;
    if (f == "refT") return t.ref_t;
    if (f == "mezF") return t.mez_f;
    if (f == "mezT") return t.mez_t;
    if (f == "ptime") return t.ptime;
    if (f == "totC") return t.tot_c;
    if (f == "tick") return t.tick;
    if (f == "minU") return t.min_u;
    if (f == "maxU") return t.max_u;
    if (f == "avgU") return t.avg_u;
    if (f == "minC") return t.min_c;
    if (f == "maxC") return t.max_c;
    if (f == "avgC") return t.avg_c;
    if (f == "warn") return t.warn;
    if (f == "cpu") return t.cpu;
    return 0;
}

void sort_tasks(std::vector<TaskStatus>& tasks, std::string_view field, bool descending) {
    const Field* f = find_field(field);
    const bool numeric = f && f->numeric;
    std::stable_sort(tasks.begin(), tasks.end(), [&](const TaskStatus& a, const TaskStatus& b) {
        if (numeric) {
            const double x = field_number(a, field), y = field_number(b, field);
            if (x != y) return descending ? x > y : x < y;
        } else {
            const std::string x = field_text(a, field), y = field_text(b, field);
            if (x != y) return descending ? x > y : x < y;
        }
        return a.slot < b.slot;
    });
}

std::string header_line(const std::vector<std::string>& fields) {
    std::string line;
    for (const auto& name : fields) {
        const Field* f = find_field(name);
        if (!line.empty()) line += ' ';
        line += pad(name, f ? f->width : 8, f && f->numeric);
    }
    return line;
}

std::string task_line(const TaskStatus& t, const std::vector<std::string>& fields) {
    std::string line;
    for (const auto& name : fields) {
        const Field* f = find_field(name);
        if (!line.empty()) line += ' ';
        line += pad(field_text(t, name), f ? f->width : 8, f && f->numeric);
    }
    return line;
}

std::vector<std::string> message_lines(const TaskStatus& t) {
    std::vector<std::string> out;
    if (!t.warning.empty()) out.push_back("WARNING> " + t.rmod + ": " + t.warning);
    if (t.state == chimera::prof::TaskState::error || !t.error.empty())
        out.push_back("ERROR> " + t.rmod + ": " + (t.error.empty() ? "(no message)" : t.error));
    return out;
}

std::string plain_text(std::string_view subsystem, const std::vector<TaskStatus>& tasks,
                       const std::vector<std::string>& fields) {
    std::string out = "subsystem " + std::string(subsystem) + ": " + std::to_string(tasks.size()) +
                      (tasks.size() == 1 ? " task\n" : " tasks\n");
    out += header_line(fields) + "\n";
    for (const auto& t : tasks) {
        out += task_line(t, fields) + "\n";
        for (const auto& m : message_lines(t)) out += m + "\n";
    }
    return out;
}

nlohmann::json to_json(std::string_view subsystem, const std::vector<TaskStatus>& tasks) {
    nlohmann::json arr = nlohmann::json::array();
    for (const auto& t : tasks) {
        nlohmann::json j;
        j["slot"] = t.slot;
        j["rmod"] = t.rmod;
        j["rtpu"] = t.rtpu;
        j["cpu"] = t.cpu;
        j["tid"] = t.tid;
        j["S"] = std::string(1, t.type);
        j["crit"] = t.crit;
        j["state"] = chimera::prof::to_string(t.state);
        j["cycle"] = t.cycle;
        j["miss"] = t.miss;
        j["refF"] = t.ref_f;
        j["refT"] = t.ref_t;
        j["mezF"] = t.mez_f;
        j["mezT"] = t.mez_t;
        j["ptime"] = t.ptime;
        j["totC"] = t.tot_c;
        j["tick"] = t.tick;
        j["minU"] = t.min_u;
        j["maxU"] = t.max_u;
        j["avgU"] = t.avg_u;
        j["minC"] = t.min_c;
        j["maxC"] = t.max_c;
        j["avgC"] = t.avg_c;
        j["warn"] = t.warn;
        j["warning"] = t.warning;
        j["error"] = t.error;
        j["policy"] = t.policy;
        j["clock"] = chimera::prof::to_string(t.cpu_clock);
        j["accounting"] = chimera::prof::to_string(t.accounting);
        j["accounted"] = t.accounted;
        j["switched"] = t.switched;
        j["reset_pending"] = t.reset_pending;
        j["consistent"] = t.consistent;
        j["inputs"] = t.inputs;
        j["outputs"] = t.outputs;
        if (t.histogram.bucket_width_ns != 0) {
            j["histogram"] = {{"bucket_width_ns", t.histogram.bucket_width_ns},
                              {"counts", t.histogram.counts}};
        }
        arr.push_back(std::move(j));
    }
    return {{"subsystem", std::string(subsystem)}, {"tasks", std::move(arr)}};
}

}  // namespace chimtop
