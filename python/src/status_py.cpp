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

// Every field of a record, in the order to_dict() and a DataFrame show them.
// Times are seconds, utilisations percent, frequencies Hz (as prof::TaskStatus).
const std::vector<std::pair<const char*, Getter>>& fields() {
    static const std::vector<std::pair<const char*, Getter>> f = {
        {"rmod", field(&TaskStatus::rmod)},
        {"rtpu", [](const TaskStatus& s) { return py::cast(s.rtpu_name.empty() ? std::to_string(s.rtpu) : s.rtpu_name); }},
        {"cpu", field(&TaskStatus::cpu)},
        {"tid", field(&TaskStatus::tid)},
        {"type", [](const TaskStatus& s) { return py::cast(std::string(1, s.type)); }},
        {"crit", field(&TaskStatus::crit)},
        {"state", [](const TaskStatus& s) { return py::cast(std::string(prof::to_string(s.state))); }},
        {"cycle", field(&TaskStatus::cycle)},
        {"miss", field(&TaskStatus::miss)},
        {"ref_f", field(&TaskStatus::ref_f)},
        {"ref_t", field(&TaskStatus::ref_t)},
        {"mez_f", field(&TaskStatus::mez_f)},
        {"mez_t", field(&TaskStatus::mez_t)},
        {"ptime", field(&TaskStatus::ptime)},
        {"tot_c", field(&TaskStatus::tot_c)},
        {"tick", field(&TaskStatus::tick)},
        {"min_u", field(&TaskStatus::min_u)},
        {"max_u", field(&TaskStatus::max_u)},
        {"avg_u", field(&TaskStatus::avg_u)},
        {"min_c", field(&TaskStatus::min_c)},
        {"max_c", field(&TaskStatus::max_c)},
        {"avg_c", field(&TaskStatus::avg_c)},
        {"last_c", field(&TaskStatus::last_c)},
        {"cyc_p50", [](const TaskStatus& s) { return seconds(s.cycle_time.percentile_ns(500000)); }},
        {"cyc_p99", [](const TaskStatus& s) { return seconds(s.cycle_time.percentile_ns(990000)); }},
        {"cyc_max", [](const TaskStatus& s) { return seconds(s.cycle_time.max_ns()); }},
        {"lat_p50", [](const TaskStatus& s) { return seconds(s.lateness.percentile_ns(500000)); }},
        {"lat_p99", [](const TaskStatus& s) { return seconds(s.lateness.percentile_ns(990000)); }},
        {"lat_max", [](const TaskStatus& s) { return seconds(s.lateness.max_ns()); }},
        {"warn", field(&TaskStatus::warn)},
        {"warning", field(&TaskStatus::warning)},
        {"error", field(&TaskStatus::error)},
        {"policy", field(&TaskStatus::policy)},
        {"inputs", [](const TaskStatus& s) { return py::cast(split_names(s.inputs)); }},
        {"outputs", [](const TaskStatus& s) { return py::cast(split_names(s.outputs)); }},
        {"cpu_clock", [](const TaskStatus& s) { return py::cast(std::string(prof::to_string(s.cpu_clock))); }},
        {"accounted", field(&TaskStatus::accounted)},
        {"switched", field(&TaskStatus::switched)},
        {"consistent", field(&TaskStatus::consistent)},
        {"windowed", field(&TaskStatus::windowed)},
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
    for (const auto& [name, get] : fields())
        task.def_property_readonly(name, [get = get](const TaskStatus& s) { return get(s); });
    task.def("to_dict", [](const TaskStatus& s) {
        py::dict d;
        for (const auto& [name, get] : fields()) d[name] = get(s);
        return d;
    }, "Every field as a dict (the row of to_dataframe()).");
    task.def("__repr__", [](const TaskStatus& s) {
        return "<TaskStatus " + s.rmod + " " + prof::to_string(s.state) + " cycle=" + std::to_string(s.cycle) +
               " miss=" + std::to_string(s.miss) + ">";
    });
    m.attr("TASK_STATUS_FIELDS") = [] {
        py::list l;
        for (const auto& f : fields()) l.append(f.first);
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
        .def_property_readonly("master_pid", [](PyStatus& s) { return s.live().creator_pid(); })
        .def_property_readonly("subsystem", [](PyStatus& s) { return s.life.subsystem(); });
}

}  // namespace chimera::python
