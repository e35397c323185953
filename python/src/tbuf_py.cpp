// Triple buffers from Python (issue #18.3): write an item (bytes or a numpy
// array of the item's size) with its time-stamp, read the newest with its
// counter-stamp, time-stamp and the items missed. Lock-free and never
// blocking, so the GIL is kept (releasing it would cost more than the copy).
#include "bindings.hpp"

#include <chimera/ipc/segment.hpp>
#include <chimera/tbuf.hpp>

#include <cstring>

namespace chimera::python {

namespace {

struct TbufItem {
    std::string status;  // fresh, reused, empty
    std::uint64_t counter = 0;
    std::int64_t time_ns = 0;
    std::uint64_t missed = 0;
    py::object data;     // bytes (read()) or None (read_into())
};

const char* status_name(tbuf::ReadStatus s) {
    switch (s) {
        case tbuf::ReadStatus::fresh: return "fresh";
        case tbuf::ReadStatus::reused: return "reused";
        case tbuf::ReadStatus::empty: return "empty";
        case tbuf::ReadStatus::corrupt: return "corrupt";
    }
    return "corrupt";
}

struct PyTbuf {
    tbuf::Tbuf buf;
    std::string segment;
    bool owner = false;
    Lifeline life;  // attached: a subsystem's; created here: its own (never gone)

    /// The buffer, once the check says its subsystem's master still runs.
    tbuf::Tbuf& live() {
        life.check();
        return buf;
    }

    ~PyTbuf() {
        if (owner) (void)buf.destroy();
    }

    py::buffer_info item_buffer(const py::buffer& b, bool writeable) const {
        py::buffer_info info = b.request(writeable);
        if (static_cast<std::size_t>(info.size * info.itemsize) != buf.item_size())
            throw py::value_error("TBUF " + name() + " holds items of " + std::to_string(buf.item_size()) +
                                  " bytes, not " + std::to_string(info.size * info.itemsize));
        const bool contiguous = info.ndim <= 1 ? info.strides.empty() || info.strides[0] == info.itemsize
                                               : py::array::ensure(b).attr("flags").attr("c_contiguous").cast<bool>();
        if (!contiguous) throw py::value_error("TBUF " + name() + ": the item must be contiguous in memory");
        return info;
    }

    const std::string& name() const { return segment; }

    std::uint64_t write(const py::buffer& item, std::optional<std::int64_t> time_ns) {
        life.check();
        const py::buffer_info info = item_buffer(item, false);
        const std::uint64_t counter = time_ns ? buf.write(info.ptr, *time_ns) : buf.write(info.ptr);
        if (counter == tbuf::kCorrupt) throw TbufError("TBUF write refused: " + buf.fault_message());
        return counter;
    }

    TbufItem finish(const tbuf::ReadResult& r) const {
        if (r.status == tbuf::ReadStatus::corrupt) throw TbufError("TBUF read refused: " + buf.fault_message());
        return TbufItem{status_name(r.status), r.counter, r.time_ns, r.missed, py::none()};
    }

    TbufItem read() {
        life.check();
        std::string bytes(buf.item_size(), '\0');
        TbufItem item = finish(buf.read(bytes.data()));
        item.data = item.status == "empty" ? py::object(py::none()) : py::object(py::bytes(bytes));
        return item;
    }

    TbufItem read_into(const py::buffer& out) {
        life.check();
        const py::buffer_info info = item_buffer(out, true);
        return finish(buf.read(info.ptr));
    }
};

}  // namespace

void bind_tbuf(py::module_& m) {
    py::class_<TbufItem>(m, "TbufItem", "What a TBUF read found.")
        .def_readonly("status", &TbufItem::status, "'fresh' (not seen before), 'reused' (the same again) or 'empty'")
        .def_readonly("counter", &TbufItem::counter, "counter-stamp: 0 for the first item written, +1 per write")
        .def_readonly("time_ns", &TbufItem::time_ns, "time-stamp, CLOCK_MONOTONIC ns (time.monotonic_ns())")
        .def_readonly("missed", &TbufItem::missed, "items written but never read since the last fresh read")
        .def_readonly("data", &TbufItem::data, "the item's bytes (read()); None from read_into() or when empty")
        .def("__repr__", [](const TbufItem& i) {
            return "<TbufItem " + i.status + " counter=" + std::to_string(i.counter) + " missed=" +
                   std::to_string(i.missed) + ">";
        });

    py::class_<PyTbuf>(m, "Tbuf", "A triple buffer (TBUF, thesis §5.6): one writer, one reader, never blocking.")
        .def_static("create", [](const std::string& name, std::size_t item_size) {
            auto t = std::make_unique<PyTbuf>();
            t->buf = tbuf::Tbuf::create(name, item_size);
            t->segment = name;
            t->owner = true;
            return t;
        }, py::arg("name"), py::arg("item_size"),
           "A new buffer in segment NAME (e.g. segment_name('arm', 'force')); removed when this object "
           "goes and no other live process maps it.")
        .def_static("attach", [](const std::string& name) {
            auto t = std::make_unique<PyTbuf>();
            t->buf = tbuf::Tbuf::attach(name);
            t->segment = name;
            // Its subsystem's end unmaps it, and removes it when this was its last user.
            t->life.watch(Lifeline::subsystem_of(name), "Tbuf", [raw = t.get()] { (void)raw->buf.destroy(); });
            return t;
        }, py::arg("name"))
        .def_property_readonly("item_size", [](PyTbuf& t) { return t.live().item_size(); }, "bytes per item")
        .def_property_readonly("missed_total", [](PyTbuf& t) { return t.live().missed_total(); },
                               "items this object's reads found missed (written, never read), in total")
        .def("write", &PyTbuf::write, py::arg("item"), py::arg("time_ns") = py::none(),
             "Publish ITEM (bytes-like of item_size bytes) stamped now (or at TIME_NS); returns its counter.")
        .def("read", &PyTbuf::read, "The newest item, its bytes in .data.")
        .def("read_into", &PyTbuf::read_into, py::arg("out"),
             "The newest item copied into OUT (a writable buffer of item_size bytes, e.g. a numpy array).")
        .def("detach", [](PyTbuf& t) {
            t.life.check();
            t.owner = false;
            t.buf.detach();
        }, "Unmap the buffer and leave its segment in place, even one this object created.");
}

}  // namespace chimera::python
