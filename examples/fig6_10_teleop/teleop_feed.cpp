// teleop_feed — an operator for the Figure 6.10 subsystem, in its own process:
// writes joint set-points into the teleop module's feed (a TBUF, thesis §5.6;
// layout in modules/teleop/teleop/feed.hpp) at a fixed rate.
//
//   teleop_feed NAME [--ndof N] [--rate HZ] [--seconds S]
//               [--base q1..qN] [--amp a1..aN] [--period P]
//   teleop_feed NAME --stdin [--ndof N]
//
// Default: a smooth sweep q(t) = base + amp * sin(2 pi t / P), starting at
// `base` (where the simulated PUMA starts), for S seconds at HZ, then it exits
// holding the last set-point (the set-points are absolute, the arm stays
// there). With --stdin every line of N numbers is sent as it arrives: type
// set-points, or pipe them from a joystick reader.
//
// NAME is the teleop module's LOCAL TBUF (segment /chimera.tbuf.NAME). Either
// side may start first.
#include <chimera/ipc/clock.hpp>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <iostream>
#include <numbers>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "teleop/feed.hpp"

namespace {

struct Options {
    std::string name;
    std::size_t ndof = 6;
    double rate = 100, seconds = 4, period = 4;
    std::vector<double> base{0.0, 0.785398, 3.141593, 0.0, 0.785398, 0.0};  // the PUMA's qn
    std::vector<double> amp{0.4, -0.3, -0.3, 0.5, 0.4, 0.6};
    bool from_stdin = false;
};

[[noreturn]] void usage(const char* prog, int code) {
    std::fprintf(code ? stderr : stdout,
                 "usage: %s NAME [--ndof N] [--rate HZ] [--seconds S] [--base q1..qN] [--amp a1..aN] [--period P]\n"
                 "       %s NAME --stdin [--ndof N]\n"
                 "  Writes operator joint set-points (rad) into the teleop feed NAME (/chimera.tbuf.NAME):\n"
                 "  base + amp * sin(2 pi t / P) at HZ for S seconds (defaults: the PUMA's nominal pose,\n"
                 "  100 Hz, 4 s, P = 4 s), or one line of N numbers at a time from stdin.\n",
                 prog, prog);
    std::exit(code);
}

double number(const char* prog, const char* what, const char* text) {
    char* end = nullptr;
    const double v = std::strtod(text, &end);
    if (end == text || *end != '\0' || !std::isfinite(v)) {
        std::fprintf(stderr, "%s: %s takes a number, not '%s'\n", prog, what, text);
        std::exit(2);
    }
    return v;
}

Options parse(int argc, char** argv) {
    Options o;
    bool base_given = false, amp_given = false;
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        auto next = [&](const char* what) -> const char* {
            if (i + 1 >= argc) {
                std::fprintf(stderr, "%s: %s needs a value\n", argv[0], what);
                std::exit(2);
            }
            return argv[++i];
        };
        auto list = [&](std::vector<double>& v, const char* what) {
            v.clear();
            while (i + 1 < argc && std::strncmp(argv[i + 1], "--", 2) != 0) v.push_back(number(argv[0], what, argv[++i]));
        };
        if (a == "--help" || a == "-h") {
            usage(argv[0], 0);
        } else if (a == "--ndof") {
            o.ndof = static_cast<std::size_t>(number(argv[0], "--ndof", next("--ndof")));
        } else if (a == "--rate") {
            o.rate = number(argv[0], "--rate", next("--rate"));
        } else if (a == "--seconds") {
            o.seconds = number(argv[0], "--seconds", next("--seconds"));
        } else if (a == "--period") {
            o.period = number(argv[0], "--period", next("--period"));
        } else if (a == "--base") {
            list(o.base, "--base");
            base_given = true;
        } else if (a == "--amp") {
            list(o.amp, "--amp");
            amp_given = true;
        } else if (a == "--stdin") {
            o.from_stdin = true;
        } else if (a.starts_with("--") || !o.name.empty()) {
            std::fprintf(stderr, "%s: unexpected argument '%s'\n", argv[0], a.c_str());
            usage(argv[0], 2);
        } else {
            o.name = a;
        }
    }
    if (o.name.empty()) usage(argv[0], 2);
    if (o.ndof < 1 || o.ndof > 64) {
        std::fprintf(stderr, "%s: --ndof must be 1..64\n", argv[0]);
        std::exit(2);
    }
    if (!base_given && o.ndof != 6) o.base.assign(o.ndof, 0.0);
    if (!amp_given && o.ndof != 6) o.amp.assign(o.ndof, 0.2);
    if (o.base.size() != o.ndof || o.amp.size() != o.ndof) {
        std::fprintf(stderr, "%s: --base and --amp take %zu values each (--ndof)\n", argv[0], o.ndof);
        std::exit(2);
    }
    if (!(o.rate > 0 && o.rate <= 10000) || !(o.seconds >= 0) || !(o.period > 0)) {
        std::fprintf(stderr, "%s: --rate must be in (0, 10000], --seconds >= 0, --period > 0\n", argv[0]);
        std::exit(2);
    }
    return o;
}

