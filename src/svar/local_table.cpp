// Local tables: a task's private copy of its variables, and the copies
// between it and the global table, each under one acquisition of the lock.
#include <algorithm>
#include <cstdlib>
#include <cstring>
#include <new>

#include "chimera/svar.hpp"
#include "layout.hpp"

namespace chimera::svar {

namespace {

void free_buffer(std::byte* p) { std::free(p); }

std::byte* alloc_buffer(std::size_t bytes) {
    const std::size_t size = ipc::align_up(bytes == 0 ? 64 : bytes, 64);
    void* p = std::aligned_alloc(64, size);
    if (!p) throw std::bad_alloc();
    std::memset(p, 0, size);
    return static_cast<std::byte*>(p);
}

}  // namespace

LocalTable::LocalTable(Table& global, std::vector<std::string> in_consts,
                       std::vector<std::string> out_consts, std::vector<std::string> in_vars,
                       std::vector<std::string> out_vars)
    : global_(&global), buffer_(nullptr, &free_buffer) {
    build({&in_consts, &out_consts, &in_vars, &out_vars},
          {"in-consts", "out-consts", "in-vars", "out-vars"});
    in_consts_ = set_of(in_consts, "in-consts");
    out_consts_ = set_of(out_consts, "out-consts");
    in_vars_ = set_of(in_vars, "in-vars");
    out_vars_ = set_of(out_vars, "out-vars");
    std::vector<std::string> on = in_vars;
    for (const auto& n : out_vars)
        if (std::find(on.begin(), on.end(), n) == on.end()) on.push_back(n);
    on_set_ = set_of(on, "in-vars/out-vars");
}

LocalTable::LocalTable(Table& global, const std::vector<std::string>& names)
    : global_(&global), buffer_(nullptr, &free_buffer) {
    build({&names}, {"variables"});
}

LocalTable::LocalTable(LocalTable&&) noexcept = default;
LocalTable::~LocalTable() = default;

void LocalTable::build(const std::vector<const std::vector<std::string>*>& lists,
                       const std::vector<const char*>& list_names) {
    if (!global_->valid()) throw Error("local table: the global table is not attached");
    if (global_->read_only())
        throw Error("local table: table " + global_->name() +
                    " is watched read-only; a task's local table needs its owner's attach()");
    hdr_ = global_->hdr_;
    gdata_ = global_->data_;
    gundo_ = global_->undo_;
    gundo_list_ = global_->undo_list_;
    by_global_.assign(global_->size(), -1);
    std::size_t offset = 0;
    for (std::size_t l = 0; l < lists.size(); ++l) {
        for (const std::string& name : *lists[l]) {
            const auto ix = global_->find(name);
            if (!ix)
                throw Error("table " + global_->name() + " (" +
                            std::string(global_->source_file()) + ") has no variable " + name +
                            " (in the " + list_names[l] + " list)");
            if (by_global_[*ix] >= 0) continue;  // in several lists: stored once
            const VarInfo info = global_->var(*ix);
            by_global_[*ix] = static_cast<std::int32_t>(vars_.size());
            vars_.push_back(LocalVar{static_cast<std::uint32_t>(*ix),
                                     static_cast<std::uint32_t>(info.bytes()), offset,
                                     global_->desc_[*ix].data_offset});
            offset = ipc::align_up(offset + info.bytes(), detail::kVarAlign);
        }
    }
    buffer_.reset(alloc_buffer(offset));
    slots_.assign(offset / detail::kVarAlign + 1, Slot{0, 0, 0});
    for (const LocalVar& v : vars_)
        slots_[v.local_offset / detail::kVarAlign] = Slot{v.bytes, v.global_index, v.global_offset};
    // Start from the table's current values, so a translated pointer never
    // shows garbage even before the first copy.
    const Status s = global_->acquire();
    if (!transferred(s))
        throw Error("local table on " + global_->name() + ": cannot lock the table (" +
                    to_string(s) + ")");
    for (const LocalVar& v : vars_)
        std::memcpy(buffer_.get() + v.local_offset,
                    global_->data_ + global_->desc_[v.global_index].data_offset, v.bytes);
    if (global_->release(s) == Status::lock_lost)
        throw Error("local table on " + global_->name() +
                    ": the table lock was reset while its values were read");
}

VarSet LocalTable::set_of(const std::vector<std::string>& names, const char* list_name) const {
    VarSet set;
    for (const std::string& name : names) {
        const auto ix = global_->find(name);
        const std::int32_t local = ix ? by_global_[*ix] : -1;
        if (local < 0)
            throw Error("local table on " + global_->name() + ": variable " + name + " (" +
                        list_name + ") is not in this local table");
        if (std::find(set.indices_.begin(), set.indices_.end(), *ix) != set.indices_.end())
            continue;  // listed twice: copy once
        const LocalVar& v = vars_[static_cast<std::size_t>(local)];
        set.entries_.push_back(
            VarSet::Entry{v.global_index, v.bytes, v.global_offset, v.local_offset});
        set.indices_.push_back(v.global_index);
        set.small_ = set.small_ && detail::is_small(v.bytes);
    }
    return set;
}

VarSet LocalTable::make_set(const std::vector<std::string>& names) const {
    return set_of(names, "set");
}

VarSet LocalTable::make_set_ix(const std::vector<std::size_t>& indices) const {
    std::vector<std::string> names;
    for (std::size_t ix : indices) {
        if (ix >= global_->size())
            throw Error("table " + global_->name() + " has no variable with index " +
                        std::to_string(ix));
        names.emplace_back(global_->var(ix).name());
    }
    return set_of(names, "set");
}

bool LocalTable::contains(std::string_view name) const noexcept {
    const auto ix = global_->find(name);
    return ix && by_global_[*ix] >= 0;
}

void* LocalTable::translate_raw(std::string_view name, std::optional<Type> type, std::size_t size) {
    const auto ix = global_->find(name);
    if (!ix)
        throw Error("translate: table " + global_->name() + " has no variable " + std::string(name));
    const std::int32_t local = by_global_[*ix];
    if (local < 0)
        throw Error("translate: variable " + std::string(name) +
                    " is not one of this task's variables (not in its local table)");
    const VarInfo info = global_->var(*ix);
    const bool is_byte = !type && size == 1;  // std::byte / untyped access to a struct
    bool ok;
    if (info.type() == Type::struct_)
        ok = (!type && (size == info.elem_size() || is_byte));
    else
        ok = type && *type == info.type();
    if (!ok)
        throw Error("translate: variable " + std::string(name) + " is " +
                    type_spelling(info.type(), info.elem_size()) + ", not " +
                    (type ? std::string(type_name(*type))
                          : "a " + std::to_string(size) + "-byte struct"));
    return buffer_.get() + vars_[static_cast<std::size_t>(local)].local_offset;
}

void* LocalTable::translate_any(std::string_view name) {
    const auto ix = global_->find(name);
    if (!ix || by_global_[*ix] < 0)
        throw Error("translate: variable " + std::string(name) + " is not in this local table");
    return buffer_.get() + vars_[static_cast<std::size_t>(by_global_[*ix])].local_offset;
}

// Inlined into read/write: with the lock they are the whole cycle path.
[[gnu::always_inline]] inline const LocalTable::Slot* LocalTable::slot_at(
    const void* p) const noexcept {
    static_assert(sizeof(Slot) == detail::kVarAlign, "the slot of offset off is at byte off");
    // Compared as integers: a pointer outside the buffer is not an error here.
    const std::uintptr_t off =
        reinterpret_cast<std::uintptr_t>(p) - reinterpret_cast<std::uintptr_t>(buffer_.get());
    // Below the buffer, off wraps to a huge value and fails the bound.
    const std::uintptr_t end = slots_.size() * sizeof(Slot);
    if (off % detail::kVarAlign != 0 || off >= end) return nullptr;
    const auto* slot = reinterpret_cast<const Slot*>(
        reinterpret_cast<const std::byte*>(slots_.data()) + off);
    return slot->bytes != 0 ? slot : nullptr;
}

std::optional<std::size_t> LocalTable::index_of(const void* local) const noexcept {
    if (const Slot* v = slot_at(local)) return v->global_index;
    return std::nullopt;
}

// The uncontended transfer of one variable of 8 to 64 bytes, inlined into
// read/write/read_ix/write_ix: the lock's CAS, the copy (a write inside its
// undo record), the release store, and no call. A function that makes calls
// saves callee-saved registers on entry, and the locked CAS then waits for
// those stores to drain; this path needs none. Anything else (this thread's
// owner word not cached yet, the lock not free, a variable outside 8..64
// bytes) goes to single_slow(), a tail call.
[[gnu::always_inline]] inline Status LocalTable::single(std::size_t local_offset,
                                                        bool to_global) noexcept {
    const Slot& v = slots_[local_offset / detail::kVarAlign];
    const std::uint64_t me = ipc::detail::t_self_owner_id;
    const std::size_t n = v.bytes;
    detail::TableHeader& h = *hdr_;
    if (me == 0 || !detail::is_small(n) || !ipc::lock_if_free(h.lock, me)) [[unlikely]]
        return single_slow(local_offset, to_global);
    std::byte* const gvar = gdata_ + v.global_offset;
    std::byte* const lvar = buffer_.get() + local_offset;
    if (to_global) {
        detail::copy_small(gundo_ + v.global_offset, gvar, n);
        gundo_list_[0] = v.global_index;
        detail::undo_mark(h, 1, me);
        detail::copy_small(gvar, lvar, n);
        detail::undo_clear(h);
    } else {
        detail::copy_small(lvar, gvar, n);
    }
    return ipc::unlock(h.lock, me) ? Status::ok : Status::lock_lost;
}

// Every other single-variable transfer: the full acquisition (spin, recover a
// dead holder and roll its write back, time out), any size.
[[gnu::noinline]] Status LocalTable::single_slow(std::size_t local_offset, bool to_global) noexcept {
    const Slot& v = slots_[local_offset / detail::kVarAlign];
    Table& g = *global_;
    const Status s = g.acquire();
    if (!transferred(s)) return s;
    std::byte* const gvar = gdata_ + v.global_offset;
    std::byte* const lvar = buffer_.get() + local_offset;
    if (to_global) {
        g.save_undo(&v.global_index, 1);
        detail::copy_var(gvar, lvar, v.bytes);
        g.clear_undo();
    } else {
        detail::copy_var(lvar, gvar, v.bytes);
    }
    return g.release(s);
}

Status LocalTable::read(const void* local) noexcept {
    if (!slot_at(local)) return Status::bad_argument;
    return single(static_cast<const std::byte*>(local) - buffer_.get(), false);
}

Status LocalTable::write(const void* local) noexcept {
    if (!slot_at(local)) return Status::bad_argument;
    return single(static_cast<const std::byte*>(local) - buffer_.get(), true);
}

Status LocalTable::read_ix(std::size_t index) noexcept {
    if (index >= by_global_.size() || by_global_[index] < 0) return Status::bad_argument;
    return single(vars_[static_cast<std::size_t>(by_global_[index])].local_offset, false);
}

Status LocalTable::write_ix(std::size_t index) noexcept {
    if (index >= by_global_.size() || by_global_[index] < 0) return Status::bad_argument;
    return single(vars_[static_cast<std::size_t>(by_global_[index])].local_offset, true);
}

// The multi-variable transfers: like single(), the uncontended copy of a set
// whose variables are all 8 to 64 bytes has no call in it; anything else goes
// to the _slow() variant.
Status LocalTable::copy_from_global(const VarSet& set) noexcept {
    const VarSet::Entry* const first = set.entries_.data();
    const VarSet::Entry* const last = first + set.entries_.size();
    if (first == last) return Status::ok;
    const std::uint64_t me = ipc::detail::t_self_owner_id;
    detail::TableHeader& h = *hdr_;
    if (me == 0 || !set.small_ || !ipc::lock_if_free(h.lock, me)) [[unlikely]]
        return copy_from_global_slow(set);
    std::byte* const local = buffer_.get();
    const std::byte* const data = gdata_;
    for (const VarSet::Entry* e = first; e != last; ++e)
        detail::copy_small(local + e->local_offset, data + e->global_offset, e->bytes);
    return ipc::unlock(h.lock, me) ? Status::ok : Status::lock_lost;
}

[[gnu::noinline]] Status LocalTable::copy_from_global_slow(const VarSet& set) noexcept {
    Table& g = *global_;
    const Status s = g.acquire();
    if (!transferred(s)) return s;
    std::byte* const local = buffer_.get();
    const std::byte* const data = gdata_;
    for (const VarSet::Entry& e : set.entries_)
        detail::copy_var(local + e.local_offset, data + e.global_offset, e.bytes);
    return g.release(s);
}

Status LocalTable::copy_to_global(const VarSet& set) noexcept {
    const VarSet::Entry* const first = set.entries_.data();
    const VarSet::Entry* const last = first + set.entries_.size();
    if (first == last) return Status::ok;
    const std::uint64_t me = ipc::detail::t_self_owner_id;
    detail::TableHeader& h = *hdr_;
    if (me == 0 || !set.small_ || !ipc::lock_if_free(h.lock, me)) [[unlikely]]
        return copy_to_global_slow(set);
    const std::byte* const local = buffer_.get();
    std::byte* const data = gdata_;
    std::byte* const undo = gundo_;
    // The undo record, from the set's own entries (the offsets and sizes the
    // descriptors hold, copied when the set was made).
    std::uint32_t* list = gundo_list_;
    for (const VarSet::Entry* e = first; e != last; ++e) {
        detail::copy_small(undo + e->global_offset, data + e->global_offset, e->bytes);
        *list++ = e->global_index;
    }
    detail::undo_mark(h, static_cast<std::uint32_t>(last - first), me);
    for (const VarSet::Entry* e = first; e != last; ++e)
        detail::copy_small(data + e->global_offset, local + e->local_offset, e->bytes);
    detail::undo_clear(h);
    return ipc::unlock(h.lock, me) ? Status::ok : Status::lock_lost;
}

[[gnu::noinline]] Status LocalTable::copy_to_global_slow(const VarSet& set) noexcept {
    Table& g = *global_;
    const Status s = g.acquire();
    if (!transferred(s)) return s;
    g.save_undo(set.indices_.data(), set.indices_.size());
    const std::byte* const local = buffer_.get();
    std::byte* const data = gdata_;
    for (const VarSet::Entry& e : set.entries_)
        detail::copy_var(data + e.global_offset, local + e.local_offset, e.bytes);
    g.clear_undo();
    return g.release(s);
}

}  // namespace chimera::svar
