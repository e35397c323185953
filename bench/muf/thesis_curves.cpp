// thesis_curves — the data behind the thesis's Figures 6.4/6.5 and 6.7–6.9, as
// CSV on stdout, for docs/thesis_plots.py to draw.
//
//   thesis_curves servers
//       Figures 6.7–6.9 from the analysis (src/muf/analysis.cpp, eq. 10–26):
//       u, then for each server (rds rss mds mss) the maximum server size for a
//       periodic utilisation u (Figure 6.7), the worst-case schedulable bound
//       u + that size (Figure 6.8), and the bound for a server of size u
//       (Figure 6.9).
//   thesis_curves dataflow TA_MS TB_MS SECONDS [--trace]
//       Figure 6.3's two tasks on real SCHED_FIFO threads on one CPU (MUF):
//       tau_a samples the sensor K sin(alpha t) (K 50, alpha 10 rad/s) at the
//       start of its cycle and publishes x at its end; tau_b reads x at its
//       start and publishes y = x at its end; C = 5 ms each. Four runs:
//         a_first   MUF, the data flow declared (tau_a's output is tau_b's
//                   input: the library gives tau_a the higher user priority,
//                   which breaks ties of equal deadlines, §6.2.4)
//         b_first   MUF, the user priorities the other way round
//         static_a  tau_a of higher criticality than tau_b: a fixed priority
//                   order whatever the deadlines (the thesis's epsilon_a)
//         static_b  the reverse (the thesis's epsilon_b)
//       Prints "case,ta_ms,tb_ms,mean_error" per run: the time average of
//       |y(t) - K sin(alpha t)| after the first 100 ms (Figure 6.5). --trace
//       adds "trace,case,t,y" lines, every change of y (Figure 6.4).
// Exit 2 when SCHED_FIFO is refused (the figures need real-time threads).
#include <sched.h>
#include <sys/sysinfo.h>

#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include "chimera/muf.hpp"

namespace muf = chimera::muf;

