// trackball_sim — a simulated six-axis trackball on a serial line: it opens a
// pseudo-terminal, links LINK to the terminal's device (what an IOD database
// names as the SIO device's PATH) and sends the packets of
// modules/teleop/teleop/trackball.hpp at its own rate, as the real device would
// whether or not anyone reads them.
//
//   trackball_sim LINK [--rate HZ] [--garbage] [--wait-start] PHASE...
//     PHASE:  idle SECONDS                         ENABLE released, axes at rest
//             move SECONDS a0 a1 a2 a3 a4 a5       ENABLE held, axis deflections
//                                                  in counts (full scale +-1000)
//             release SECONDS a0 a1 a2 a3 a4 a5    axes deflected, ENABLE released
//     --rate HZ      packets per second (default 50)
//     --garbage      before every 10th packet, a few bytes of line noise (a
//                    stray sync byte among them) that the reader must skip
//     --wait-start   send idle packets until SIGUSR1, then run the phases (so
//                    a master can start the operator once its tasks are on)
//
// Exits when the phases are done, removing LINK. Stdout: one line "ready LINK"
// once the line is there, then "sent N packets, M dropped" at the end (dropped:
// the reader did not keep up and the line's buffer was full).
#include "teleop/trackball.hpp"

#include <fcntl.h>
#include <signal.h>
#include <termios.h>
#include <unistd.h>

#include <array>
#include <cerrno>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

namespace {

namespace tp = chimera::teleop;
using Clock = std::chrono::steady_clock;

struct Phase {
    double seconds = 0;
    bool enabled = false;
    std::array<std::int16_t, tp::kTrackballAxes> axes{};
};

volatile sig_atomic_t g_started = 0;
extern "C" void on_start(int) { g_started = 1; }

struct Options {
    std::string link;
    double rate = 50;
    bool garbage = false;
    bool wait_start = false;
    std::vector<Phase> phases;
};

[[noreturn]] void usage(const char* prog, const std::string& why) {
    std::fprintf(stderr,
                 "%s: %s\nusage: %s LINK [--rate HZ] [--garbage] [--wait-start] PHASE...\n"
                 "  PHASE: idle SECONDS | move SECONDS a0 a1 a2 a3 a4 a5 | release SECONDS a0 a1 a2 a3 a4 a5\n"
                 "         (axes in counts, full scale +-1000; move holds ENABLE, release does not)\n",
                 prog, why.c_str(), prog);
    std::exit(2);
}

double number(const char* prog, const char* text, double lo, double hi) {
    char* end = nullptr;
    const double v = std::strtod(text, &end);
    if (end == text || *end != '\0' || !(v >= lo && v <= hi))
        usage(prog, std::string("'") + text + "' is not a number from " + std::to_string(lo) + " to " +
                        std::to_string(hi));
    return v;
}

Options parse(int argc, char** argv) {
    Options o;
    if (argc < 2) usage(argv[0], "LINK is missing");
    o.link = argv[1];
    for (int i = 2; i < argc; ++i) {
        const std::string a = argv[i];
        if (a == "--rate" && i + 1 < argc) {
            o.rate = number(argv[0], argv[++i], 1, 1000);
        } else if (a == "--garbage") {
            o.garbage = true;
        } else if (a == "--wait-start") {
            o.wait_start = true;
        } else if (a == "idle" && i + 1 < argc) {
            o.phases.push_back({number(argv[0], argv[++i], 0, 3600), false, {}});
        } else if ((a == "move" || a == "release") && i + 1 + static_cast<int>(tp::kTrackballAxes) < argc) {
            Phase p{number(argv[0], argv[++i], 0, 3600), a == "move", {}};
            for (auto& x : p.axes) x = static_cast<std::int16_t>(number(argv[0], argv[++i], -32768, 32767));
            o.phases.push_back(p);
        } else {
            usage(argv[0], "unexpected '" + a + "'");
        }
    }
    if (o.phases.empty()) usage(argv[0], "no PHASE given");
    return o;
}

// The device end of the line: a pseudo-terminal whose terminal side is raw (no
// echo, no line editing, no CR/LF translation) from the start, so the bytes
// arrive as sent even before the reader opens it and sets it up itself. Keeping
// the terminal side open also keeps the line up while the reader reopens it.
struct Line {
    int master = -1, terminal = -1;
};

Line open_line(const std::string& link) {
    Line l;
    l.master = ::posix_openpt(O_RDWR | O_NOCTTY | O_CLOEXEC);
    if (l.master < 0 || ::grantpt(l.master) != 0 || ::unlockpt(l.master) != 0) {
        std::perror("trackball_sim: posix_openpt");
        std::exit(1);
    }
    char name[128];
    if (::ptsname_r(l.master, name, sizeof name) != 0) {
        std::perror("trackball_sim: ptsname");
        std::exit(1);
    }
    l.terminal = ::open(name, O_RDWR | O_NOCTTY | O_CLOEXEC);
    termios t{};
    if (l.terminal < 0 || ::tcgetattr(l.terminal, &t) != 0) {
        std::perror("trackball_sim: opening the terminal side");
        std::exit(1);
    }
    ::cfmakeraw(&t);
    ::cfsetispeed(&t, B9600);
    ::cfsetospeed(&t, B9600);
    if (::tcsetattr(l.terminal, TCSANOW, &t) != 0) {
        std::perror("trackball_sim: tcsetattr");
        std::exit(1);
    }
    // Never block on a reader that does not keep up: drop the packet instead.
    ::fcntl(l.master, F_SETFL, ::fcntl(l.master, F_GETFL) | O_NONBLOCK);
    // The link appears complete or not at all.
    const std::string tmp = link + ".new";
    ::unlink(tmp.c_str());
    if (::symlink(name, tmp.c_str()) != 0 || ::rename(tmp.c_str(), link.c_str()) != 0) {
        std::fprintf(stderr, "trackball_sim: linking %s to %s: %s\n", link.c_str(), name, std::strerror(errno));
        std::exit(1);
    }
    return l;
}

bool send(int fd, const std::uint8_t* bytes, std::size_t n) {
    const ssize_t w = ::write(fd, bytes, n);
    return w == static_cast<ssize_t>(n);  // a partial write is a packet the reader resyncs past
}

}  // namespace

