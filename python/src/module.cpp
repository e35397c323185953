// chimera._core: the Python extension (issue #18). The package chimera
// (python/chimera/__init__.py) re-exports it with the master client.
#include "bindings.hpp"

#include <chimera/cfg.hpp>
#include <chimera/ipc/segment.hpp>
#include <chimera/sampler.hpp>

#include <cstdlib>
#include <string>

#ifndef CHIMERA_VERSION
#error "CHIMERA_VERSION must be defined by the build (meson.project_version())"
#endif

namespace chimera::python {

void bind_svar(py::module_& m) {
    py::class_<VarRecord>(m, "VarInfo", "One state variable of the table: its .svar definition and its users.")
        .def_readonly("name", &VarRecord::name, "the .svar NAME")
        .def_readonly("index", &VarRecord::index, "position in the table, as in names()")
        .def_readonly("type", &VarRecord::type, "the .svar TYPE: 'double', 'float', 'struct[32]', ...")
        .def_readonly("nelem", &VarRecord::nelem, "the .svar NELEM: number of elements")
        .def_readonly("elem_size", &VarRecord::elem_size, "bytes per element")
        .def_readonly("desc", &VarRecord::desc, "the .svar DESC text")
        .def_readonly("units", &VarRecord::units, "the .svar UNITS text")
        .def_readonly("dtype", &VarRecord::dtype, "numpy dtype of an element (uint8 for struct)")
        .def_readonly("shape", &VarRecord::shape, "(NELEM,), or (NELEM, N) for struct[N]")
        .def_readonly("init", &VarRecord::init, "INIT values as float64 (None for struct)")
        .def_readonly("min", &VarRecord::min, "MIN values as float64, None without a range")
        .def_readonly("max", &VarRecord::max, "MAX values as float64, None without a range")
        .def_readonly("producers", &VarRecord::producers, "live tasks that write it (out-vars)")
        .def_readonly("consumers", &VarRecord::consumers, "live tasks that read it (in-vars)")
        .def("__repr__", [](const VarRecord& r) {
            return "<VarInfo " + r.name + " " + r.type + "[" + std::to_string(r.nelem) + "] " + r.units + ">";
        });

    py::class_<Reader, std::shared_ptr<Reader>>(m, "Reader",
        "Variables read together: read() copies the whole set under one table lock into a private local "
        "table, whose read-only numpy views (arrays) it refreshes in place.")
        .def("read", [](Reader& r) { r.read(); return r.views(false); },
             "Copy the set from the table (one lock, GIL released); returns {name: view}.")
        .def_property_readonly("names", &Reader::names, "the variables of the set, in the order given")
        .def_property_readonly("arrays", [](Reader& r) { return r.views(false); },
                               "{name: read-only view into the local table}")
        .def_property_readonly("last_status", &Reader::last_status,
                               "'ok', or 'recovered' when the read took the lock over from a dead holder");

    py::class_<Writer, Reader, std::shared_ptr<Writer>>(m, "Writer",
        "Variables written together: fill arrays (writable views), then write() checks every value "
        "(type, .svar MIN/MAX, producer rule) and copies the set under one table lock.")
        .def("write", &Writer::write, "Check and copy the set to the table (one lock, GIL released).")
        .def("set", [](Writer& w, const std::string& name, const py::object& value) {
                 const auto& n = w.names();
                 const auto it = std::find(n.begin(), n.end(), name);
                 if (it == n.end()) throw py::key_error(name + " is not in this writer");
                 w.fill(static_cast<std::size_t>(it - n.begin()), value);
             }, py::arg("name"), py::arg("values"), "Check values and put them in the local table.")
        .def_property_readonly("arrays", [](Writer& w) { return w.views(true); },
                               "{name: writable view into the local table}")
        .def_property_readonly("force", &Writer::force,
                               "True: write() skips the producer rule (no ProducerConflict)");

    py::class_<PyTable, std::shared_ptr<PyTable>>(m, "Table",
        "A subsystem's global state-variable table (SVAR, thesis §5.5), mapped into this process.")
        .def_static("attach", &PyTable::attach, py::arg("subsystem"), py::arg("lock_timeout") = 0.1,
                    "Attach to the table of the running subsystem SUBSYSTEM (/chimera.SUBSYSTEM.svar).")
        .def_static("create", &PyTable::create, py::arg("subsystem"), py::arg("svar_file"),
                    py::arg("lock_timeout") = 0.1,
                    "Create a table from a .svar file (no master: for simulation and tests); it is "
                    "removed when this object goes and no other process maps it.")
        .def_property_readonly("subsystem", &PyTable::subsystem, "the subsystem's name")
        .def_property_readonly("segment", [](PyTable& t) { return t.table().name(); },
                               "the shared-memory segment: /chimera.SUBSYSTEM.svar")
        .def_property("lock_timeout", &PyTable::lock_timeout, &PyTable::set_lock_timeout,
                      "seconds a read or write waits for the table lock before LockTimeout")
        .def("names", &PyTable::names, "The variables' names in table order.")
        .def("variables", &PyTable::variables, "Every variable with type, size, units, MIN/MAX, producers.")
        .def("info", &PyTable::info, py::arg("name"), "One variable's VarInfo (KeyError naming the table's variables).")
        .def("read", &PyTable::read, py::arg("names"),
             "read('Q_REF') -> ndarray; read(['Q_REF', 'Q_MEZ']) -> {name: ndarray}: one consistent "
             "whole-set copy under one table lock.")
        .def("write", &PyTable::write, py::arg("what"), py::arg("values") = py::none(), py::kw_only(),
             py::arg("force") = false,
             "write('Q_REF', values) or write({'Q_REF': v, 'GAIN': g}): every value checked against the "
             "type and the .svar MIN/MAX (ValueError), refused while a live task produces a variable "
             "(ProducerConflict) unless force=True; then one copy under one table lock.")
        .def("reader", [](PyTable& t, const std::vector<std::string>& names) {
                 return std::make_shared<Reader>(t.shared_from_this(), names);
             }, py::arg("names"),
             "A Reader of NAMES: one lock per read into its own local table (KeyError for an unknown name).")
        .def("writer", [](PyTable& t, const std::vector<std::string>& names, bool force) {
                 return std::make_shared<Writer>(t.shared_from_this(), names, force);
             }, py::arg("names"), py::kw_only(), py::arg("force") = false,
             "A Writer of NAMES; force=True skips the producer rule (KeyError for an unknown name).")
        .def("stats", &PyTable::stats, "Lock recoveries, rollbacks, timeouts and forced resets since creation.")
        .def("__contains__", [](PyTable& t, const std::string& n) { return t.table().find(n).has_value(); })
        .def("__len__", [](PyTable& t) { return t.table().size(); })
        .def("__repr__", [](PyTable& t) {
            if (t.gone()) return "<chimera.Table of subsystem " + t.subsystem() + ", finished>";
            return "<chimera.Table " + t.table().name() + ", " + std::to_string(t.table().size()) + " variables>";
        });
}

}  // namespace chimera::python

