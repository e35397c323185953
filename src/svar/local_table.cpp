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
    var_at_slot_.assign(offset / detail::kVarAlign + 1, -1);
    for (std::size_t i = 0; i < vars_.size(); ++i)
        var_at_slot_[vars_[i].local_offset / detail::kVarAlign] = static_cast<std::int32_t>(i);
    // Start from the table's current values, so a translated pointer never
    // shows garbage even before the first copy.
    const Status s = global_->acquire();
    if (!transferred(s))
        throw Error("local table on " + global_->name() + ": cannot lock the table (" +
                    to_string(s) + ")");
    for (const LocalVar& v : vars_)
        std::memcpy(buffer_.get() + v.local_offset,
                    global_->data_ + global_->desc_[v.global_index].data_offset, v.bytes);
    global_->release(s);
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
[[gnu::always_inline]] inline const LocalTable::LocalVar* LocalTable::local_at(
    const void* p) const noexcept {
    // Compared as integers: a pointer outside the buffer is not an error here.
    const auto addr = reinterpret_cast<std::uintptr_t>(p);
    const auto base = reinterpret_cast<std::uintptr_t>(buffer_.get());
    const std::uintptr_t off = addr - base;  // wraps to a huge value below the buffer
    if (off % detail::kVarAlign != 0) return nullptr;
    const std::uintptr_t slot = off / detail::kVarAlign;
    if (addr < base || slot >= var_at_slot_.size()) return nullptr;
    const std::int32_t i = var_at_slot_[slot];
    return i < 0 ? nullptr : &vars_[static_cast<std::size_t>(i)];
}

std::optional<std::size_t> LocalTable::index_of(const void* local) const noexcept {
    if (const LocalVar* v = local_at(local)) return v->global_index;
    return std::nullopt;
}

[[gnu::always_inline]] inline Status LocalTable::single(const LocalVar* v, bool to_global) noexcept {
    Table& g = *global_;
    const std::uint64_t goff = v->global_offset;
    const Status s = g.acquire();
    if (!transferred(s)) return s;
    if (to_global) {
        g.save_undo(&v->global_index, 1);
        detail::copy_var(g.data_ + goff, buffer_.get() + v->local_offset, v->bytes);
        g.clear_undo();
    } else {
        detail::copy_var(buffer_.get() + v->local_offset, g.data_ + goff, v->bytes);
    }
    return g.release(s);
}

Status LocalTable::read(const void* local) noexcept {
    const LocalVar* v = local_at(local);
    return v ? single(v, false) : Status::bad_argument;
}

Status LocalTable::write(const void* local) noexcept {
    const LocalVar* v = local_at(local);
    return v ? single(v, true) : Status::bad_argument;
}

Status LocalTable::read_ix(std::size_t index) noexcept {
    if (index >= by_global_.size() || by_global_[index] < 0) return Status::bad_argument;
    return single(&vars_[static_cast<std::size_t>(by_global_[index])], false);
}

Status LocalTable::write_ix(std::size_t index) noexcept {
    if (index >= by_global_.size() || by_global_[index] < 0) return Status::bad_argument;
    return single(&vars_[static_cast<std::size_t>(by_global_[index])], true);
}

Status LocalTable::copy_from_global(const VarSet& set) noexcept {
    if (set.entries_.empty()) return Status::ok;
    Table& g = *global_;
    const Status s = g.acquire();
    if (!transferred(s)) return s;
    std::byte* local = buffer_.get();
    const std::byte* data = g.data_;
    for (const VarSet::Entry& e : set.entries_)
        detail::copy_var(local + e.local_offset, data + e.global_offset, e.bytes);
    return g.release(s);
}

Status LocalTable::copy_to_global(const VarSet& set) noexcept {
    if (set.entries_.empty()) return Status::ok;
    Table& g = *global_;
    const Status s = g.acquire();
    if (!transferred(s)) return s;
    g.save_undo(set.indices_.data(), set.indices_.size());
    const std::byte* local = buffer_.get();
    std::byte* data = g.data_;
    for (const VarSet::Entry& e : set.entries_)
        detail::copy_var(data + e.global_offset, local + e.local_offset, e.bytes);
    g.clear_undo();
    return g.release(s);
}

}  // namespace chimera::svar
