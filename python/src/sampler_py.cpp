// The sampler ring from Python (issues #18.4, #17.5): a reader of the ring a
// `sample` task writes at its rate, returning numpy arrays of the samples
// taken since the last read, and counting what it lost if it fell behind. A
// read never waits, so it keeps the GIL.
#include "bindings.hpp"

#include <chimera/sampler.hpp>

namespace chimera::python {

namespace {

struct PyRing {
    sampler::RingReader reader;
    Lifeline life;

    /// The reader, once the check says its subsystem's master still runs.
    sampler::RingReader& live() {
        life.check();
        return reader;
    }

    py::tuple read(std::optional<std::size_t> max_samples) {
        life.check();
        const std::uint64_t available = reader.head() - reader.position();
        std::size_t n = static_cast<std::size_t>(std::min<std::uint64_t>(available, reader.capacity()));
        if (max_samples) n = std::min(n, *max_samples);
        const std::size_t width = reader.channels();
        py::array_t<std::int64_t> t(static_cast<py::ssize_t>(n));
        py::array_t<std::uint64_t> cycle(static_cast<py::ssize_t>(n));
        py::array_t<double> values({static_cast<py::ssize_t>(n), static_cast<py::ssize_t>(width)});
        const sampler::ReadCount c = reader.read(t.mutable_data(), cycle.mutable_data(), values.mutable_data(), n);
        if (c.samples < n) {  // some were overwritten meanwhile: keep the rows taken
            t.resize({static_cast<py::ssize_t>(c.samples)});
            cycle.resize({static_cast<py::ssize_t>(c.samples)});
            values.resize({static_cast<py::ssize_t>(c.samples), static_cast<py::ssize_t>(width)});
        }
        return py::make_tuple(t, cycle, values, c.lost);
    }
};

}  // namespace

void bind_sampler(py::module_& m) {
    py::class_<PyRing>(m, "Ring",
                       "A reader of a sampler ring (the `sample` command's task): samples taken at the task's rate, "
                       "each delivered once, loss counted when this reader falls behind. Many readers may follow one "
                       "ring; none of them can delay the task.")
        .def_static("attach", [](const std::string& name) {
            auto r = std::make_unique<PyRing>();
            r->reader = sampler::RingReader::attach(name);
            r->life.watch(Lifeline::subsystem_of(name), "Ring", [raw = r.get()] { raw->reader = sampler::RingReader(); });
            return r;
        }, py::arg("name"), "Map the ring NAME read-only; reading starts with the next sample written.")
        .def_property_readonly("name", [](PyRing& r) { return r.live().name(); }, "the ring's shared-memory segment")
        .def_property_readonly("channels", [](PyRing& r) { return r.live().channel_names(); },
                               "column names: 'Q_REF[0]', ..., or 'X' for a scalar")
        .def_property_readonly("capacity", [](PyRing& r) { return r.live().capacity(); },
                               "samples the ring holds before the oldest is overwritten")
        .def_property_readonly("rate", [](PyRing& r) { return r.live().rate_hz(); }, "the sampling task's rate, Hz")
        .def_property_readonly("position", [](PyRing& r) { return r.live().position(); },
                               "number of the next sample this reader takes")
        .def_property_readonly("head", [](PyRing& r) { return r.live().head(); }, "samples written so far")
        .def_property_readonly("lost", [](PyRing& r) { return r.live().lost_total(); },
                               "samples this reader lost (overwritten before it read them) since it attached")
        .def_property_readonly("closed", [](PyRing& r) { return r.live().closed(); },
                               "True once the sampling task has been killed: nothing follows")
        .def("rewind", [](PyRing& r) { r.live().rewind(); }, "Go back to the oldest sample the ring still holds.")
        .def("read", &PyRing::read, py::arg("max_samples") = py::none(),
             "The samples written since the last read (at most MAX_SAMPLES), oldest first: (time_ns int64[n], "
             "cycle uint64[n], values float64[n, channels], lost) — lost: samples skipped because this reader fell "
             "behind.")
        .def("__repr__", [](PyRing& r) {
            if (r.life.gone()) return "<chimera.Ring of subsystem " + r.life.subsystem() + ", finished>";
            return "<chimera.Ring " + r.reader.name() + ", " + std::to_string(r.reader.channels()) + " channels>";
        });
}

}  // namespace chimera::python