namespace {

// pybind11 before 2.12 reads numpy arrays through numpy 1.x's C structures
// (PyArray_Descr's layout changed in numpy 2.0): under numpy 2 its arrays
// carry wrong element sizes and reads return wrong values, silently. Refuse
// the import instead, naming both versions and the way out.
void refuse_an_incompatible_numpy() {
    namespace py = pybind11;
#if PYBIND11_VERSION_MAJOR < 2 || (PYBIND11_VERSION_MAJOR == 2 && PYBIND11_VERSION_MINOR < 12)
    const py::module_ numpy = py::module_::import("numpy");
    const std::string version = py::str(numpy.attr("__version__"));
    if (std::atoi(version.c_str()) < 2) return;
    const std::string where = py::hasattr(numpy, "__file__") ? std::string(py::str(numpy.attr("__file__"))) : "?";
    throw py::import_error("chimera: numpy " + version + " (" + where + ") is imported, but chimera's bindings were "
                           "built with pybind11 " PYBIND11_TOSTRING(PYBIND11_VERSION_MAJOR) "." PYBIND11_TOSTRING(
                               PYBIND11_VERSION_MINOR) ", which reads numpy 1.x arrays only: use numpy < 2 (Debian's "
                           "python3-numpy; in a virtual environment 'pip install \"numpy<2\"' or "
                           "--system-site-packages), or rebuild the bindings with pybind11 2.12 or later");
#endif
}

}  // namespace

