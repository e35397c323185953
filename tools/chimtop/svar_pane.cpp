#include "svar_pane.hpp"

#include <sys/stat.h>

#include <cstdio>
#include <cstring>
#include <optional>
#include <string_view>

#if CHIMTOP_HAVE_SVAR
#include "chimera/svar.hpp"
#endif

namespace chimtop {

namespace {

[[maybe_unused]] std::vector<std::string> split(const std::string& list) {
    std::vector<std::string> out;
    std::size_t pos = 0;
    while (pos <= list.size()) {
        std::size_t end = list.find(',', pos);
        if (end == std::string::npos) end = list.size();
        std::string name = list.substr(pos, end - pos);
        while (!name.empty() && name.front() == ' ') name.erase(0, 1);
        while (!name.empty() && name.back() == ' ') name.pop_back();
        if (!name.empty()) out.push_back(name);
        pos = end + 1;
    }
    return out;
}

#if CHIMTOP_HAVE_SVAR
using chimera::svar::Table;
using chimera::svar::Type;

ino_t inode_of(const std::string& segment) {
    struct stat st;
    return ::stat(("/dev/shm" + segment).c_str(), &st) == 0 ? st.st_ino : 0;
}

// One attachment per chimtop process, re-made when the name now names another
// segment (the subsystem restarted) or is gone.
Table* table_for(const std::string& segment, std::string& why) {
    static std::optional<Table> table;
    static std::string attached;
    static ino_t attached_inode = 0;
    const ino_t ino = inode_of(segment);
    if (table && (attached != segment || ino != attached_inode)) table.reset();
    if (ino == 0) {
        why = "segment " + segment + " not found";
        return nullptr;
    }
    if (!table) {
        attached_inode = ino;
        try {
            chimera::svar::TableOptions opt;
            opt.attach.prefault = false;
            table = Table::watch(segment, opt);  // read-only, takes no table lock
            attached = segment;
        } catch (const std::exception& e) {
            why = e.what();
            return nullptr;
        }
    }
    return &*table;
}

std::vector<double> values(const chimera::svar::VarInfo& v, const std::vector<unsigned char>& buf) {
    std::vector<double> out;
    for (std::size_t k = 0; k < v.nelem(); ++k) {
        const unsigned char* p = buf.data() + k * v.elem_size();
        switch (v.type()) {
            case Type::byte_: out.push_back(*p); break;
            case Type::char_: out.push_back(static_cast<signed char>(*p)); break;
            case Type::word: { std::uint16_t x; std::memcpy(&x, p, 2); out.push_back(x); break; }
            case Type::short_: { std::int16_t x; std::memcpy(&x, p, 2); out.push_back(x); break; }
            case Type::unsigned_: { std::uint32_t x; std::memcpy(&x, p, 4); out.push_back(x); break; }
            case Type::int_: { std::int32_t x; std::memcpy(&x, p, 4); out.push_back(x); break; }
            case Type::float_: { float x; std::memcpy(&x, p, 4); out.push_back(x); break; }
            case Type::double_: { double x; std::memcpy(&x, p, 8); out.push_back(x); break; }
            case Type::struct_: return {};
        }
    }
    return out;
}

struct VarValue {
    std::string name, type, units;
    std::vector<double> values;
    std::string error;
};

std::vector<VarValue> read_vars(const std::string& segment, const std::vector<std::string>& names,
                                std::string& why) {
    std::vector<VarValue> out;
    Table* t = table_for(segment, why);
    if (!t) return out;
    for (const auto& n : names) {
        VarValue vv;
        vv.name = n;
        const auto ix = t->find(n);
        if (!ix) {
            vv.error = "not in table " + segment;
            out.push_back(vv);
            continue;
        }
        const auto info = t->var(*ix);
        vv.type = chimera::svar::type_spelling(info.type(), info.elem_size());
        if (info.nelem() > 1) vv.type += "[" + std::to_string(info.nelem()) + "]";
        vv.units = std::string(info.units());
        std::vector<unsigned char> buf(info.bytes());
        const auto st = t->read(*ix, buf.data());
        if (!chimera::svar::transferred(st))
            vv.error = chimera::svar::to_string(st);
        else
            vv.values = values(info, buf);
        out.push_back(std::move(vv));
    }
    return out;
}
#endif

}  // namespace

std::vector<std::string> svar_lines(const std::string& segment, const std::string& inputs,
                                    const std::string& outputs) {
    std::vector<std::string> lines;
#if CHIMTOP_HAVE_SVAR
    for (int dir = 0; dir < 2; ++dir) {
        std::string why;
        const auto vars = read_vars(segment, split(dir == 0 ? inputs : outputs), why);
        if (!why.empty()) return {"SVAR table " + segment + ": " + why};
        for (const auto& v : vars) {
            std::string l = std::string(dir == 0 ? "in  " : "out ") + v.name + "  " + v.type + "  ";
            if (!v.error.empty()) {
                l += "(" + v.error + ")";
            } else {
                for (double x : v.values) {
                    char b[32];
                    std::snprintf(b, sizeof b, "%.6g ", x);
                    l += b;
                }
                l += v.units;
            }
            lines.push_back(l);
        }
    }
    if (lines.empty()) lines.push_back("(the task reads and writes no SVAR)");
#else
    (void)segment;
    (void)inputs;
    (void)outputs;
    lines.push_back("SVAR pane: chimtop was built without the svar service");
#endif
    return lines;
}

nlohmann::json svar_values_json(const std::string& segment, const std::string& inputs,
                                const std::string& outputs) {
    nlohmann::json j = nlohmann::json::object();
#if CHIMTOP_HAVE_SVAR
    for (int dir = 0; dir < 2; ++dir) {
        std::string why;
        const auto vars = read_vars(segment, split(dir == 0 ? inputs : outputs), why);
        if (!why.empty()) return {{"error", why}};
        nlohmann::json d = nlohmann::json::object();
        for (const auto& v : vars) {
            if (!v.error.empty()) d[v.name] = {{"error", v.error}};
            else d[v.name] = v.values;
        }
        j[dir == 0 ? "in" : "out"] = d;
    }
#else
    (void)inputs;
    (void)outputs;
    j["error"] = "chimtop was built without the svar service (" + segment + ")";
#endif
    return j;
}

}  // namespace chimtop
