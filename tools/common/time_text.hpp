// tools/common/time_text.hpp — times as every tool shows them: in microseconds
// (one unit for the prompt's `status`, chimtop and their JSON; the column
// headers say "[us]"), and the per-task percentiles of release lateness and
// cycle time (issue 14.11) taken from the status segment's histograms.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <limits>
#include <optional>
#include <string>

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

}  // namespace chimera::tools