PYBIND11_MODULE(_core, m) {
    namespace cp = chimera::python;
    namespace py = pybind11;
    refuse_an_incompatible_numpy();
    m.doc() = "Chimera for Linux: state variables, triple buffers and task status from Python (issue #18).";
    m.attr("__version__") = CHIMERA_VERSION;
    static py::exception<std::runtime_error> base(m, "ChimeraError", PyExc_RuntimeError);
    static py::exception<cp::SvarError> svar_error(m, "SvarError", base.ptr());
    static py::exception<cp::LockTimeout> lock_timeout(m, "LockTimeout", svar_error.ptr());
    static py::exception<cp::ProducerConflict> producer(m, "ProducerConflict", svar_error.ptr());
    static py::exception<cp::TbufError> tbuf_error(m, "TbufError", base.ptr());
    static py::exception<cp::SubsystemGone> gone(m, "SubsystemGone", base.ptr());
    base.doc() = "Base of the extension's errors (SvarError, TbufError, SubsystemGone); raised itself when a "
                 "shared-memory segment, a status segment, a sampler ring or a configuration file fails.";
    svar_error.doc() = "A state-variable table error: the subsystem's table or status segment is missing, or a "
                       "table operation failed (the message says which).";
    lock_timeout.doc() = "The table lock was not had within the Table's lock_timeout seconds.";
    producer.doc() = "A write to a variable a live task produces, without force=True (sbs setvar's rule).";
    tbuf_error.doc() = "A TBUF read or write refused: the buffer is corrupt (the message says how).";
    gone.doc() = "The master of the object's subsystem has finished; the object has let go of its segments "
                 "(attach again once the subsystem runs again).";
    py::register_exception_translator([](std::exception_ptr p) {
        try {
            if (p) std::rethrow_exception(p);
        } catch (const cp::LockTimeout& e) {
            PyErr_SetString(lock_timeout.ptr(), e.what());
        } catch (const cp::ProducerConflict& e) {
            PyErr_SetString(producer.ptr(), e.what());
        } catch (const cp::SvarError& e) {
            PyErr_SetString(svar_error.ptr(), e.what());
        } catch (const cp::TbufError& e) {
            PyErr_SetString(tbuf_error.ptr(), e.what());
        } catch (const cp::SubsystemGone& e) {
            PyErr_SetString(gone.ptr(), e.what());
        } catch (const chimera::sampler::Error& e) {
            PyErr_SetString(base.ptr(), e.what());
        } catch (const chimera::svar::Error& e) {
            PyErr_SetString(svar_error.ptr(), e.what());
        } catch (const chimera::ipc::SegmentError& e) {
            PyErr_SetString(base.ptr(), e.what());
        } catch (const chimera::prof::StatusError& e) {
            PyErr_SetString(base.ptr(), e.what());
        } catch (const chimera::cfg::ParseError& e) {
            PyErr_SetString(base.ptr(), e.what());
        }
    });
    m.def("segment_name", &chimera::ipc::segment_name, py::arg("subsystem"), py::arg("object"),
          "The shared-memory name of a subsystem's object: /chimera.SUBSYSTEM.OBJECT.");
    m.def("_master_alive", &cp::Lifeline::master_alive, py::arg("subsystem"),
          "True when a master of SUBSYSTEM runs (its status segment is published and its process lives).");
    cp::bind_svar(m);
    cp::bind_status(m);
    cp::bind_tbuf(m);
    cp::bind_sampler(m);
}
