// The state-variable table from Python (issue #18.2): attach by subsystem,
// the variables with their producers, whole-set reads and writes under one
// table lock into and out of numpy arrays.
//
// The GIL is released around every call that takes the table lock (it may
// spin or wait for a holder), and no Python code runs while the lock is held:
// values are checked and converted into a private local table first, then one
// copy_to_global / copy_from_global moves the whole set (issue #18.6).
#include "bindings.hpp"

#include "svar_values.hpp"

#include <chimera/ipc/segment.hpp>

#include <cerrno>
#include <cstring>

namespace chimera::python {

namespace {

const char* numpy_name(svar::Type t) {
    switch (t) {
        case svar::Type::byte_: return "uint8";
        case svar::Type::char_: return "int8";
        case svar::Type::word: return "uint16";
        case svar::Type::short_: return "int16";
        case svar::Type::unsigned_: return "uint32";
        case svar::Type::int_: return "int32";
        case svar::Type::float_: return "float32";
        case svar::Type::double_: return "float64";
        case svar::Type::struct_: return "uint8";
    }
    return "uint8";
}

// A struct[N] variable is an (NELEM, N) array of bytes; any other (NELEM,).
std::vector<py::ssize_t> shape_of(const svar::VarInfo& v) {
    if (v.type() == svar::Type::struct_)
        return {static_cast<py::ssize_t>(v.nelem()), static_cast<py::ssize_t>(v.elem_size())};
    return {static_cast<py::ssize_t>(v.nelem())};
}

py::object values_or_none(const svar::VarInfo& v, bool present, double (svar::VarInfo::*at)(std::size_t) const) {
    if (!present || v.type() == svar::Type::struct_) return py::none();
    py::array_t<double> a(static_cast<py::ssize_t>(v.nelem()));
    auto w = a.mutable_unchecked<1>();
    for (std::size_t k = 0; k < v.nelem(); ++k) w(static_cast<py::ssize_t>(k)) = (v.*at)(k);
    return a;
}

}  // namespace

std::vector<std::string> split_names(const std::string& list) {
    std::vector<std::string> out;
    std::size_t start = 0;
    while (start <= list.size()) {
        const std::size_t comma = std::min(list.find(',', start), list.size());
        if (comma > start) out.push_back(list.substr(start, comma - start));
        start = comma + 1;
    }
    return out;
}

void throw_if_not_transferred(svar::Status st, const std::string& table, const char* what) {
    if (svar::transferred(st)) return;
    if (st == svar::Status::timed_out)
        throw LockTimeout(table + ": " + what + ": the table lock was not obtained in time (nothing transferred)");
    throw SvarError(table + ": " + what + ": " + svar::to_string(st) + " (nothing transferred)");
}

// ------------------------------------------------------------------ PyTable

std::shared_ptr<PyTable> PyTable::attach(const std::string& subsystem, double lock_timeout_s) {
    auto t = std::shared_ptr<PyTable>(new PyTable());
    t->subsystem_ = subsystem;
    const std::string segment = ipc::segment_name(subsystem, "svar");
    try {
        t->table_ = svar::Table::attach(segment);
    } catch (const ipc::SegmentError& e) {
        if (e.error_number() == ENOENT)
            throw SvarError("no subsystem " + subsystem + " is running (no segment " + segment + ")");
        throw SvarError("attaching to subsystem " + subsystem + ": " + e.what());
    }
    t->life_.watch(subsystem, "Table", [raw = t.get()] { raw->release(); });
    t->needs_status_ = true;
    t->attach_status();
    t->set_lock_timeout(lock_timeout_s);
    return t;
}

// The status segment tells who produces what. The master makes it just after
// the table, so a failure is tried again at the next use, and a write is
// refused while the producer rule cannot be checked (status_error_).
bool PyTable::attach_status() const {
    if (status_ || !needs_status_) return true;
    int error_number = 0;
    status_ = prof::StatusReader::try_attach(subsystem_, error_number, status_error_);
    if (!status_) return false;
    try {
        ipc::AttachOptions read_only_use;
        read_only_use.prefault = false;
        status_map_ = ipc::Segment::attach(status_->name(), {ipc::ObjectType::prof_status, prof::kStatusLayoutVersion},
                                           read_only_use);
    } catch (const ipc::SegmentError& e) {
        status_.reset();
        status_error_ = e.what();
        return false;
    }
    return true;
}

std::shared_ptr<PyTable> PyTable::create(const std::string& subsystem, const std::string& svar_file,
                                         double lock_timeout_s) {
    auto t = std::shared_ptr<PyTable>(new PyTable());
    t->subsystem_ = subsystem;
    t->table_ = svar::Table::create(ipc::segment_name(subsystem, "svar"), svar_file);
    t->owner_ = true;
    t->set_lock_timeout(lock_timeout_s);
    return t;
}

PyTable::~PyTable() {
    if (owner_) (void)table_.destroy();
}

// The master has finished: this process must not keep its table alive. The
// master removed the name already (end_for_all); after a crash it is removed
// here when this was the last user.
void PyTable::release() {
    (void)table_.destroy();
    status_.reset();
    status_map_.detach();
    users_.clear();
    needs_status_ = false;
}

void PyTable::set_lock_timeout(double seconds) {
    life_.check();
    if (!(seconds > 0) || seconds > 3600) throw py::value_error("lock_timeout must be in (0, 3600] seconds");
    ipc::LockOptions o = table_.lock_options();
    o.timeout_ns = static_cast<std::int64_t>(seconds * 1e9);
    table_.set_lock_options(o);
}

double PyTable::lock_timeout() const {
    life_.check();
    return static_cast<double>(table_.lock_options().timeout_ns) / 1e9;
}

std::size_t PyTable::index_of(const std::string& name) const {
    life_.check();
    const auto ix = table_.find(name);
    if (!ix) {
        std::string known;
        for (std::size_t i = 0; i < table_.size() && i < 12; ++i)
            known += (known.empty() ? "" : " ") + std::string(table_.var(i).name());
        throw py::key_error("table " + table_.name() + " has no variable " + name + " (it has " + known +
                            (table_.size() > 12 ? " ..." : "") + ")");
    }
    return *ix;
}

const std::map<std::string, PyTable::Users>& PyTable::all_users() const {
    if (!attach_status() || !status_) return users_;  // none known: a table made here, or see attach_status()
    const auto* hdr = static_cast<const prof::StatusHeader*>(status_map_.base());
    const std::uint32_t generation = hdr->generation.load(std::memory_order_acquire);
    if (users_generation_ == generation) return users_;
    users_.clear();
    for (const auto& task : status_->snapshot()) {
        for (const auto& v : split_names(task.outputs)) users_[v].producers.push_back(task.rmod);
        for (const auto& v : split_names(task.inputs)) users_[v].consumers.push_back(task.rmod);
    }
    users_generation_ = generation;  // a claim during the snapshot moves it again: read anew next time
    return users_;
}

PyTable::Users PyTable::users_of(const std::string& name) const {
    const auto& all = all_users();
    const auto it = all.find(name);
    return it == all.end() ? Users{} : it->second;
}

VarRecord PyTable::info(const std::string& name) const {
    const svar::VarInfo v = table_.var(index_of(name));
    VarRecord r;
    r.name = std::string(v.name());
    r.index = v.index();
    r.type = svar::type_spelling(v.type(), v.elem_size());
    r.nelem = v.nelem();
    r.elem_size = v.elem_size();
    r.desc = std::string(v.desc());
    r.units = std::string(v.units());
    r.dtype = py::dtype(numpy_name(v.type()));
    r.shape = py::tuple(py::cast(shape_of(v)));
    r.init = values_or_none(v, true, &svar::VarInfo::init);
    r.min = values_or_none(v, v.has_range(), &svar::VarInfo::min);
    r.max = values_or_none(v, v.has_range(), &svar::VarInfo::max);
    const Users u = users_of(r.name);
    r.producers = u.producers;
    r.consumers = u.consumers;
    return r;
}

std::vector<VarRecord> PyTable::variables() const {
    life_.check();
    std::vector<VarRecord> out;
    for (std::size_t i = 0; i < table_.size(); ++i) out.push_back(info(std::string(table_.var(i).name())));
    return out;
}

std::vector<std::string> PyTable::names() const {
    life_.check();
    std::vector<std::string> out;
    for (std::size_t i = 0; i < table_.size(); ++i) out.emplace_back(table_.var(i).name());
    return out;
}

py::object PyTable::read(const py::object& names) {
    if (py::isinstance<py::str>(names)) {
        Reader r(shared_from_this(), std::vector<std::string>{names.cast<std::string>()});
        r.read();
        return r.copy_of(0);
    }
    Reader r(shared_from_this(), names.cast<std::vector<std::string>>());
    r.read();
    py::dict out;
    for (std::size_t i = 0; i < r.size(); ++i) out[py::str(r.names()[i])] = r.copy_of(i);
    return out;
}

void PyTable::write(const py::object& what, const py::object& values, bool force) {
    std::vector<std::string> names;
    std::vector<py::object> items;
    if (py::isinstance<py::str>(what)) {
        if (values.is_none()) throw py::type_error("write(NAME, VALUES): VALUES missing");
        names.push_back(what.cast<std::string>());
        items.push_back(values);
    } else {
        if (!values.is_none()) throw py::type_error("write({NAME: VALUES, ...}) takes no second argument");
        for (const auto& [k, v] : what.cast<py::dict>()) {
            names.push_back(k.cast<std::string>());
            items.push_back(py::reinterpret_borrow<py::object>(v));
        }
    }
    Writer w(shared_from_this(), names, force);
    for (std::size_t i = 0; i < names.size(); ++i) w.fill(i, items[i]);
    w.write();
}

void PyTable::check_producers(const std::vector<std::string>& names) const {
    if (!attach_status())
        throw ProducerConflict(table_.name() + ": cannot tell which tasks produce " + names.front() +
                               " (status of subsystem " + subsystem_ + ": " + status_error_ +
                               "); write(..., force=True) writes anyway");
    const auto& all = all_users();
    for (const auto& name : names) {
        const auto it = all.find(name);
        if (it == all.end() || it->second.producers.empty()) continue;
        const Users& u = it->second;
        std::string who;
        for (const auto& p : u.producers) who += (who.empty() ? "" : ", ") + p;
        throw ProducerConflict(table_.name() + ": " + name + " is produced by " + who +
                               ": its next cycle overwrites it (write(..., force=True) writes it anyway)");
    }
}

py::dict PyTable::stats() const {
    life_.check();
    const svar::TableStats s = table_.stats();
    py::dict d;
    d["recoveries"] = s.recoveries;
    d["rollbacks"] = s.rollbacks;
    d["timeouts"] = s.timeouts;
    d["forced"] = s.forced;
    return d;
}

// ------------------------------------------------------------------ Reader

namespace {
// The local table of `names`, made with the GIL released: making it takes the
// table lock once (it starts from the table's current values).
svar::LocalTable checked_local(PyTable& t, const std::vector<std::string>& names) {
    if (names.empty()) throw py::value_error("no variable named");
    for (const auto& n : names) (void)t.index_of(n);  // a KeyError naming the table and the variable
    const Lifeline::Use in_use(t.life());  // the table stays mapped while the GIL is released
    try {
        py::gil_scoped_release nogil;
        return svar::LocalTable(t.table_unchecked(), names);
    } catch (const svar::Error& e) {
        if (std::string_view(e.what()).find(svar::to_string(svar::Status::timed_out)) != std::string_view::npos)
            throw_if_not_transferred(svar::Status::timed_out, t.table().name(), "read");
        throw;
    }
}
}  // namespace

Reader::Reader(std::shared_ptr<PyTable> table, std::vector<std::string> names)
    : table_(std::move(table)), names_(std::move(names)) {
    svar::LocalTable local = checked_local(*table_, names_);
    svar::VarSet set = local.make_set(names_);
    store_ = std::make_shared<Storage>(Storage{std::move(local), std::move(set)});
}

Reader::Busy::Busy(Reader& r) : flag_(r.busy_) {
    if (flag_.exchange(true, std::memory_order_acquire))
        throw SvarError(r.table_->table().name() + ": a Reader or Writer is one thread's at a time (another thread "
                        "is transferring through this one now): make one per thread");
}

void Reader::read() {
    const Busy busy(*this);
    const Lifeline::Use in_use(table_->life());
    svar::Status st;
    {
        py::gil_scoped_release nogil;
        st = store_->local.copy_from_global(store_->set);
    }
    throw_if_not_transferred(st, table_->table().name(), "read");
    last_ = st;
}

py::array Reader::view(std::size_t i, bool writeable) const {
    const svar::VarInfo v = table_->table().var(names_[i]);
    auto* keep = new std::shared_ptr<Storage>(store_);
    py::capsule base(keep, [](void* p) { delete static_cast<std::shared_ptr<Storage>*>(p); });
    py::array a(py::dtype(numpy_name(v.type())), shape_of(v), {}, store_->local.translate_any(names_[i]), base);
    if (!writeable) py::detail::array_proxy(a.ptr())->flags &= ~py::detail::npy_api::NPY_ARRAY_WRITEABLE_;
    return a;
}

py::array Reader::copy_of(std::size_t i) const {
    const svar::VarInfo v = table_->table().var(names_[i]);
    return py::array(py::dtype(numpy_name(v.type())), shape_of(v), {}, store_->local.translate_any(names_[i]));  // no base: copied
}

const py::dict& Reader::views(bool writeable) {
    py::dict& d = writeable ? writeable_ : read_only_;
    if (d.empty())
        for (std::size_t i = 0; i < names_.size(); ++i) d[py::str(names_[i])] = view(i, writeable);
    return d;
}

// ------------------------------------------------------------------ Writer

Writer::Writer(std::shared_ptr<PyTable> table, std::vector<std::string> names, bool force)
    : Reader(std::move(table), std::move(names)), force_(force) {}

void Writer::fill(std::size_t i, const py::object& value) {
    const std::string& name = names()[i];
    const svar::VarInfo v = table_->table().var(name);
    auto* dst = static_cast<unsigned char*>(store_->local.translate_any(name));
    if (v.type() == svar::Type::struct_) {
        const py::buffer_info b = py::buffer(value).request();
        if (static_cast<std::size_t>(b.size * b.itemsize) != v.bytes())
            throw py::value_error(name + " is " + tools::type_text(v) + ": give exactly " + std::to_string(v.bytes()) +
                                  " bytes, not " + std::to_string(b.size * b.itemsize));
        std::memcpy(dst, b.ptr, v.bytes());
        return;
    }
    const auto a = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(value);
    if (!a) throw py::type_error(name + ": the values are not numbers");
    const auto n = static_cast<std::size_t>(a.size());
    if (n != v.nelem() && n != 1)
        throw py::value_error(name + " has " + std::to_string(v.nelem()) + " elements: give one value for all or every value, not " +
                              std::to_string(n));
    for (std::size_t k = 0; k < v.nelem(); ++k) {
        const double x = a.data()[n == 1 ? 0 : k];
        if (const std::string why = tools::value_refusal(v, k, x); !why.empty())
            throw py::value_error(table_->table().name() + ": " + name + "[" + std::to_string(k) + "]: " +
                                  py::str(py::float_(x)).cast<std::string>() + " " + why);
        tools::store_number(v, dst, k, x);
    }
}

void Writer::check_local() {
    for (const auto& name : names()) {
        const svar::VarInfo v = table_->table().var(name);
        const auto values = tools::numbers_of(v, static_cast<const unsigned char*>(store_->local.translate_any(name)));
        for (std::size_t k = 0; k < values.size(); ++k)
            if (const std::string why = tools::value_refusal(v, k, values[k]); !why.empty())
                throw py::value_error(table_->table().name() + ": " + name + "[" + std::to_string(k) + "]: " +
                                      py::str(py::float_(values[k])).cast<std::string>() + " " + why);
    }
}

void Writer::write() {
    const Busy busy(*this);
    const Lifeline::Use in_use(table_->life());
    if (!force_) table_->check_producers(names());
    check_local();
    svar::Status st;
    {
        py::gil_scoped_release nogil;
        st = store_->local.copy_to_global(store_->set);
    }
    throw_if_not_transferred(st, table_->table().name(), "write");
    last_ = st;
}

}  // namespace chimera::python
