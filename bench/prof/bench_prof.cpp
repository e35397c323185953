// Profiling cost per cycle (issue 5, docs/architecture.md §11): TaskProfiler's
// cycle_begin + cycle_end with the perf-page clock, with the
// CLOCK_THREAD_CPUTIME_ID fallback, and nothing (profiling off), measured in
// the same run; the LTTng tracepoint alone; the vDSO clock read the perf-page
// path is built on. Results and commands: bench/results/prof.md.
//
// System calls are counted by the kernel, per thread, with a perf counter on
// the raw_syscalls:sys_enter tracepoint (needs tracefs mounted; the results
// file shows how to mount it in a private mount namespace). Reported as the
// counter `syscalls/cycle` (the counter's own read() is subtracted); absent
// when the tracepoint cannot be opened.
//
// `bench_prof --count-syscalls N [perf|cputime|off]` runs N profiled cycles
// without the benchmark framework, for `strace -c -f`: the system calls it
// makes must not grow with N.
#include <benchmark/benchmark.h>
#include <linux/perf_event.h>
#include <pthread.h>
#include <sched.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <fstream>
#include <string>

#include "chimera/ipc/clock.hpp"
#include "chimera/prof.hpp"
#include "chimera/trace.hpp"

using namespace chimera::prof;

namespace {

std::string subsystem_name(const char* tag) {
    return std::string("profbench_") + tag + "_" + std::to_string(getpid());
}

StatusSegment make_segment(const char* tag) {
    StatusOptions o;
    o.rtpus = 1;
    return StatusSegment::create(subsystem_name(tag), 1, o);
}

TaskIdentity bench_task() {
    TaskIdentity t;
    t.rmod = "bench";
    t.rtpu = 0;
    t.ref_freq = 1000;
    return t;
}

// A per-thread counter of system-call entries (the kernel counts them).
class SyscallCounter {
public:
    SyscallCounter() {
        std::ifstream f("/sys/kernel/tracing/events/raw_syscalls/sys_enter/id");
        if (!f) f.open("/sys/kernel/debug/tracing/events/raw_syscalls/sys_enter/id");
        long id = -1;
        if (!(f >> id)) return;
        perf_event_attr a;
        std::memset(&a, 0, sizeof a);
        a.size = sizeof a;
        a.type = PERF_TYPE_TRACEPOINT;
        a.config = static_cast<std::uint64_t>(id);
        fd_ = static_cast<int>(syscall(SYS_perf_event_open, &a, 0, -1, -1, PERF_FLAG_FD_CLOEXEC));
        if (fd_ >= 0) {
            // What one read() of the counter adds to the count.
            const std::uint64_t a0 = read_raw(), a1 = read_raw();
            per_read_ = a1 - a0;
        }
    }
    ~SyscallCounter() {
        if (fd_ >= 0) close(fd_);
    }
    SyscallCounter(const SyscallCounter&) = delete;
    SyscallCounter& operator=(const SyscallCounter&) = delete;
    bool ok() const { return fd_ >= 0; }
    std::uint64_t read_raw() const {
        std::uint64_t v = 0;
        if (read(fd_, &v, sizeof v) != sizeof v) return 0;
        return v;
    }
    /// System calls between two readings, without the reading itself.
    std::uint64_t since(std::uint64_t start) const { return read_raw() - start - per_read_; }

private:
    int fd_ = -1;
    std::uint64_t per_read_ = 0;
};

void pin_to_last_cpu() {
    const long n = sysconf(_SC_NPROCESSORS_ONLN);
    cpu_set_t set;
    CPU_ZERO(&set);
    CPU_SET(static_cast<int>(n > 0 ? n - 1 : 0), &set);
    pthread_setaffinity_np(pthread_self(), sizeof set, &set);
}

// The measured loop with the syscall/switch counters around it.
template <typename Body>
void run_cycles(benchmark::State& state, const StatusSegment* seg, Body&& body) {
    pin_to_last_cpu();
    SyscallCounter counter;
    const std::uint64_t sys0 = counter.ok() ? counter.read_raw() : 0;
    const std::uint64_t sw0 = seg ? seg->snapshot()[0].switched : 0;
    for (auto _ : state) body();
    const double cycles = static_cast<double>(state.iterations());
    if (counter.ok())
        state.counters["syscalls/cycle"] = static_cast<double>(counter.since(sys0)) / cycles;
    if (seg) {
        const auto s = seg->snapshot()[0];
        state.counters["switched/cycle"] = static_cast<double>(s.switched - sw0) / cycles;
        state.counters["clock_is_perf"] = s.cpu_clock == CpuClock::perf_switch ? 1 : 0;
    }
}

// Profiling off: the cycle boundary does nothing.
void BM_CycleProfilingOff(benchmark::State& state) {
    run_cycles(state, nullptr, [] { benchmark::ClobberMemory(); });
}
BENCHMARK(BM_CycleProfilingOff);

// Profiling on, the default source: perf task-clock page + vDSO clock.
void BM_CycleProfilingPerfPage(benchmark::State& state) {
    auto seg = make_segment("perf");
    TaskProfiler p(seg.claim(bench_task()));
    if (p.clock() != CpuClock::perf_switch) {
        state.SkipWithError("perf_event_open refused: the perf-page clock is not available here");
        return;
    }
    run_cycles(state, &seg, [&] {
        p.cycle_begin();
        p.cycle_end();
    });
}
BENCHMARK(BM_CycleProfilingPerfPage);

// Profiling on, with the per-cycle histogram (the §6.4 execution profile).
void BM_CycleProfilingPerfPageHistogram(benchmark::State& state) {
    auto seg = make_segment("hist");
    TaskProfiler p(seg.claim(bench_task()));
    p.set_histogram(1000);
    run_cycles(state, &seg, [&] {
        p.cycle_begin();
        p.cycle_end();
    });
}
BENCHMARK(BM_CycleProfilingPerfPageHistogram);

// Profiling on, the fallback: CLOCK_THREAD_CPUTIME_ID at both ends.
void BM_CycleProfilingThreadCputime(benchmark::State& state) {
    auto seg = make_segment("cputime");
    TaskProfiler p(seg.claim(bench_task()), /*allow_perf=*/false);
    run_cycles(state, &seg, [&] {
        p.cycle_begin();
        p.cycle_end();
    });
}
BENCHMARK(BM_CycleProfilingThreadCputime);

// What the perf-page path is built on: one CLOCK_MONOTONIC read (vDSO).
void BM_ClockMonotonicVdso(benchmark::State& state) {
    run_cycles(state, nullptr, [] { benchmark::DoNotOptimize(chimera::ipc::now_ns()); });
}
BENCHMARK(BM_ClockMonotonicVdso);

// One tracepoint alone (chimera:cycle_end). With no session it is a load and
// a not-taken branch; run it under `lttng start` for the cost with a session.
void BM_TracepointCycleEnd(benchmark::State& state) {
    if (!chimera::trace::enabled) {
        state.SkipWithError("built without LTTng-ust: the tracepoints compile to nothing");
        return;
    }
    std::uint64_t n = 0;
    run_cycles(state, nullptr, [&] {
        ++n;
        CHIMERA_TRACE_CYCLE_END("bench", 0u, n, 1234ul, 0);
        benchmark::ClobberMemory();
    });
}
BENCHMARK(BM_TracepointCycleEnd);

int count_syscalls_mode(int argc, char** argv) {
    const long n = std::atol(argv[2]);
    const std::string mode = argc > 3 ? argv[3] : "perf";
    auto seg = make_segment("strace");
    TaskProfiler p(seg.claim(bench_task()), mode != "cputime");
    std::fprintf(stderr, "count-syscalls: %ld cycles, clock %s%s\n", n, to_string(p.clock()),
                 mode == "off" ? " (profiling off: empty loop)" : "");
    std::fflush(stderr);
    // Marker lines around the loop, to find it in `strace -f` output
    // (lttng-ust's own threads make system calls of their own).
    std::fputs("count-syscalls: loop begins\n", stderr);
    if (mode == "off") {
        for (long i = 0; i < n; ++i) benchmark::ClobberMemory();
    } else {
        for (long i = 0; i < n; ++i) {
            p.cycle_begin();
            p.cycle_end();
        }
    }
    std::fputs("count-syscalls: loop ended\n", stderr);
    const auto s = seg.snapshot()[0];
    std::fprintf(stderr, "count-syscalls: cycle=%llu switched=%llu\n",
                 static_cast<unsigned long long>(s.cycle), static_cast<unsigned long long>(s.switched));
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    if (argc >= 3 && std::strcmp(argv[1], "--count-syscalls") == 0) return count_syscalls_mode(argc, argv);
    benchmark::Initialize(&argc, argv);
    if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
    benchmark::RunSpecifiedBenchmarks();
    benchmark::Shutdown();
    return 0;
}
