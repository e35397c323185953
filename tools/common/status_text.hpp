// tools/common/status_text.hpp — the status fields as every tool shows them
// (the prompt's `status`, chimtop, their JSON): times in microseconds, one
// unit everywhere (the column headers say "[us]"), and the per-task
// percentiles of release lateness and cycle time (issue 14.11) taken from the
// status segment's histograms.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <limits>
#include <optional>
#include <string>
#include <string_view>

#include <nlohmann/json.hpp>

#include "chimera/prof.hpp"

namespace chimera::tools {

/// The unit every time is shown in, as printed ("us", ASCII for any terminal).
inline constexpr const char* kTimeUnit = "us";

/// A header for a time column: "maxC[us]".
inline std::string time_header(const std::string& field) { return field + "[" + kTimeUnit + "]"; }

/// Seconds (the library's unit) to microseconds.
constexpr double to_us(double seconds) noexcept { return seconds * 1e6; }

/// A time in µs as text: three decimals below 1000 µs (ns resolution), one
/// below 10 s, none above.
inline std::string us_text(double us) {
    char buf[48];
    std::snprintf(buf, sizeof buf, us < 1000 ? "%.3f" : us < 1e7 ? "%.1f" : "%.0f", us);
    return buf;
}

/// The percentiles the status shows, in parts per million (p50, p99) and the
/// highest bucket (max).
enum class Tail { p50, p99, max };

/// A histogram's percentile in µs: nullopt with no sample in the window,
/// +infinity beyond the histogram's range (2^32 ns).
inline std::optional<double> tail_us(const prof::TimeHistogram& h, Tail tail) {
    const std::optional<std::uint64_t> ns = tail == Tail::max   ? h.max_ns()
                                            : tail == Tail::p50 ? h.percentile_ns(500'000)
                                                                : h.percentile_ns(990'000);
    if (!ns) return std::nullopt;
    if (*ns == UINT64_MAX) return std::numeric_limits<double>::infinity();
    return static_cast<double>(*ns) / 1000.0;
}

/// "-" without samples, ">4294967" beyond the range, else us_text().
inline std::string tail_text(const std::optional<double>& us) {
    if (!us) return "-";
    if (std::isinf(*us)) return ">" + us_text(std::ldexp(1.0, static_cast<int>(prof::kTimeMaxBits)) / 1000.0);
    return us_text(*us);
}

/// JSON: null without samples, the string ">4294967.296" beyond the range.
inline nlohmann::json tail_json(const std::optional<double>& us) {
    if (!us) return nullptr;
    if (std::isinf(*us)) return tail_text(us);
    return *us;
}

/// The value of a status field the profile holds, as JSON: counts, Hz and %
/// as they are, times in µs, percentiles by tail_json(); null for a field
/// the profile does not hold (identity fields: the caller has them).
inline nlohmann::json profile_value(const prof::TaskStatus& p, std::string_view f) {
    if (f == "cycle") return p.cycle;
    if (f == "miss") return p.miss;
    if (f == "warn") return p.warn;
    if (f == "mezF") return p.mez_f;
    if (f == "minU") return p.min_u;
    if (f == "maxU") return p.max_u;
    if (f == "avgU") return p.avg_u;
    if (f == "refT") return to_us(p.ref_t);
    if (f == "mezT") return to_us(p.mez_t);
    if (f == "ptime") return to_us(p.ptime);
    if (f == "totC") return to_us(p.tot_c);
    if (f == "tick") return to_us(p.tick);
    if (f == "minC") return to_us(p.min_c);
    if (f == "maxC") return to_us(p.max_c);
    if (f == "avgC") return to_us(p.avg_c);
    if (f.size() == 6 && (f.substr(0, 3) == "cyc" || f.substr(0, 3) == "lat")) {
        const prof::TimeHistogram& h = f[0] == 'c' ? p.cycle_time : p.lateness;
        const std::string_view tail = f.substr(3);
        if (tail == "P50") return tail_json(tail_us(h, Tail::p50));
        if (tail == "P99") return tail_json(tail_us(h, Tail::p99));
        if (tail == "Max") return tail_json(tail_us(h, Tail::max));
    }
    return nullptr;
}

/// A field's value as text: "-" for null or "", times by us_text(), other
/// fractions with two decimals (Hz, %), integers as they are.
inline std::string value_text(const nlohmann::json& v, bool time) {
    if (v.is_null()) return "-";
    if (v.is_string()) return v.get<std::string>().empty() ? "-" : v.get<std::string>();
    if (v.is_number_float()) {
        if (time) return us_text(v.get<double>());
        char buf[48];
        std::snprintf(buf, sizeof buf, "%.2f", v.get<double>());
        return buf;
    }
    return v.dump();
}

}  // namespace chimera::tools
