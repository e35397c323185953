// fuzz/fuzz_svar.cpp — the .svar reader (thesis §5.5.2) on arbitrary text.
//
// Invariants: only cfg::ParseError escapes, with FILE:LINE; a table the
// reader accepts is one Table::create lays out as it is (names, sizes that
// match their types, INIT/MIN/MAX within the type, INIT at most and MIN/MAX
// exactly NELEM long (nothing is stored per element beyond them), MIN <= MAX,
// the data within kMaxTableDataBytes without overflow, names unique).
#include <cmath>
#include <limits>

#include "chimera/cfg.hpp"
#include "chimera/svar.hpp"
#include "harness.hpp"

using namespace chimera;
using fuzz::require;

namespace {

void check_values(const svar::VarSpec& v, const std::vector<double>& values, const char* what, bool all) {
    require(all ? values.size() == v.nelem : values.size() <= v.nelem,
            v.name + ": " + what + (all ? " does not hold NELEM values" : " holds more than NELEM values"));
    for (double x : values) {
        require(std::isfinite(x), v.name + ": " + what + " value not finite");
        if (v.type == svar::Type::float_)
            require(std::fabs(x) <= std::numeric_limits<float>::max(), v.name + ": " + what + " outside float");
        else if (v.type != svar::Type::double_)
            require(x == std::trunc(x), v.name + ": " + what + " value of an integer type has a fraction");
    }
}

void check_spec(const svar::TableSpec& spec) {
    require(!spec.vars.empty(), "a table without variables was accepted");
    std::size_t total = 0;
    for (std::size_t i = 0; i < spec.vars.size(); ++i) {
        const svar::VarSpec& v = spec.vars[i];
        require(!v.name.empty() && v.name.size() <= svar::kMaxNameLength, "bad name '" + v.name + "' accepted");
        require(spec.find(v.name) == i, v.name + " is not found at its own index (duplicate?)");
        require(v.nelem >= 1 && v.elem_size >= 1, v.name + " has no size");
        require(v.elem_size <= svar::kMaxTableDataBytes && v.nelem <= svar::kMaxTableDataBytes / v.elem_size,
                v.name + ": NELEM x element size overflows or passes the table limit");
        total += v.bytes();
        require(total <= svar::kMaxTableDataBytes, v.name + " takes the table past kMaxTableDataBytes");
        if (v.type == svar::Type::struct_) {
            require(v.init.empty() && !v.has_init && !v.has_range, v.name + ": a struct with values");
            continue;
        }
        require(v.elem_size == svar::type_size(v.type), v.name + ": element size does not match the type");
        require(v.has_init == !v.init.empty(), v.name + ": INIT values without INIT, or none with it");
        check_values(v, v.init, "INIT", false);
        if (v.has_range) {
            check_values(v, v.min, "MIN", true);
            check_values(v, v.max, "MAX", true);
            for (std::size_t k = 0; k < v.nelem; ++k) require(v.min[k] <= v.max[k], v.name + ": MIN above MAX");
        }
    }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const std::string file = "fuzz.svar";
    svar::TableSpec spec;
    if (fuzz::accepted<cfg::ParseError>(file, [&] { spec = svar::parse_svar_string(fuzz::text_of(data, size), file); }))
        check_spec(spec);
    return 0;
}