namespace {

constexpr std::int64_t kMs = 1'000'000;
constexpr double kAmplitude = 50.0, kAlpha = 10.0;  // the thesis's K and alpha
constexpr std::int64_t kExec = 5 * kMs;             // C_a = C_b

std::int64_t now_ns() {
    timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return static_cast<std::int64_t>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec;
}

void burn_cpu(std::int64_t ns) {
    timespec ts;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
    const std::int64_t end = static_cast<std::int64_t>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec + ns;
    for (;;) {
        clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
        if (static_cast<std::int64_t>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec >= end) return;
    }
}

double sensor(double t) { return kAmplitude * std::sin(kAlpha * t); }

void servers() {
    const muf::Server all[] = {muf::Server::rds, muf::Server::rss, muf::Server::mds, muf::Server::mss};
    std::printf("u");
    for (const char* what : {"size", "bound_vs_up", "bound_vs_us"})
        for (auto s : all) std::printf(",%s_%s", std::string(muf::to_string(s)).c_str(), what);
    std::printf("\n");
    for (int i = 0; i <= 100; ++i) {
        const double u = i / 100.0;
        std::printf("%.2f", u);
        for (auto s : all) std::printf(",%.6f", muf::server_max_size(s, u));
        for (auto s : all) std::printf(",%.6f", u + muf::server_max_size(s, u));
        for (auto s : all) std::printf(",%.6f", muf::server_schedulable_bound(s, u));
        std::printf("\n");
    }
}

// y's changes, written by tau_b only, read after the run.
struct Trace {
    std::vector<std::int64_t> t;
    std::vector<double> y;
    std::size_t n = 0;
};

struct Shared {
    std::int64_t t0 = 0;
    std::atomic<double> x{0.0}, y{0.0};
    Trace trace;
};

void task_thread(muf::RtpuScheduler& sch, muf::TaskHandle h, Shared& sh, bool is_a, std::atomic<bool>& failed) {
    try {
        sch.attach_current_thread(h);
    } catch (const muf::SchedError& e) {
        std::fprintf(stderr, "thesis_curves: %s\n", e.what());
        failed = true;
        return;
    }
    for (;;) {
        const muf::Wake w = sch.wait_release(h);
        if (w == muf::Wake::detached) break;
        if (w != muf::Wake::release) continue;
        if (is_a) {
            const double s = sensor(static_cast<double>(now_ns() - sh.t0) * 1e-9);
            burn_cpu(kExec);
            sh.x.store(s);
        } else {
            const double in = sh.x.load();
            burn_cpu(kExec);
            sh.y.store(in);
            Trace& tr = sh.trace;
            if (tr.n < tr.t.size()) {
                tr.t[tr.n] = now_ns() - sh.t0;
                tr.y[tr.n] = in;
                ++tr.n;
            }
        }
        sch.cycle_complete(h);
    }
    sch.detach_current_thread(h);
}

enum class Order { a_first, b_first, static_a, static_b };
constexpr Order kOrders[] = {Order::a_first, Order::b_first, Order::static_a, Order::static_b};
const char* name_of(Order o) {
    switch (o) {
        case Order::a_first: return "a_first";
        case Order::b_first: return "b_first";
        case Order::static_a: return "static_a";
        case Order::static_b: return "static_b";
    }
    return "?";
}

// One run; the mean error of y against the sensor over [100 ms, seconds).
double run_case(Order order, std::int64_t ta, std::int64_t tb, double seconds, Trace& trace_out) {
    muf::RtpuOptions o;
    o.name = "dataflow";
    o.cpu = get_nprocs() - 1;
    o.policy = muf::Policy::muf;
    o.quiet = true;
    muf::RtpuScheduler sch(o);
    if (!sch.privileged()) {
        std::fprintf(stderr, "thesis_curves: SCHED_FIFO refused: the data-flow figures need real-time threads\n");
        std::exit(2);
    }
    Shared sh;
    const std::int64_t start = now_ns() + 20 * kMs;
    sh.t0 = start;
    const auto max_changes = static_cast<std::size_t>(seconds * 1e9 / static_cast<double>(tb)) + 16;
    sh.trace.t.assign(max_changes, 0);
    sh.trace.y.assign(max_changes, 0.0);
    muf::RtTaskParams a, b;
    a.name = "tau_a", b.name = "tau_b";
    a.period_ns = ta, b.period_ns = tb;
    a.wcet_ns = b.wcet_ns = kExec;
    a.maxexec_check = b.maxexec_check = false;
    a.first_release_ns = b.first_release_ns = start;
    switch (order) {
        case Order::a_first:
            a.outputs = {"x"};
            b.inputs = {"x"};
            break;
        case Order::b_first:
            a.uprio = 1;  // tau_b above tau_a: the data flow ignored the wrong way
            b.uprio = 2;
            break;
        case Order::static_a:
            a.crit = 12;  // criticality outranks the deadline: a fixed order
            b.crit = 11;
            break;
        case Order::static_b:
            a.crit = 11;
            b.crit = 12;
            break;
    }
    const muf::TaskHandle ha = sch.add_task(a), hb = sch.add_task(b);
    std::atomic<bool> failed{false};
    std::thread tha(task_thread, std::ref(sch), ha, std::ref(sh), true, std::ref(failed));
    std::thread thb(task_thread, std::ref(sch), hb, std::ref(sh), false, std::ref(failed));
    std::this_thread::sleep_until(std::chrono::steady_clock::time_point(std::chrono::nanoseconds(start)) +
                                  std::chrono::nanoseconds(static_cast<std::int64_t>(seconds * 1e9)));
    sch.remove_task(ha);
    sch.remove_task(hb);
    tha.join();
    thb.join();
    if (failed) std::exit(1);
    // Integrate |y - s| on a 0.1 ms grid; y holds its last value between changes.
    const Trace& tr = sh.trace;
    double sum = 0, y = 0;
    std::size_t k = 0, samples = 0;
    for (std::int64_t t = 0; t < static_cast<std::int64_t>(seconds * 1e9); t += 100'000) {
        while (k < tr.n && tr.t[k] <= t) y = tr.y[k++];
        if (t < 100 * kMs) continue;
        sum += std::fabs(y - sensor(static_cast<double>(t) * 1e-9));
        ++samples;
    }
    trace_out = sh.trace;
    return samples ? sum / static_cast<double>(samples) : 0;
}

int dataflow(double ta_ms, double tb_ms, double seconds, bool trace) {
    const auto ta = static_cast<std::int64_t>(ta_ms * kMs), tb = static_cast<std::int64_t>(tb_ms * kMs);
    for (Order order : kOrders) {
        Trace tr;
        const double e = run_case(order, ta, tb, seconds, tr);
        const char* name = name_of(order);
        std::printf("%s,%g,%g,%.4f\n", name, ta_ms, tb_ms, e);
        if (trace)
            for (std::size_t i = 0; i < tr.n; ++i)
                std::printf("trace,%s,%.6f,%.4f\n", name, static_cast<double>(tr.t[i]) * 1e-9, tr.y[i]);
        std::fflush(stdout);
    }
    return 0;
}

int usage() {
    std::fprintf(stderr,
                 "usage: thesis_curves servers\n"
                 "       thesis_curves dataflow TA_MS TB_MS SECONDS [--trace]\n");
    return 2;
}

}  // namespace

int main(int argc, char** argv) {
    if (argc >= 2 && std::strcmp(argv[1], "servers") == 0 && argc == 2) {
        servers();
        return 0;
    }
    if (argc >= 5 && std::strcmp(argv[1], "dataflow") == 0) {
        const double ta = std::atof(argv[2]), tb = std::atof(argv[3]), s = std::atof(argv[4]);
        const bool trace = argc == 6 && std::strcmp(argv[5], "--trace") == 0;
        if (!(ta >= 10 && tb >= 10 && s > 0.2 && s <= 60) || (argc == 6 && !trace) || argc > 6) return usage();
        return dataflow(ta, tb, s, trace);
    }
    return usage();
}
