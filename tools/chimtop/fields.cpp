#include "fields.hpp"

#include <algorithm>
#include <cctype>
#include <cstdio>
#include <stdexcept>

#include "status_text.hpp"

namespace chimtop {

using chimera::prof::TaskStatus;
namespace tools = chimera::tools;

namespace {

std::string pad(const std::string& s, int width, bool right) {
    if (static_cast<int>(s.size()) >= width) return s;
    const std::string fill(static_cast<std::size_t>(width) - s.size(), ' ');
    return right ? fill + s : s + fill;
}

std::string rtpu_text(const TaskStatus& t) { return t.rtpu_name.empty() ? std::to_string(t.rtpu) : t.rtpu_name; }

// The value of a field as JSON (numbers as numbers, times in µs).
nlohmann::json field_value(const TaskStatus& t, std::string_view f) {
    if (f == "rmod") return t.rmod;
    if (f == "rtpu") return rtpu_text(t);
    if (f == "tid") return t.tid;
    if (f == "S") return std::string(1, t.type);
    if (f == "crit") return t.crit;
    if (f == "state") return chimera::prof::to_string(t.state);
    if (f == "refF") return t.ref_f;
    if (f == "policy") return t.policy;
    if (f == "clock") return chimera::prof::to_string(t.cpu_clock);
    if (f == "cpu") return t.cpu;
    return tools::profile_value(t, f);
}

bool contains_nocase(std::string_view hay, std::string_view needle) {
    return std::search(hay.begin(), hay.end(), needle.begin(), needle.end(), [](char a, char b) {
               return std::tolower(static_cast<unsigned char>(a)) == std::tolower(static_cast<unsigned char>(b));
           }) != hay.end();
}

}  // namespace

const std::vector<Field>& all_fields() {
    static const std::vector<Field> fields = {
        {"rmod", 12, false, false, "RMOD name of the task"},
        {"rtpu", 8, false, false, "RTPU the task runs on, named as in the .sbs"},
        {"tid", 7, true, false, "thread id"},
        {"S", 1, false, false, "type: P periodic, Y synchronous, S sporadic, D deferrable, B background"},
        {"crit", 4, true, false, "criticality"},
        {"state", 11, false, false, "task state"},
        {"cycle", 8, true, false, "cycles in this window (since z, or the RTPU's last reset)"},
        {"miss", 6, true, false, "deadlines missed in this window (a job late or aborted, a release skipped)"},
        {"refF", 9, true, false, "reference frequency (Hz)"},
        {"refT", 10, true, true, "reference period (us)"},
        {"mezF", 9, true, false, "measured frequency in this window (Hz)"},
        {"mezT", 10, true, true, "measured period (us), rounded to the tick"},
        {"ptime", 12, true, true, "profiling time: length of this window (us)"},
        {"totC", 10, true, true, "total CPU time in this window (us)"},
        {"tick", 9, true, true, "resolution of the profile (us)"},
        {"minU", 6, true, false, "minimum CPU utilisation of one cycle since the RTPU's reset (%)"},
        {"maxU", 6, true, false, "maximum CPU utilisation of one cycle since the RTPU's reset (%)"},
        {"avgU", 6, true, false, "average CPU utilisation per cycle in this window (%)"},
        {"minC", 10, true, true, "minimum CPU time of one cycle since the RTPU's reset (us)"},
        {"maxC", 10, true, true, "maximum CPU time of one cycle since the RTPU's reset (us)"},
        {"avgC", 10, true, true, "average CPU time of one cycle in this window (us)"},
        {"warn", 4, true, false, "warnings in this window"},
        {"policy", 22, false, false, "scheduling policy in force"},
        {"clock", 14, false, false, "source of the CPU times"},
        {"cpu", 3, true, false, "CPU the task is pinned to"},
        {"cycP50", 10, true, true, "cycle time (wake-up to end of cycle, wall clock), median in this window (us)"},
        {"cycP99", 10, true, true, "cycle time, 99th percentile in this window (us)"},
        {"cycMax", 10, true, true, "cycle time, highest in this window (us, within 6.25%)"},
        {"latP50", 10, true, true, "release lateness (wake-up minus release), median in this window (us)"},
        {"latP99", 10, true, true, "release lateness, 99th percentile in this window (us)"},
        {"latMax", 10, true, true, "release lateness, highest in this window (us, within 6.25%)"},
    };
    return fields;
}

std::vector<std::string> default_fields() {
    // 153 columns: an htop-sized terminal; f adds the rest.
    return {"rmod", "rtpu", "tid",  "S",      "crit",   "state", "cycle", "miss",
            "mezF", "avgC", "maxC", "cycP99", "latP99", "avgU",  "warn",  "policy"};
}

const Field* find_field(std::string_view name) {
    for (const auto& f : all_fields())
        if (name == f.name) return &f;
    return nullptr;
}

std::string field_header(std::string_view name) {
    const Field* f = find_field(name);
    return f && f->time ? tools::time_header(std::string(name)) : std::string(name);
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
    const Field* fd = find_field(f);
    if (!fd) return "?";
    return tools::value_text(field_value(t, f), fd->time);
}

double field_number(const TaskStatus& t, std::string_view f) {
    if (f == "rtpu") return t.rtpu;  // by number, as the .sbs lists them
    const nlohmann::json v = field_value(t, f);
    if (v.is_number()) return v.get<double>();
    if (v.is_string() && !v.get<std::string>().empty() && v.get<std::string>()[0] == '>') return 1e300;  // overflow
    return -1;  // no sample: first
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

bool matches(const TaskStatus& t, std::string_view text) {
    if (text.empty()) return true;
    for (const std::string& s : {t.rmod, rtpu_text(t), std::string(chimera::prof::to_string(t.state)), t.policy})
        if (contains_nocase(s, text)) return true;
    return false;
}

std::string header_line(const std::vector<std::string>& fields) {
    std::string line;
    for (const auto& name : fields) {
        const Field* f = find_field(name);
        if (!line.empty()) line += ' ';
        line += pad(field_header(name), f ? f->width : 8, f && f->numeric);
    }
    return line;
}

std::string task_line(const TaskStatus& t, const std::vector<std::string>& fields) {
    std::string line;
    for (const auto& name : fields) {
        const Field* f = find_field(name);
        if (!line.empty()) line += ' ';
        std::string text = field_text(t, name);
        // The last column may run on; the others are cut to keep the columns
        // under their headers (a long policy text).
        if (f && !f->numeric && &name != &fields.back() && static_cast<int>(text.size()) > f->width)
            text = text.substr(0, static_cast<std::size_t>(f->width - 1)) + "~";
        line += pad(text, f ? f->width : 8, f && f->numeric);
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

std::vector<RtpuSummary> summarise(const std::vector<chimera::prof::RtpuEpoch>& rtpus,
                                   const std::vector<TaskStatus>& tasks) {
    std::vector<RtpuSummary> out(rtpus.size());
    for (std::size_t r = 0; r < rtpus.size(); ++r) {
        out[r].index = static_cast<int>(r);
        out[r].name = rtpus[r].name.empty() ? std::to_string(r) : rtpus[r].name;
        out[r].cpu = rtpus[r].cpu;
    }
    auto worse = [](std::optional<double>& worst, std::optional<double> v) {
        if (v && (!worst || *v > *worst)) worst = v;
    };
    for (const auto& t : tasks) {
        if (t.rtpu < 0 || static_cast<std::size_t>(t.rtpu) >= out.size()) continue;
        RtpuSummary& s = out[static_cast<std::size_t>(t.rtpu)];
        ++s.tasks;
        s.miss += t.miss;
        if (t.state == chimera::prof::TaskState::error) ++s.errors;
        if (t.state != chimera::prof::TaskState::on) continue;
        ++s.on;
        s.util += t.avg_u;
        worse(s.lat_p99_us, tools::tail_us(t.lateness, tools::Tail::p99));
        worse(s.cyc_p99_us, tools::tail_us(t.cycle_time, tools::Tail::p99));
    }
    return out;
}

std::string summary_line(const RtpuSummary& s) {
    char head[96];
    std::snprintf(head, sizeof head, "RTPU %-8s cpu %-3s %2d task%s %2d ON", s.name.c_str(),
                  s.cpu >= 0 ? std::to_string(s.cpu).c_str() : "-", s.tasks, s.tasks == 1 ? " " : "s", s.on);
    std::string line = head;
    char util[32];
    std::snprintf(util, sizeof util, "  CPU %5.1f%%", s.util);
    line += util;
    line += "  miss " + std::to_string(s.miss);
    line += "  worst latP99 " + tools::tail_text(s.lat_p99_us) + "us  cycP99 " + tools::tail_text(s.cyc_p99_us) + "us";
    if (s.errors > 0) line += "  " + std::to_string(s.errors) + " in ERROR";
    return line;
}

std::string plain_text(std::string_view subsystem, const std::vector<chimera::prof::RtpuEpoch>& rtpus,
                       const std::vector<TaskStatus>& tasks, const std::vector<std::string>& fields) {
    std::string out = "subsystem " + std::string(subsystem) + ": " + std::to_string(tasks.size()) +
                      (tasks.size() == 1 ? " task" : " tasks") + " (times in " + tools::kTimeUnit + ")\n";
    for (const auto& s : summarise(rtpus, tasks)) out += summary_line(s) + "\n";
    out += header_line(fields) + "\n";
    for (const auto& t : tasks) {
        out += task_line(t, fields) + "\n";
        for (const auto& m : message_lines(t)) out += m + "\n";
    }
    return out;
}

nlohmann::json to_json(std::string_view subsystem, const std::vector<chimera::prof::RtpuEpoch>& rtpus,
                       const std::vector<TaskStatus>& tasks) {
    nlohmann::json arr = nlohmann::json::array();
    for (const auto& t : tasks) {
        nlohmann::json j;
        for (const auto& f : all_fields()) j[f.name] = field_value(t, f.name);
        j["slot"] = t.slot;
        j["rtpu"] = t.rtpu;  // the number; the name is rtpu_name
        j["rtpu_name"] = rtpu_text(t);
        j["warning"] = t.warning;
        j["error"] = t.error;
        j["accounting"] = chimera::prof::to_string(t.accounting);
        j["accounted"] = t.accounted;
        j["switched"] = t.switched;
        j["reset_pending"] = t.reset_pending;
        j["windowed"] = t.windowed;
        j["consistent"] = t.consistent;
        j["inputs"] = t.inputs;
        j["outputs"] = t.outputs;
        if (t.histogram.bucket_width_ns != 0)
            j["histogram"] = {{"bucket_width_ns", t.histogram.bucket_width_ns}, {"counts", t.histogram.counts}};
        arr.push_back(std::move(j));
    }
    nlohmann::json jr = nlohmann::json::array();
    for (const auto& s : summarise(rtpus, tasks))
        jr.push_back({{"rtpu", s.index}, {"name", s.name}, {"cpu", s.cpu}, {"tasks", s.tasks}, {"on", s.on},
                      {"errors", s.errors}, {"miss", s.miss}, {"util", s.util},
                      {"latP99", tools::tail_json(s.lat_p99_us)}, {"cycP99", tools::tail_json(s.cyc_p99_us)}});
    return {{"subsystem", std::string(subsystem)}, {"time_unit", tools::kTimeUnit}, {"rtpus", std::move(jr)},
            {"tasks", std::move(arr)}};
}

}  // namespace chimtop
