// Task status from Python (issue #18.3): the §4.4.1 fields of every task as
// typed records, read from the status segment like chimtop (never writing a
// task's group), with a per-reader window like the prompt's `status`.
#include "bindings.hpp"

#include <cerrno>
#include <cstdint>
#include <functional>
#include <limits>
#include <utility>

namespace chimera::python {

namespace {

using prof::TaskStatus;

// A percentile or maximum in seconds: None without a sample, inf past the last bucket.
py::object seconds(std::optional<std::uint64_t> ns) {
    if (!ns) return py::none();
    if (*ns == UINT64_MAX) return py::float_(std::numeric_limits<double>::infinity());
    return py::float_(static_cast<double>(*ns) / 1e9);
}

using Getter = std::function<py::object(const TaskStatus&)>;

template <typename T>
Getter field(T TaskStatus::*member) {
    return [member](const TaskStatus& s) { return py::cast(s.*member); };
}

struct Field {
    const char* name;
    Getter get;
    const char* doc;
};

// Every field of a record, in the order to_dict() and a DataFrame show them.
// Times are seconds, utilisations percent, frequencies Hz (as prof::TaskStatus).
// "The window": since the RTPU's last reset (snapshot()) or this reader's last take().
const std::vector<Field>& fields() {
    static const std::vector<Field> f = {
        {"rmod", field(&TaskStatus::rmod),
         "the task's RMOD name"},
        {"rtpu", [](const TaskStatus& s) { return py::cast(s.rtpu_name.empty() ? std::to_string(s.rtpu) : s.rtpu_name); },
         "its RTPU: the name in the .sbs, else the index as text"},
        {"cpu", field(&TaskStatus::cpu),
         "the CPU its thread is pinned to (-1: none)"},
        {"tid", field(&TaskStatus::tid),
         "its Linux thread id"},
        {"type", [](const TaskStatus& s) { return py::cast(std::string(1, s.type)); },
         "'P' periodic, 'Y' synchronous, 'S' sporadic, 'D' deferrable, 'B' background server"},
        {"crit", field(&TaskStatus::crit),
         "criticality (MUF)"},
        {"state", [](const TaskStatus& s) { return py::cast(std::string(prof::to_string(s.state))); },
         "'NOT-CREATED', 'SPAWNING', 'OFF', 'ON', 'ERROR' or 'KILLING'"},
        {"cycle", field(&TaskStatus::cycle),
         "cycles (events for a server) in the window"},
        {"miss", field(&TaskStatus::miss),
         "missed cycles in the window"},
        {"ref_f", field(&TaskStatus::ref_f),
         "reference frequency, Hz (0: aperiodic)"},
        {"ref_t", field(&TaskStatus::ref_t),
         "reference period, s (1/ref_f)"},
        {"mez_f", field(&TaskStatus::mez_f),
         "measured frequency, Hz: cycle / ptime"},
        {"mez_t", field(&TaskStatus::mez_t),
         "measured period, s: ptime / (cycle + miss), rounded to the tick"},
        {"ptime", field(&TaskStatus::ptime),
         "profiling time, s: the window's length"},
        {"tot_c", field(&TaskStatus::tot_c),
         "CPU time of the accounted cycles, s"},
        {"tick", field(&TaskStatus::tick),
         "resolution of the times, s: 1 ns, or the tick in half-tick mode"},
        {"min_u", field(&TaskStatus::min_u),
         "least CPU utilisation of one cycle, % of the period (since the RTPU's last reset)"},
        {"max_u", field(&TaskStatus::max_u),
         "most CPU utilisation of one cycle, % of the period (since the RTPU's last reset)"},
        {"avg_u", field(&TaskStatus::avg_u),
         "mean CPU utilisation of one cycle, % of the period"},
        {"min_c", field(&TaskStatus::min_c),
         "least CPU time of one cycle, s (since the RTPU's last reset)"},
        {"max_c", field(&TaskStatus::max_c),
         "most CPU time of one cycle, s (since the RTPU's last reset)"},
        {"avg_c", field(&TaskStatus::avg_c),
         "mean CPU time of one cycle, s (over the accounted cycles)"},
        {"last_c", field(&TaskStatus::last_c),
         "CPU time of the last cycle, s"},
        {"cyc_p50", [](const TaskStatus& s) { return seconds(s.cycle_time.percentile_ns(500000)); },
         "median cycle time (wake-up to end of cycle, wall clock), s; None without a sample, inf beyond the histogram"},
        {"cyc_p99", [](const TaskStatus& s) { return seconds(s.cycle_time.percentile_ns(990000)); },
         "99th percentile of the cycle time, s; None without a sample, inf beyond the histogram"},
        {"cyc_max", [](const TaskStatus& s) { return seconds(s.cycle_time.max_ns()); },
         "longest cycle time, s; None without a sample, inf beyond the histogram"},
        {"lat_p50", [](const TaskStatus& s) { return seconds(s.lateness.percentile_ns(500000)); },
         "median release lateness (wake-up minus release), s; None without a sample, inf beyond the histogram"},
        {"lat_p99", [](const TaskStatus& s) { return seconds(s.lateness.percentile_ns(990000)); },
         "99th percentile of the release lateness, s; None without a sample, inf beyond the histogram"},
        {"lat_max", [](const TaskStatus& s) { return seconds(s.lateness.max_ns()); },
         "greatest release lateness, s; None without a sample, inf beyond the histogram"},
        {"warn", field(&TaskStatus::warn),
         "warnings in the window"},
        {"warning", field(&TaskStatus::warning),
         "the first warning since the last status reset ('' if none)"},
        {"error", field(&TaskStatus::error),
         "the message that put the task in ERROR ('' otherwise)"},
        {"policy", field(&TaskStatus::policy),
         "the scheduling policy its thread really runs under"},
        {"inputs", [](const TaskStatus& s) { return py::cast(split_names(s.inputs)); },
         "the variables it reads (in-vars)"},
        {"outputs", [](const TaskStatus& s) { return py::cast(split_names(s.outputs)); },
         "the variables it writes (out-vars)"},
        {"cpu_clock", [](const TaskStatus& s) { return py::cast(std::string(prof::to_string(s.cpu_clock))); },
         "the CPU-time source: 'perf-page', 'thread-cputime' or 'none'"},
        {"accounted", field(&TaskStatus::accounted),
         "cycles whose CPU time is in tot_c"},
        {"switched", field(&TaskStatus::switched),
         "cycles during which its thread was switched out"},
        {"consistent", field(&TaskStatus::consistent),
         "False when its counters could not be read consistently in time"},
        {"windowed", field(&TaskStatus::windowed),
         "True: counts since this reader's last take(); False: since the RTPU's last reset"},
    };
    return f;
}

// A subsystem's status segment, read-only, with this reader's own window.
struct PyStatus {
    prof::StatusReader reader;
    prof::StatusWindow window;

