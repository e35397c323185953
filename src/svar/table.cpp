// The global state variable table: creation from a spec, attach, the locked
// single-variable access, the undo record and its roll-back.
#include <cstring>
#include <new>
#include <utility>

#include "chimera/svar.hpp"
#include "layout.hpp"

namespace chimera::svar {

using detail::Descriptor;
using detail::TableHeader;

namespace {

constexpr ipc::SegmentKind kKind{ipc::ObjectType::svar_table, kLayoutVersion};

// Stores `x` as one element of type `t` at `dst`.
void store_value(Type t, void* dst, double x) noexcept {
    switch (t) {
        case Type::byte_: { auto v = static_cast<std::uint8_t>(x); std::memcpy(dst, &v, 1); break; }
        case Type::char_: { auto v = static_cast<char>(static_cast<int>(x)); std::memcpy(dst, &v, 1); break; }
        case Type::word: { auto v = static_cast<std::uint16_t>(x); std::memcpy(dst, &v, 2); break; }
        case Type::short_: { auto v = static_cast<std::int16_t>(x); std::memcpy(dst, &v, 2); break; }
        case Type::unsigned_: { auto v = static_cast<std::uint32_t>(x); std::memcpy(dst, &v, 4); break; }
        case Type::int_: { auto v = static_cast<std::int32_t>(x); std::memcpy(dst, &v, 4); break; }
        case Type::float_: { auto v = static_cast<float>(x); std::memcpy(dst, &v, 4); break; }
        case Type::double_: std::memcpy(dst, &x, 8); break;
        case Type::struct_: break;
    }
}

template <typename T>
double load_as(const void* src) noexcept {
    T v;
    std::memcpy(&v, src, sizeof v);
    return static_cast<double>(v);
}

}  // namespace

double element_value(Type t, const void* src) noexcept {
    switch (t) {
        case Type::byte_: return load_as<std::uint8_t>(src);
        case Type::char_: return load_as<char>(src);
        case Type::word: return load_as<std::uint16_t>(src);
        case Type::short_: return load_as<std::int16_t>(src);
        case Type::unsigned_: return load_as<std::uint32_t>(src);
        case Type::int_: return load_as<std::int32_t>(src);
        case Type::float_: return load_as<float>(src);
        case Type::double_: return load_as<double>(src);
        case Type::struct_: return 0.0;
    }
    return 0.0;
}

const char* to_string(Status s) noexcept {
    switch (s) {
        case Status::ok: return "ok";
        case Status::recovered: return "lock recovered from a dead holder";
        case Status::forced: return "lock reset after a timeout";
        case Status::lock_lost: return "lock reset by another task while held";
        case Status::timed_out: return "lock timed out";
        case Status::reentered: return "table lock already held by this thread";
        case Status::bad_argument: return "not a variable of this table";
        case Status::lock_corrupt: return "the SVAR table's lock word is corrupt (it names no thread that could hold it)";
        case Status::read_only: return "permission denied: the table is watched read-only (only its owner writes)";
    }
    return "unknown";
}

// --- VarInfo -----------------------------------------------------------------

std::size_t VarInfo::index() const noexcept {
    return static_cast<std::size_t>(d_ - table_->desc_);
}
std::string_view VarInfo::name() const noexcept { return d_->name; }
Type VarInfo::type() const noexcept { return static_cast<Type>(d_->type); }
std::size_t VarInfo::elem_size() const noexcept { return d_->elem_size; }
std::size_t VarInfo::nelem() const noexcept { return d_->nelem; }
std::string_view VarInfo::desc() const noexcept {
    return {table_->seg_.at_bytes<const char>(d_->desc_offset), d_->desc_len};
}
std::string_view VarInfo::units() const noexcept {
    return {table_->seg_.at_bytes<const char>(d_->units_offset), d_->units_len};
}
bool VarInfo::has_range() const noexcept { return (d_->flags & detail::kHasRange) != 0; }
bool VarInfo::has_init() const noexcept { return (d_->flags & detail::kHasInit) != 0; }

double VarInfo::init(std::size_t k) const noexcept {
    if (!d_->init_offset || k >= d_->nelem) return 0.0;
    return element_value(type(), table_->seg_.at_bytes(d_->init_offset + k * d_->elem_size));
}
double VarInfo::min(std::size_t k) const noexcept {
    if (!d_->min_offset || k >= d_->nelem) return 0.0;
    return element_value(type(), table_->seg_.at_bytes(d_->min_offset + k * d_->elem_size));
}
double VarInfo::max(std::size_t k) const noexcept {
    if (!d_->max_offset || k >= d_->nelem) return 0.0;
    return element_value(type(), table_->seg_.at_bytes(d_->max_offset + k * d_->elem_size));
}

// --- Table -------------------------------------------------------------------

Table::Table() noexcept = default;
Table::Table(Table&& o) noexcept { *this = std::move(o); }
Table& Table::operator=(Table&& o) noexcept {
    if (this != &o) {
        seg_ = std::move(o.seg_);
        lock_options_ = o.lock_options_;
        hdr_ = std::exchange(o.hdr_, nullptr);
        own_desc_ = std::move(o.own_desc_);
        desc_ = std::exchange(o.desc_, nullptr);
        nvars_ = std::exchange(o.nvars_, 0);
        read_only_ = std::exchange(o.read_only_, false);
        data_ = std::exchange(o.data_, nullptr);
        undo_ = std::exchange(o.undo_, nullptr);
        undo_list_ = std::exchange(o.undo_list_, nullptr);
        source_ = std::exchange(o.source_, {});
    }
    return *this;
}
Table::~Table() = default;

Table::Table(ipc::Segment seg, const TableOptions& options) noexcept
    : seg_(std::move(seg)), lock_options_(options.lock) {
    bind();
}

// Keeps the fixed part of a table already checked (or just made): the
// descriptors copied, the areas' addresses, the counts.
void Table::bind() noexcept {
    hdr_ = seg_.at_bytes<TableHeader>(0);
    nvars_ = hdr_->nvars;
    read_only_ = seg_.read_only();
    own_desc_.reset(new (std::nothrow) Descriptor[nvars_]);
    if (own_desc_)
        std::memcpy(own_desc_.get(), seg_.at_bytes<const Descriptor>(hdr_->desc_offset),
                    nvars_ * sizeof(Descriptor));
    desc_ = own_desc_.get();
    if (!desc_) nvars_ = 0;  // out of memory: an empty table, not a shared one
    data_ = seg_.at_bytes(hdr_->data_offset);
    undo_ = seg_.at_bytes(hdr_->undo_offset);
    undo_list_ = seg_.at_bytes<std::uint32_t>(hdr_->undo_index_offset);
    source_ = {seg_.at_bytes<const char>(hdr_->source_offset), hdr_->source_len};
}

namespace {

// One descriptor's offsets and sizes, against the segment's `size`.
ipc::Fault descriptor_fault(const Descriptor& d, std::int64_t i, const TableHeader& h,
                            std::size_t size) noexcept {
    using ipc::fault_if;
    if (ipc::Fault f = fault_if(strnlen(d.name, sizeof d.name) > kMaxNameLength, "variable name length",
                                strnlen(d.name, sizeof d.name), kMaxNameLength, "at most", i))
        return f;
    if (ipc::Fault f = fault_if(d.type > static_cast<std::uint32_t>(Type::struct_), "variable type", d.type,
                                static_cast<std::uint32_t>(Type::struct_), "at most", i))
        return f;
    const auto type = static_cast<Type>(d.type);
    if (ipc::Fault f = fault_if(type != Type::struct_ && d.elem_size != type_size(type),
                                "variable element size", d.elem_size, type_size(type), "equal to", i))
        return f;
    if (ipc::Fault f = fault_if(d.elem_size == 0 || d.nelem == 0, "variable element size * NELEM",
                                std::uint64_t{d.elem_size} * d.nelem, 1, "at least", i))
        return f;
    if (ipc::Fault f = fault_if(d.bytes != std::uint64_t{d.elem_size} * d.nelem, "variable bytes", d.bytes,
                                std::uint64_t{d.elem_size} * d.nelem, "equal to", i))
        return f;
    if (ipc::Fault f = fault_if(d.data_offset % detail::kVarAlign != 0, "variable data offset",
                                d.data_offset, detail::kVarAlign, "a multiple of", i))
        return f;
    if (ipc::Fault f = fault_if(d.data_offset > h.data_bytes || d.bytes > h.data_bytes - d.data_offset,
                                "variable data end", d.data_offset + d.bytes, h.data_bytes, "at most", i))
        return f;
    // INIT/MIN/MAX values, DESC/UNITS strings: inside the segment.
    const auto inside = [&](std::uint64_t off, std::uint64_t len) { return off <= size && len <= size - off; };
    for (const std::uint64_t off : {d.init_offset, d.min_offset, d.max_offset})
        if (ipc::Fault f = fault_if(off != 0 && !inside(off, d.bytes), "variable INIT/MIN/MAX offset", off,
                                    size - std::min<std::uint64_t>(size, d.bytes), "at most", i))
            return f;
    if (ipc::Fault f = fault_if(!inside(d.desc_offset, d.desc_len), "variable DESC end",
                                d.desc_offset + d.desc_len, size, "at most", i))
        return f;
    return fault_if(!inside(d.units_offset, d.units_len), "variable UNITS end", d.units_offset + d.units_len,
                    size, "at most", i);
}

}  // namespace

ipc::Fault validate_table(const void* image, std::size_t size) noexcept {
    if (ipc::Fault f = ipc::header_fault(image, size, kKind)) return f;
    if (size < sizeof(TableHeader)) return {"size", -1, size, sizeof(TableHeader), "at least"};
    const auto* base = static_cast<const std::byte*>(image);
    const auto& h = *static_cast<const TableHeader*>(image);
    const auto inside = [&](std::uint64_t off, std::uint64_t len) { return off <= size && len <= size - off; };
    using ipc::fault_if;
    if (ipc::Fault f = fault_if(h.nvars == 0, "nvars", h.nvars, 1, "at least")) return f;
    if (ipc::Fault f = fault_if(!inside(h.desc_offset, std::uint64_t{h.nvars} * sizeof(Descriptor)),
                                "descriptors end", h.desc_offset + std::uint64_t{h.nvars} * sizeof(Descriptor),
                                size))
        return f;
    if (ipc::Fault f = fault_if(h.desc_offset % alignof(Descriptor) != 0, "descriptor offset", h.desc_offset,
                                alignof(Descriptor), "a multiple of"))
        return f;
    if (ipc::Fault f = fault_if(!inside(h.undo_index_offset, std::uint64_t{h.nvars} * 4) ||
                                    h.undo_index_offset % 4 != 0,
                                "undo list offset", h.undo_index_offset, size))
        return f;
    if (ipc::Fault f = fault_if(!inside(h.data_offset, h.data_bytes) || h.data_offset % 64 != 0, "data end",
                                h.data_offset + h.data_bytes, size))
        return f;
    if (ipc::Fault f = fault_if(!inside(h.undo_offset, h.data_bytes) || h.undo_offset % 64 != 0, "undo data end",
                                h.undo_offset + h.data_bytes, size))
        return f;
    if (ipc::Fault f = fault_if(!inside(h.source_offset, h.source_len), "source name end",
                                h.source_offset + h.source_len, size))
        return f;
    const auto* d = reinterpret_cast<const Descriptor*>(base + h.desc_offset);
    for (std::uint32_t i = 0; i < h.nvars; ++i)
        if (ipc::Fault f = descriptor_fault(d[i], i, h, size)) return f;
    if (h.undo_active.load(std::memory_order_relaxed) != 0) {
        if (ipc::Fault f = fault_if(h.undo_count > h.nvars, "undo count", h.undo_count, h.nvars)) return f;
        const auto* list = reinterpret_cast<const std::uint32_t*>(base + h.undo_index_offset);
        for (std::uint32_t i = 0; i < h.undo_count; ++i)
            if (ipc::Fault f = fault_if(list[i] >= h.nvars, "undo list index", list[i], h.nvars, "below", i))
                return f;
    }
    return {};
}

Table Table::create(const std::string& segment_name, const std::string& svar_file,
                    const TableOptions& options) {
    // Parse first: a bad file throws before any segment exists.
    return create(segment_name, parse_svar_file(svar_file), options);
}

Table Table::create(const std::string& segment_name, const TableSpec& spec,
                    const TableOptions& options) {
    using ipc::align_up;
    const std::size_t n = spec.vars.size();
    if (n == 0) throw Error("table " + segment_name + ": no variables");
    for (const VarSpec& v : spec.vars) {
        if (v.name.empty() || v.name.size() > kMaxNameLength)
            throw Error("table " + segment_name + ": bad variable name '" + v.name + "'");
        if (v.elem_size == 0 || v.nelem == 0)
            throw Error("table " + segment_name + ": variable " + v.name + " has no size");
        if (v.type != Type::struct_ && v.elem_size != type_size(v.type))
            throw Error("table " + segment_name + ": variable " + v.name +
                        " has the wrong element size for its type");
    }
    // Lay the segment out.
    std::size_t off = sizeof(TableHeader);
    const std::size_t desc_off = off;
    off += n * sizeof(Descriptor);
    const std::size_t undo_index_off = off;
    off = align_up(off + n * sizeof(std::uint32_t), 64);
    const std::size_t data_off = off;
    std::vector<std::size_t> var_off(n);
    std::size_t data_bytes = 0;
    for (std::size_t i = 0; i < n; ++i) {
        var_off[i] = data_bytes;
        data_bytes = align_up(data_bytes + spec.vars[i].bytes(), detail::kVarAlign);
    }
    data_bytes = align_up(data_bytes, 64);
    const std::size_t undo_off = data_off + data_bytes;
    off = undo_off + data_bytes;
    std::vector<std::size_t> val_off(n);
    for (std::size_t i = 0; i < n; ++i) {
        const VarSpec& v = spec.vars[i];
        val_off[i] = off;
        if (v.type != Type::struct_) off += v.bytes() * (v.has_range ? 3 : 1);
        off = align_up(off, 8);
    }
    std::vector<std::size_t> str_off(n);
    for (std::size_t i = 0; i < n; ++i) {
        str_off[i] = off;
        off += spec.vars[i].desc.size() + spec.vars[i].units.size();
    }
    const std::size_t source_off = off;
    off = align_up(off + spec.file.size() + 1, 64);
    const std::size_t total = off;

    ipc::Segment seg = ipc::Segment::create(segment_name, total, kKind, options.segment);
    // The segment is zero-filled: data without INIT is 0 as the thesis says.
    TableHeader& hdr = *seg.at_bytes<TableHeader>(0);
    new (&hdr.lock) ipc::LockWord{};
    hdr.nvars = static_cast<std::uint32_t>(n);
    hdr.source_len = static_cast<std::uint32_t>(spec.file.size());
    hdr.desc_offset = desc_off;
    hdr.undo_index_offset = undo_index_off;
    hdr.data_offset = data_off;
    hdr.data_bytes = data_bytes;
    hdr.undo_offset = undo_off;
    hdr.source_offset = source_off;
    hdr.illegal_config.store(0, std::memory_order_relaxed);
    hdr.rollbacks.store(0, std::memory_order_relaxed);
    hdr.undo_active.store(0, std::memory_order_relaxed);
    std::memcpy(seg.at_bytes(source_off), spec.file.data(), spec.file.size());

    auto* descs = seg.at_bytes<Descriptor>(desc_off);
    for (std::size_t i = 0; i < n; ++i) {
        const VarSpec& v = spec.vars[i];
        Descriptor& d = descs[i];
        std::memset(&d, 0, sizeof d);
        std::memcpy(d.name, v.name.data(), v.name.size());
        d.type = static_cast<std::uint32_t>(v.type);
        d.elem_size = static_cast<std::uint32_t>(v.elem_size);
        d.nelem = static_cast<std::uint32_t>(v.nelem);
        d.data_offset = var_off[i];
        d.bytes = v.bytes();
        if (v.type != Type::struct_) {
            d.flags |= v.has_init ? detail::kHasInit : 0u;
            d.init_offset = val_off[i];
            std::byte* data = seg.at_bytes(data_off + var_off[i]);
            for (std::size_t k = 0; k < v.nelem; ++k) {
                const double x = v.init_at(k);
                store_value(v.type, seg.at_bytes(d.init_offset + k * v.elem_size), x);
                store_value(v.type, data + k * v.elem_size, x);  // INIT applied at creation
            }
            if (v.has_range) {
                d.flags |= detail::kHasRange;
                d.min_offset = val_off[i] + v.bytes();
                d.max_offset = val_off[i] + 2 * v.bytes();
                for (std::size_t k = 0; k < v.nelem; ++k) {
                    store_value(v.type, seg.at_bytes(d.min_offset + k * v.elem_size), v.min[k]);
                    store_value(v.type, seg.at_bytes(d.max_offset + k * v.elem_size), v.max[k]);
                }
            }
        }
        d.desc_offset = str_off[i];
        d.desc_len = static_cast<std::uint32_t>(v.desc.size());
        std::memcpy(seg.at_bytes(d.desc_offset), v.desc.data(), v.desc.size());
        d.units_offset = str_off[i] + v.desc.size();
        d.units_len = static_cast<std::uint32_t>(v.units.size());
        std::memcpy(seg.at_bytes(d.units_offset), v.units.data(), v.units.size());
    }
    seg.publish();
    Table t(std::move(seg), options);
    if (!t.desc_) {
        t.destroy();  // nothing half-built is left behind
        throw std::bad_alloc();
    }
    return t;
}

Table Table::attach(const std::string& segment_name, const TableOptions& options) {
    return checked(ipc::Segment::attach(segment_name, kKind, options.attach), options);
}

Table Table::watch(const std::string& segment_name, const TableOptions& options) {
    return checked(ipc::Segment::watch(segment_name, kKind, options.attach), options);
}

Table Table::checked(ipc::Segment seg, const TableOptions& options) {
    const std::string segment_name = seg.name();
    // Validate every offset before trusting any; the handle keeps what it checked.
    if (const ipc::Fault f = validate_table(seg.base(), seg.size()))
        throw Error("table " + segment_name + ": corrupt: " + ipc::describe(segment_name, f));
    Table t(std::move(seg), options);
    if (!t.desc_) throw std::bad_alloc();
    return t;
}

void Table::detach() noexcept {
    seg_.detach();
    hdr_ = nullptr;
    desc_ = nullptr;
    data_ = nullptr;
}

bool Table::destroy() noexcept {
    const bool removed = seg_.detach_destroy_if_last();
    hdr_ = nullptr;
    desc_ = nullptr;
    data_ = nullptr;
    return removed;
}

bool Table::end_for_all() noexcept {
    const bool removed = seg_.end_for_all();
    hdr_ = nullptr;
    desc_ = nullptr;
    data_ = nullptr;
    return removed;
}

std::string_view Table::source_file() const noexcept { return source_; }

std::size_t Table::size() const noexcept { return nvars_; }

std::optional<std::size_t> Table::find(std::string_view name) const noexcept {
    for (std::size_t i = 0; i < size(); ++i)
        if (name == desc_[i].name) return i;
    return std::nullopt;
}

std::size_t Table::index_of(std::string_view name) const {
    if (auto i = find(name)) return *i;
    throw Error("table " + seg_.name() + " (" + std::string(source_file()) + ") has no variable " +
                std::string(name));
}

VarInfo Table::var(std::size_t index) const noexcept { return VarInfo(this, desc_ + index); }

ipc::LockWord& Table::lock_word() const noexcept { return hdr_->lock; }

std::uint32_t Table::illegal_configuration() const noexcept {
    return hdr_->illegal_config.load(std::memory_order_acquire);
}
void Table::set_illegal_configuration(std::uint32_t flags) noexcept {
    if (read_only()) return;  // a watcher's mapping is PROT_READ
    hdr_->illegal_config.store(flags, std::memory_order_release);
}

TableStats Table::stats() const noexcept {
    return TableStats{hdr_->lock.recoveries.load(std::memory_order_relaxed),
                      hdr_->rollbacks.load(std::memory_order_relaxed),
                      hdr_->lock.timeouts.load(std::memory_order_relaxed),
                      hdr_->lock.forced.load(std::memory_order_relaxed)};
}

// --- the cycle path ------------------------------------------------------------

void Table::save_undo(const std::uint32_t* indices, std::size_t count) noexcept {
    std::byte* undo = undo_;
    std::uint32_t* list = undo_list_;
    for (std::size_t i = 0; i < count; ++i) {
        const Descriptor& d = desc_[indices[i]];
        detail::copy_var(undo + d.data_offset, data_ + d.data_offset, d.bytes);
        list[i] = indices[i];
    }
    detail::undo_mark(*hdr_, static_cast<std::uint32_t>(count), ipc::self_owner_id());
}

void Table::clear_undo() noexcept { detail::undo_clear(*hdr_); }

void Table::roll_back() noexcept {
    // A holder that died inside undo_mark() may have left the write sequence
    // odd with no record active: even it again (we hold the lock: the writer).
    const auto seq = hdr_->write_seq.load(std::memory_order_relaxed);
    if (hdr_->undo_active.load(std::memory_order_acquire) == 0) {
        if (seq & 1u) hdr_->write_seq.store(seq + 1, std::memory_order_release);
        return;
    }
    if ((seq & 1u) == 0) ipc::seqlock::write_begin(hdr_->write_seq);
    const std::byte* undo = undo_;
    const std::uint32_t* list = undo_list_;
    // Written by another process (the writer that died): bounded before use.
    const std::uint32_t count = hdr_->undo_count <= nvars_ ? hdr_->undo_count : 0;
    for (std::uint32_t i = 0; i < count; ++i) {
        if (list[i] >= nvars_) continue;
        const Descriptor& d = desc_[list[i]];
        std::memcpy(data_ + d.data_offset, undo + d.data_offset, d.bytes);
    }
    hdr_->rollbacks.fetch_add(1, std::memory_order_relaxed);
    hdr_->undo_active.store(0, std::memory_order_release);
    ipc::seqlock::write_end(hdr_->write_seq);
}

Status Table::read(std::size_t index, void* buffer) noexcept {
    if (index >= size()) return Status::bad_argument;
    const Descriptor& d = desc_[index];
    if (read_only()) {
        // A watcher may not write the lock word, and must not make a task wait:
        // a copy that no write overlapped (writers hold the lock, one at a time).
        const bool whole = ipc::seqlock::read_consistent(
            hdr_->write_seq, [&]() noexcept { std::memcpy(buffer, data_ + d.data_offset, d.bytes); },
            lock_options_.timeout_ns >= 0 ? lock_options_.timeout_ns : ipc::LockOptions{}.timeout_ns);
        return whole ? Status::ok : Status::timed_out;
    }
    const Status s = acquire();
    if (!transferred(s)) return s;
    std::memcpy(buffer, data_ + d.data_offset, d.bytes);
    return release(s);
}

Status Table::write(std::size_t index, const void* buffer) noexcept {
    if (index >= size()) return Status::bad_argument;
    if (read_only()) return Status::read_only;
    const Descriptor& d = desc_[index];
    const Status s = acquire();
    if (!transferred(s)) return s;
    const auto ix = static_cast<std::uint32_t>(index);
    save_undo(&ix, 1);
    std::memcpy(data_ + d.data_offset, buffer, d.bytes);
    clear_undo();
    return release(s);
}

}  // namespace chimera::svar
