// The .svar file parser (thesis §5.5.2) on the shared configuration reader.
#include <cmath>
#include <limits>
#include <map>
#include <set>
#include <string>

#include "chimera/cfg.hpp"
#include "chimera/svar.hpp"

namespace chimera::svar {
namespace {

struct TypeRow {
    std::string_view name;
    Type type;
    std::size_t size;
    double lo, hi;  // representable range, for INIT/MIN/MAX checks
};

constexpr double kFloatMax = static_cast<double>(std::numeric_limits<float>::max());
constexpr double kDoubleMax = std::numeric_limits<double>::max();

constexpr TypeRow kTypes[] = {
    {"byte", Type::byte_, 1, 0, 255},
    {"char", Type::char_, 1, -128, 127},
    {"word", Type::word, 2, 0, 65535},
    {"short", Type::short_, 2, -32768, 32767},
    {"unsigned", Type::unsigned_, 4, 0, 4294967295.0},
    {"int", Type::int_, 4, -2147483648.0, 2147483647.0},
    {"float", Type::float_, 4, -kFloatMax, kFloatMax},
    {"double", Type::double_, 8, -kDoubleMax, kDoubleMax},
};

bool is_integer(Type t) { return t != Type::float_ && t != Type::double_ && t != Type::struct_; }

const TypeRow* row_of(Type t) {
    for (const auto& r : kTypes)
        if (r.type == t) return &r;
    return nullptr;
}

std::string valid_types() {
    std::string s;
    for (const auto& r : kTypes) s += std::string(r.name) + ", ";
    return s + "struct[N]";
}

// Reads all values of a line as numbers of type `t`, checking range.
std::vector<double> values(cfg::Reader& r, const cfg::Line& line, const VarSpec& v,
                           std::string_view what) {
    std::vector<double> out;
    const TypeRow* row = row_of(v.type);
    for (std::size_t i = 0; i < line.args.size(); ++i) {
        const std::string label = std::string(what) + " value " + std::to_string(i + 1) + " of " + v.name;
        double x;
        if (is_integer(v.type)) {
            x = static_cast<double>(r.to_int(line, i, label));
        } else {
            x = r.to_double(line, i, label);
            if (!std::isfinite(x)) r.fail(line, label + " is not finite");
        }
        if (x < row->lo || x > row->hi)
            r.fail(line, label + " is " + line.args[i] + ", outside the range of " +
                             std::string(row->name));
        out.push_back(x);
    }
    return out;
}

VarSpec parse_var(cfg::Reader& r) {
    VarSpec v;
    const cfg::Line name = r.expect("NAME");
    r.require_args(name, 1);
    v.name = name.args[0];
    v.line = name.number;
    if (v.name.size() > kMaxNameLength)
        r.fail(name, "variable name " + v.name + " has " + std::to_string(v.name.size()) +
                         " characters, at most " + std::to_string(kMaxNameLength) + " are allowed");

    const cfg::Line type = r.expect("TYPE");
    r.require_args(type, 1);
    const std::string& t = type.args[0];
    bool known = false;
    for (const auto& row : kTypes)
        if (t == row.name) {
            v.type = row.type;
            v.elem_size = row.size;
            known = true;
        }
    if (!known) {
        if (t.rfind("struct[", 0) == 0 && t.size() > 8 && t.back() == ']') {
            const auto n = cfg::parse_int(std::string_view(t).substr(7, t.size() - 8));
            if (!n || *n <= 0 || *n > (1 << 30))
                r.fail(type, "struct size must be a positive integer, found " + t);
            v.type = Type::struct_;
            v.elem_size = static_cast<std::size_t>(*n);
        } else {
            r.fail(type, "unknown type " + t + " for " + v.name + " (valid: " + valid_types() + ")");
        }
    }

    v.desc = r.expect("DESC").text;
    v.units = r.expect("UNITS").text;

    const cfg::Line nelem = r.expect("NELEM");
    r.require_args(nelem, 1);
    const std::int64_t n = r.to_int(nelem, 0, "NELEM of " + v.name);
    if (n < 1) r.fail(nelem, "NELEM of " + v.name + " must be at least 1, found " + nelem.args[0]);
    // Checked before anything of that size is allocated (INIT below is NELEM
    // doubles), and without overflow: elem_size ≤ the limit here.
    if (v.elem_size > kMaxTableDataBytes ||
        static_cast<std::uint64_t>(n) > kMaxTableDataBytes / v.elem_size)
        r.fail(nelem, "NELEM " + nelem.args[0] + " of " + v.name + " (" + type_spelling(v.type, v.elem_size) +
                          ") needs more than the " + std::to_string(kMaxTableDataBytes >> 20) +
                          " MiB a table may hold");
    v.nelem = static_cast<std::size_t>(n);

    const bool is_struct = v.type == Type::struct_;
    if (auto init = r.accept("INIT")) {
        if (is_struct) r.fail(*init, "struct variable " + v.name + " cannot have INIT");
        if (init->args.empty()) r.fail(*init, "INIT of " + v.name + " has no values");
        if (init->args.size() > v.nelem)
            r.fail(*init, "INIT of " + v.name + " has " + std::to_string(init->args.size()) +
                              " values, NELEM is " + std::to_string(v.nelem));
        v.init = values(r, *init, v, "INIT");
        v.has_init = true;
    }
    // "All others are set to 0": init_at() says so without storing them (a
    // byte array at the table limit would take 2 GB of doubles to parse).

    if (auto min = r.accept("MIN")) {
        if (is_struct) r.fail(*min, "struct variable " + v.name + " cannot have MIN/MAX");
        if (min->args.size() != v.nelem)
            r.fail(*min, "MIN of " + v.name + " needs all " + std::to_string(v.nelem) +
                             " values, found " + std::to_string(min->args.size()));
        if (!r.next_is("MAX")) {
            const cfg::Line* next = r.peek();
            r.fail(next ? next->number : r.end_line(),
                   "MIN of " + v.name + " must be followed by MAX, found " +
                       (next ? next->keyword : std::string("EOF")));
        }
        const cfg::Line max = r.expect("MAX");
        if (max.args.size() != v.nelem)
            r.fail(max, "MAX of " + v.name + " needs all " + std::to_string(v.nelem) +
                            " values, found " + std::to_string(max.args.size()));
        v.min = values(r, *min, v, "MIN");
        v.max = values(r, max, v, "MAX");
        for (std::size_t i = 0; i < v.nelem; ++i)
            if (v.min[i] > v.max[i])
                r.fail(max, "MAX value " + std::to_string(i + 1) + " of " + v.name + " (" +
                                max.args[i] + ") is below MIN (" + min->args[i] + ")");
        v.has_range = true;
    } else if (const cfg::Line* l = r.peek(); l && l->keyword == "MAX") {
        r.fail(*l, "MAX of " + v.name + " without MIN (both or neither)");
    }
    if (const cfg::Line* l = r.peek()) {
        for (std::string_view k : {"TYPE", "DESC", "UNITS", "NELEM", "INIT", "MIN", "MAX"})
            if (l->keyword == k)
                r.fail(*l, l->keyword + " out of order in " + v.name +
                               ": the order is NAME, TYPE, DESC, UNITS, NELEM, [INIT], [MIN, MAX]");
    }
    return v;
}

TableSpec parse(cfg::Reader r) {
    TableSpec spec;
    spec.file = r.file();
    std::map<std::string, int, std::less<>> seen;
    std::size_t data_bytes = 0;  // each term is at most the limit: the sum cannot wrap
    while (r.peek() != nullptr) {
        VarSpec v = parse_var(r);
        if (auto it = seen.find(v.name); it != seen.end())
            r.fail(v.line, "duplicate variable " + v.name + " (first defined at line " +
                               std::to_string(it->second) + ")");
        data_bytes += v.nelem * v.elem_size;
        if (data_bytes > kMaxTableDataBytes)
            r.fail(v.line, "variable " + v.name + " takes the table's data past the " +
                               std::to_string(kMaxTableDataBytes >> 20) + " MiB a table may hold");
        seen.emplace(v.name, v.line);
        spec.vars.push_back(std::move(v));
    }
    if (spec.vars.empty()) r.fail(r.end_line(), "no variables defined (expected NAME before EOF)");
    r.expect_end();
    return spec;
}

}  // namespace

std::string_view type_name(Type type) noexcept {
    if (type == Type::struct_) return "struct";
    const TypeRow* row = row_of(type);
    return row ? row->name : "unknown";
}

std::size_t type_size(Type type) noexcept {
    const TypeRow* row = row_of(type);
    return row ? row->size : 0;
}

std::pair<double, double> type_range(Type type) noexcept {
    const TypeRow* row = row_of(type);
    if (!row) return {-HUGE_VAL, HUGE_VAL};
    return {row->lo, row->hi};
}

std::string type_spelling(Type type, std::size_t elem_size) {
    if (type == Type::struct_) return "struct[" + std::to_string(elem_size) + "]";
    return std::string(type_name(type));
}

std::optional<std::size_t> TableSpec::find(std::string_view name) const noexcept {
    for (std::size_t i = 0; i < vars.size(); ++i)
        if (vars[i].name == name) return i;
    return std::nullopt;
}

TableSpec parse_svar_file(const std::string& path) { return parse(cfg::Reader::from_file(path)); }

TableSpec parse_svar_string(std::string_view text, const std::string& name) {
    return parse(cfg::Reader::from_string(text, name));
}

}  // namespace chimera::svar