// A write the buffer refused (its shared state word is damaged) stops the feed.
bool written(const chimera::tbuf::Tbuf& feed, std::uint64_t counter) {
    if (counter != chimera::tbuf::kCorrupt) return true;
    std::fprintf(stderr, "teleop_feed: %s\n", feed.fault_message().c_str());
    return false;
}

int sweep(const Options& o, chimera::tbuf::Tbuf& feed) {
    std::vector<double> q(o.ndof);
    const std::int64_t step_ns = static_cast<std::int64_t>(1e9 / o.rate);
    const std::int64_t start = chimera::ipc::now_ns();
    const auto count = static_cast<std::int64_t>(std::floor(o.seconds * o.rate));
    for (std::int64_t k = 0; k <= count; ++k) {
        const std::int64_t at = start + k * step_ns;
        std::this_thread::sleep_for(std::chrono::nanoseconds(at - chimera::ipc::now_ns()));
        const double s = std::sin(2 * std::numbers::pi * (static_cast<double>(k) / o.rate) / o.period);
        for (std::size_t j = 0; j < o.ndof; ++j) q[j] = o.base[j] + o.amp[j] * s;
        if (!written(feed, feed.write(q.data()))) return 1;
    }
    std::printf("teleop_feed: %lld set-points written to %s, last [", static_cast<long long>(count + 1),
                chimera::teleop::feed_segment(o.name).c_str());
    for (std::size_t j = 0; j < o.ndof; ++j) std::printf("%s%.4f", j ? " " : "", q[j]);
    std::printf("] rad\n");
    return 0;
}

int from_stdin(const Options& o, chimera::tbuf::Tbuf& feed) {
    std::vector<double> q(o.ndof);
    std::string line;
    long line_no = 0, sent = 0;
    while (std::getline(std::cin, line)) {
        ++line_no;
        if (line.empty() || line[0] == '#') continue;
        std::istringstream in(line);
        std::size_t got = 0;
        double v;
        while (got < o.ndof && in >> v) q[got++] = v;
        if (got != o.ndof || !(in >> std::ws).eof()) {
            std::fprintf(stderr, "teleop_feed: stdin line %ld: expected %zu numbers (rad), skipped\n", line_no, o.ndof);
            continue;
        }
        if (!written(feed, feed.write(q.data()))) return 1;
        ++sent;
    }
    std::printf("teleop_feed: %ld set-points written to %s\n", sent, chimera::teleop::feed_segment(o.name).c_str());
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    const Options o = parse(argc, argv);
    try {
        chimera::tbuf::Tbuf feed = chimera::teleop::open_feed(o.name, o.ndof);
        const int rc = o.from_stdin ? from_stdin(o, feed) : sweep(o, feed);
        feed.destroy();  // removed only if the teleop module has gone too
        return rc;
    } catch (const std::exception& e) {
        std::fprintf(stderr, "teleop_feed: %s\n", e.what());
        return 1;
    }
}
