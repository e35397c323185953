#include "svar_values.hpp"

#include <chimera/cfg.hpp>

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>

namespace chimera::tools {

std::vector<double> numbers_of(const svar::VarInfo& v, const unsigned char* buf) {
    std::vector<double> out;
    for (std::size_t k = 0; k < v.nelem(); ++k) {
        const unsigned char* p = buf + k * v.elem_size();
        switch (v.type()) {
            case svar::Type::byte_: out.push_back(*p); break;
            case svar::Type::char_: out.push_back(static_cast<signed char>(*p)); break;
            case svar::Type::word: { std::uint16_t x; std::memcpy(&x, p, 2); out.push_back(x); break; }
            case svar::Type::short_: { std::int16_t x; std::memcpy(&x, p, 2); out.push_back(x); break; }
            case svar::Type::unsigned_: { std::uint32_t x; std::memcpy(&x, p, 4); out.push_back(x); break; }
            case svar::Type::int_: { std::int32_t x; std::memcpy(&x, p, 4); out.push_back(x); break; }
            case svar::Type::float_: { float x; std::memcpy(&x, p, 4); out.push_back(x); break; }
            case svar::Type::double_: { double x; std::memcpy(&x, p, 8); out.push_back(x); break; }
            case svar::Type::struct_: return {};
        }
    }
    return out;
}

void store_number(const svar::VarInfo& v, unsigned char* buf, std::size_t k, double x) {
    unsigned char* p = buf + k * v.elem_size();
    auto put = [p](auto value) { std::memcpy(p, &value, sizeof value); };
    switch (v.type()) {
        case svar::Type::byte_: put(static_cast<std::uint8_t>(std::llround(x))); break;
        case svar::Type::char_: put(static_cast<std::int8_t>(std::llround(x))); break;
        case svar::Type::word: put(static_cast<std::uint16_t>(std::llround(x))); break;
        case svar::Type::short_: put(static_cast<std::int16_t>(std::llround(x))); break;
        case svar::Type::unsigned_: put(static_cast<std::uint32_t>(std::llround(x))); break;
        case svar::Type::int_: put(static_cast<std::int32_t>(std::llround(x))); break;
        case svar::Type::float_: put(static_cast<float>(x)); break;
        case svar::Type::double_: put(x); break;
        case svar::Type::struct_: break;
    }
}

std::string type_text(const svar::VarInfo& v) {
    std::string t = svar::type_spelling(v.type(), v.elem_size());
    if (v.nelem() > 1) t += "[" + std::to_string(v.nelem()) + "]";
    return t;
}

std::string value_refusal(const svar::VarInfo& v, std::size_t k, double x) {
    if (!std::isfinite(x)) return "is not a finite number";
    const auto [lo, hi] = svar::type_range(v.type());
    if (x < lo || x > hi) return "does not fit type " + type_text(v);
    if (v.has_range() && (x < v.min(k) || x > v.max(k)))
        return "is outside the .svar range [" + cfg::number_text(v.min(k)) + ", " + cfg::number_text(v.max(k)) + "]";
    return {};
}

}  // namespace chimera::tools
