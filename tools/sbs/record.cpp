#include "record.hpp"

#include "command_line.hpp"

#include <chimera/cfg.hpp>
#include <chimera/sampler.hpp>

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

Reply record(const Executor& exec, std::string_view command) {
    std::vector<std::string> words;
    try {
        words = split_words(command);
    } catch (const std::exception& e) {
        return Reply::failure("record", e.what());
    }
    std::vector<std::string> positional, options;
    for (std::size_t i = 1; i < words.size(); ++i) {
        if ((words[i] == "--rate" || words[i] == "--rtpu") && i + 1 < words.size()) {
            options.push_back(words[i]);
            options.push_back(words[++i]);
        } else if (words[i].rfind("--", 0) == 0) {
            return Reply::failure("record", "record: unknown option " + words[i] + " (--rate HZ, --rtpu RTPU)");
        } else {
            positional.push_back(words[i]);
        }
    }
    if (positional.size() < 3) return Reply::failure("record", kUsage);
    const std::string file = positional.back();
    double seconds = 0;
    try {
        seconds = parse_duration(positional[positional.size() - 2]);
    } catch (const std::exception& e) {
        return Reply::failure("record", e.what());
    }
    const std::vector<std::string> vars(positional.begin(), positional.end() - 2);
    const std::string part = file + ".part";
    std::ofstream out(part, std::ios::trunc);
    if (!out) return Reply::failure("record", "record: cannot write " + part);

    Reply started = exec("sample " + join(vars) + (options.empty() ? "" : " " + join(options)));
    if (!started.ok) {
        std::filesystem::remove(part);
        return Reply::failure("record", started.error);
    }
    const std::string rmod = started.data.value("rmod", "");
    const std::string ring = started.data.value("ring", "");
    const double rate = started.data.value("rate", 0.0);
    const std::uint64_t want = std::max<std::uint64_t>(1, static_cast<std::uint64_t>(std::llround(seconds * rate)));

    std::string failure;
    std::uint64_t rows = 0, lost = 0;
    std::size_t width = 0;
    try {
        sampler::RingReader reader = sampler::RingReader::attach(ring);
        width = reader.channels();
        std::string header = "t";
        for (const auto& c : reader.channel_names()) header += "," + c;
        out << header << '\n';
        constexpr std::size_t kChunk = 4096;
        std::vector<std::int64_t> t(kChunk);
        std::vector<std::uint64_t> cycle(kChunk);
        std::vector<double> v(kChunk * width);
        std::int64_t first = 0;
        // Twice the duration, and 2 s, for a sampler that misses releases.
        const auto deadline = std::chrono::steady_clock::now() + std::chrono::duration<double>(2 * seconds + 2);
        std::string text;
        while (rows < want) {
            const sampler::ReadCount c =
                reader.read(t.data(), cycle.data(), v.data(), static_cast<std::size_t>(std::min<std::uint64_t>(kChunk, want - rows)));
            lost += c.lost;
            text.clear();
            for (std::size_t k = 0; k < c.samples; ++k) {
                if (rows + k == 0) first = t[0];
                append_number(text, static_cast<double>(t[k] - first) / 1e9);  // correctly rounded: 0.002012614
                for (std::size_t i = 0; i < width; ++i) {
                    text += ',';
                    append_number(text, v[k * width + i]);
                }
                text += '\n';
            }
            out << text;
            rows += c.samples;
            if (rows >= want) break;
            if (c.samples == 0) {
                if (reader.closed()) {
                    failure = "the sampler task " + rmod + " stopped";
                    break;
                }
                if (std::chrono::steady_clock::now() > deadline) {
                    failure = "the sampler task " + rmod + " gave " + std::to_string(rows) + " of " +
                              std::to_string(want) + " samples in " + cfg::number_text(2 * seconds + 2) + " s";
                    break;
                }
                std::this_thread::sleep_for(std::chrono::milliseconds(5));
            }
        }
    } catch (const std::exception& e) {
        failure = e.what();
    }
    (void)exec("kill " + rmod);
    out.close();
    if (!out) failure = failure.empty() ? "cannot write " + part : failure;
    if (failure.empty()) {
        std::error_code ec;
        std::filesystem::rename(part, file, ec);
        if (ec) failure = "cannot rename " + part + " to " + file + ": " + ec.message();
    } else {
        std::filesystem::remove(part);
    }
    if (failure.empty() && lost > 0)
        failure = std::to_string(lost) + " samples lost (this reader fell behind the ring); " + std::to_string(rows) +
                  " written to " + file;
    Reply r = failure.empty() ? Reply{} : Reply::failure("record", "record: " + failure);
    r.command = "record";
    r.data = {{"file", file}, {"samples", rows}, {"channels", width}, {"rate", rate}, {"lost", lost}, {"ring", ring}};
    if (failure.empty())
        r.text = "recorded " + std::to_string(rows) + " samples of " + std::to_string(width) + " channel(s) at " +
                 cfg::number_text(rate) + " Hz to " + file + ", 0 lost";
    return r;
}

}  // namespace chimera::cli
