#include "record.hpp"

#include "command_line.hpp"

#include <chimera/cfg.hpp>
#include <chimera/sampler.hpp>

#include <algorithm>
#include <atomic>
#include <charconv>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

namespace chimera::cli {

namespace {

constexpr const char* kUsage = "usage: record VAR[IDX]... DURATION FILE.csv [--rate HZ] [--rtpu RTPU]";

// The shortest text that reads back as the same double.
void append_number(std::string& out, double v) {
    char buf[32];
    const auto [end, ec] = std::to_chars(buf, buf + sizeof buf, v);
    out.append(buf, ec == std::errc{} ? end : buf);
}

std::string join(const std::vector<std::string>& v) {
    std::string s;
    for (const auto& x : v) s += (s.empty() ? "" : " ") + x;
    return s;
}

}  // namespace

bool is_record(std::string_view command) {
    const auto start = command.find_first_not_of(" \t");
    if (start == std::string_view::npos) return false;
    const std::string_view rest = command.substr(start);
    return rest == "record" || rest.rfind("record ", 0) == 0 || rest.rfind("record\t", 0) == 0;
}

double parse_duration(std::string_view text) {
    const std::string t(text);
    char* end = nullptr;
    const double v = std::strtod(t.c_str(), &end);
    const std::string unit(end ? end : "");
    double scale = 0;
    if (unit.empty() || unit == "s") scale = 1;
    else if (unit == "ms") scale = 1e-3;
    else if (unit == "min") scale = 60;
    if (end == t.c_str() || scale == 0 || !(v > 0) || !std::isfinite(v))
        throw std::invalid_argument("record: duration " + t + " is not a positive time (5s, 500ms, 2min, 1.5)");
    return v * scale;
}

namespace {

struct RecordArgs {
    std::vector<std::string> vars, options;  // options: passed on to `sample`
    double seconds = 0;
    std::string file;
};

// Throws std::invalid_argument with the reply's message.
RecordArgs parse_record(std::string_view command) {
    const std::vector<std::string> words = split_words(command);
    RecordArgs a;
    std::vector<std::string> positional;
    for (std::size_t i = 1; i < words.size(); ++i) {
        if ((words[i] == "--rate" || words[i] == "--rtpu") && i + 1 < words.size()) {
            a.options.push_back(words[i]);
            a.options.push_back(words[++i]);
        } else if (words[i].rfind("--", 0) == 0) {
            throw std::invalid_argument("record: unknown option " + words[i] + " (--rate HZ, --rtpu RTPU)");
        } else {
            positional.push_back(words[i]);
        }
    }
    if (positional.size() < 3) throw std::invalid_argument(kUsage);
    a.file = positional.back();
    a.seconds = parse_duration(positional[positional.size() - 2]);
    a.vars.assign(positional.begin(), positional.end() - 2);
    return a;
}

struct Followed {
    std::uint64_t rows = 0, lost = 0;
    std::size_t width = 0;
    std::string failure;  // "" when `want` rows were written
};

// One CSV row per sample: t from the first sample's time-stamp, then the values.
void append_rows(std::string& text, const sampler::ReadCount& c, const std::int64_t* t, const double* v,
                 std::size_t width, std::int64_t first) {
    for (std::size_t k = 0; k < c.samples; ++k) {
        append_number(text, static_cast<double>(t[k] - first) / 1e9);  // correctly rounded: 0.002012614
        for (std::size_t i = 0; i < width; ++i) {
            text += ',';
            append_number(text, v[k * width + i]);
        }
        text += '\n';
    }
}

// Follows the ring for `want` samples into `out` (header first). Stops early
// when the sampler task stops, it gives too few samples in 2 x seconds + 2 s
// (missed releases), or `interrupted` is set (Ctrl-C).
Followed follow_ring(const std::string& ring, const std::string& rmod, std::uint64_t want, double seconds,
                     std::ostream& out, const std::atomic<bool>* interrupted) {
    Followed f;
    sampler::RingReader reader = sampler::RingReader::attach(ring);
    f.width = reader.channels();
    std::string text = "t";
    for (const auto& c : reader.channel_names()) text += "," + c;
    out << text << '\n';
    constexpr std::size_t kChunk = 4096;
    std::vector<std::int64_t> t(kChunk);
    std::vector<std::uint64_t> cycle(kChunk);
    std::vector<double> v(kChunk * f.width);
    std::int64_t first = 0;
    const double patience = 2 * seconds + 2;
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::duration<double>(patience);
    while (f.rows < want) {
        const auto chunk = static_cast<std::size_t>(std::min<std::uint64_t>(kChunk, want - f.rows));
        const sampler::ReadCount c = reader.read(t.data(), cycle.data(), v.data(), chunk);
        if (f.rows == 0 && c.samples > 0) first = t[0];
        f.lost += c.lost;
        text.clear();
        append_rows(text, c, t.data(), v.data(), f.width, first);
        out << text;
        f.rows += c.samples;
        if (interrupted && interrupted->load()) {
            f.failure = "interrupted after " + std::to_string(f.rows) + " of " + std::to_string(want) + " samples";
            break;
        }
        if (f.rows >= want || c.samples > 0) continue;
        if (reader.closed()) {
            f.failure = "the sampler task " + rmod + " stopped";
            break;
        }
        if (std::chrono::steady_clock::now() > deadline) {
            f.failure = "the sampler task " + rmod + " gave " + std::to_string(f.rows) + " of " + std::to_string(want) +
                        " samples in " + cfg::number_text(patience) + " s";
            break;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    return f;
}

}  // namespace

Reply record(const Executor& exec, std::string_view command, const std::atomic<bool>* interrupted) {
    RecordArgs a;
    try {
        a = parse_record(command);
    } catch (const std::exception& e) {
        return Reply::failure("record", e.what());
    }
    const std::string part = a.file + ".part";
    std::ofstream out(part, std::ios::trunc);
    if (!out) return Reply::failure("record", "record: cannot write " + part);

    const Reply started = exec("sample " + join(a.vars) + (a.options.empty() ? "" : " " + join(a.options)));
    if (!started.ok) {
        std::filesystem::remove(part);
        return Reply::failure("record", started.error);
    }
    const std::string rmod = started.data.value("rmod", "");
    const std::string ring = started.data.value("ring", "");
    const double rate = started.data.value("rate", 0.0);
    const auto want = std::max<std::uint64_t>(1, static_cast<std::uint64_t>(std::llround(a.seconds * rate)));
    Followed f;
    try {
        f = follow_ring(ring, rmod, want, a.seconds, out, interrupted);
    } catch (const std::exception& e) {
        f.failure = e.what();
    }
    const Reply killed = exec("kill " + rmod);  // also after a failure: the task is record's own
    out.close();
    if (!out && f.failure.empty()) f.failure = "cannot write " + part;
    // What was taken is kept when the operator interrupts; any other failure leaves no file.
    const bool keep = f.failure.empty() || (interrupted && interrupted->load() && out);
    std::error_code ec;
    if (keep) std::filesystem::rename(part, a.file, ec);
    else std::filesystem::remove(part, ec);
    if (keep && ec) f.failure = "cannot rename " + part + " to " + a.file + ": " + ec.message();
    if (f.failure.empty() && f.lost > 0)
        f.failure = std::to_string(f.lost) + " samples lost (this reader fell behind the ring); " +
                    std::to_string(f.rows) + " written to " + a.file;
    Reply r = f.failure.empty() ? Reply{} : Reply::failure("record", "record: " + f.failure);
    r.command = "record";
    r.rmod = killed.rmod;  // the default RMOD the master fell back to, for an attached prompt
    r.data = {{"file", a.file}, {"samples", f.rows}, {"channels", f.width}, {"rate", rate}, {"lost", f.lost},
              {"ring", ring}};
    if (f.failure.empty())
        r.text = "recorded " + std::to_string(f.rows) + " samples of " + std::to_string(f.width) + " channel(s) at " +
                 cfg::number_text(rate) + " Hz to " + a.file + ", 0 lost";
    return r;
}

}  // namespace chimera::cli