int main(int argc, char** argv) {
    const Options opt = parse(argc, argv);
    struct sigaction sa {};
    sa.sa_handler = on_start;
    ::sigemptyset(&sa.sa_mask);
    ::sigaction(SIGUSR1, &sa, nullptr);  // before the link exists: a master may signal once it sees it
    const Line line = open_line(opt.link);
    std::printf("ready %s\n", opt.link.c_str());
    std::fflush(stdout);

    const auto period = std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(1.0 / opt.rate));
    const std::uint8_t noise[] = {0x13, tp::kTrackballSync, 0x00, 0x7F, 0xFF};
    std::uint64_t sent = 0, dropped = 0;
    std::uint8_t sequence = 0;
    auto next = Clock::now();
    const auto packet = [&](const Phase& phase) {
        std::this_thread::sleep_until(next);
        next += period;
        tp::TrackballPacket p;
        p.buttons = phase.enabled ? tp::kTrackballEnable : 0;
        p.axes = phase.axes;
        p.sequence = sequence++;
        if (opt.garbage && p.sequence % 10 == 0) send(line.master, noise, sizeof noise);
        const auto bytes = tp::encode(p);
        if (send(line.master, bytes.data(), bytes.size())) {
            ++sent;
        } else {
            ++dropped;
        }
    };
    if (opt.wait_start) {
        while (!g_started) packet(Phase{});
        next = Clock::now();
    }
    for (const Phase& phase : opt.phases) {
        const auto end = next + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(phase.seconds));
        while (next < end) packet(phase);
    }
    // Let the reader drain what is queued before the line goes away.
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    ::unlink(opt.link.c_str());
    std::printf("sent %llu packets, %llu dropped\n", static_cast<unsigned long long>(sent),
                static_cast<unsigned long long>(dropped));
    ::close(line.terminal);
    ::close(line.master);
    return 0;
}