    static std::unique_ptr<PyStatus> attach(const std::string& subsystem) {
        int error_number = 0;
        std::string why;
        auto r = prof::StatusReader::try_attach(subsystem, error_number, why);
        if (!r) {
            if (error_number == ENOENT)
                throw SvarError("no subsystem " + subsystem + " is running (no status segment)");
            throw SvarError("status of subsystem " + subsystem + ": " + why);
        }
        auto s = std::make_unique<PyStatus>();
        s->reader = std::move(*r);
        s->window.restart(s->reader);
        s->life.watch(subsystem, "StatusReader", [raw = s.get()] { raw->reader = prof::StatusReader(); });
        return s;
    }
    /// The reader, once the check says its master still runs.
    prof::StatusReader& live() {
        life.check();
        return reader;
    }
    Lifeline life;
};

}  // namespace

void bind_status(py::module_& m) {
    auto task = py::class_<TaskStatus>(m, "TaskStatus",
        "One task's status (thesis §4.4.1): times in seconds, utilisations in percent, frequencies in Hz.");
    for (const auto& [name, get, doc] : fields())
        task.def_property_readonly(name, [get = get](const TaskStatus& s) { return get(s); }, doc);
    task.def("to_dict", [](const TaskStatus& s) {
        py::dict d;
        for (const auto& [name, get, doc] : fields()) d[name] = get(s);
        return d;
    }, "Every field as a dict (the row of to_dataframe()).");
    task.def("__repr__", [](const TaskStatus& s) {
        return "<TaskStatus " + s.rmod + " " + prof::to_string(s.state) + " cycle=" + std::to_string(s.cycle) +
               " miss=" + std::to_string(s.miss) + ">";
    });
    m.attr("TASK_STATUS_FIELDS") = [] {
        py::list l;
        for (const auto& f : fields()) l.append(f.name);
        return l;
    }();

    py::class_<PyStatus>(m, "StatusReader",
        "The status segment of a running subsystem (read-only, as chimtop reads it).")
        .def(py::init(&PyStatus::attach), py::arg("subsystem"))
        .def("snapshot", [](PyStatus& s) {
            const Lifeline::Use in_use(s.life);  // mapped until the copy ends
            py::gil_scoped_release nogil;
            return s.reader.snapshot();
        }, "Every task, counted since its RTPU's last reset.")
        .def("take", [](PyStatus& s) {
            const Lifeline::Use in_use(s.life);
            py::gil_scoped_release nogil;
            return s.window.take(s.reader);
        }, "Every task, counted since this reader's last take() (its own window, as the prompt's `status`); "
           "no other reader's counts change.")
        .def_property_readonly("alive", [](PyStatus& s) { return s.live().alive(); },
                               "the master that created the segment still runs (SubsystemGone once it has finished)")
        .def_property_readonly("master_pid", [](PyStatus& s) { return s.live().creator_pid(); },
                               "process id of the master that created the segment")
        .def_property_readonly("subsystem", [](PyStatus& s) { return s.life.subsystem(); }, "the subsystem's name");
}

}  // namespace chimera::python
