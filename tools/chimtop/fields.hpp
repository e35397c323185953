// chimtop fields: the §4.4.1 status fields as columns (name, width, text,
// sort key), shared by the ncurses view, --once and --json; and the summary
// line of each RTPU. Every time is in µs (tools/common/status_text.hpp): the
// column header says "[us]".
#pragma once

#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json.hpp>

#include "chimera/prof.hpp"

namespace chimtop {

struct Field {
    const char* name;     ///< as `status set` spells it: rmod, rtpu, tid, S, ...
    int width;
    bool numeric;         ///< right-aligned, sorted by value
    bool time;            ///< a time, in µs
    const char* help;
};

/// Every field, in §4.4.1 order, then the Linux additions (policy, clock,
/// cpu, the lateness and cycle-time percentiles).
const std::vector<Field>& all_fields();
/// The default selection.
std::vector<std::string> default_fields();
/// Parses "rmod,cycle,miss" (case-sensitive names, as listed); throws
/// std::invalid_argument naming the unknown field.
std::vector<std::string> parse_fields(std::string_view list);
const Field* find_field(std::string_view name);
/// The column header of a field: its name, with "[us]" for a time.
std::string field_header(std::string_view name);

/// Text of one field of one task.
std::string field_text(const chimera::prof::TaskStatus& t, std::string_view field);
/// Sort key: a number for numeric fields, else the text.
double field_number(const chimera::prof::TaskStatus& t, std::string_view field);

/// Sorts by `field`, ascending unless `descending`; ties by slot.
void sort_tasks(std::vector<chimera::prof::TaskStatus>& tasks, std::string_view field,
                bool descending);

/// Whether a task matches a search or filter text: a case-insensitive
/// substring of its rmod, RTPU name, state or policy.
bool matches(const chimera::prof::TaskStatus& t, std::string_view text);

/// The header line and one line per task, then its WARNING>/ERROR> lines
/// (the §4.4.1 status display).
std::string header_line(const std::vector<std::string>& fields);
std::string task_line(const chimera::prof::TaskStatus& t, const std::vector<std::string>& fields);
std::vector<std::string> message_lines(const chimera::prof::TaskStatus& t);

/// One RTPU as its summary line shows it.
struct RtpuSummary {
    int index = 0;
    std::string name;  ///< as in the .sbs, or the number
    int cpu = -1;
    int tasks = 0, on = 0, errors = 0;
    std::uint64_t miss = 0;
    double util = 0;  ///< sum of avgU of the tasks ON (% of the CPU)
    std::optional<double> lat_p99_us, cyc_p99_us;  ///< the worst task's
};
/// One summary per RTPU of the segment (those without tasks too).
std::vector<RtpuSummary> summarise(const std::vector<chimera::prof::RtpuEpoch>& rtpus,
                                   const std::vector<chimera::prof::TaskStatus>& tasks);
std::string summary_line(const RtpuSummary& s);

/// Plain-text snapshot (--once).
std::string plain_text(std::string_view subsystem, const std::vector<chimera::prof::RtpuEpoch>& rtpus,
                       const std::vector<chimera::prof::TaskStatus>& tasks, const std::vector<std::string>& fields);
/// JSON snapshot (--json): every field of every task, numbers as numbers,
/// times in µs ("time_unit": "us"), the RTPUs with their summaries.
nlohmann::json to_json(std::string_view subsystem, const std::vector<chimera::prof::RtpuEpoch>& rtpus,
                       const std::vector<chimera::prof::TaskStatus>& tasks);

}  // namespace chimtop
