// Costs of the muf Linux backends (thesis §6.2.3: 28 µs per MUF reschedule on
// a 25 MHz MC68030): the dispatcher per release and per priority change, the
// DEADLINE/MAXEXEC timer arm and disarm of every cycle, and the release jitter
// of a 1 kHz task next to a bare clock_nanosleep loop measured in the same run
// (compare with `cyclictest -m -p 80 -i 1000 -l 5000 -q -t1`, see
// bench/results/muf.md).
#include <benchmark/benchmark.h>

#include <sched.h>
#include <sys/mman.h>
#include <sys/syscall.h>
#include <sys/sysinfo.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "chimera/ipc/futex.hpp"
#include "chimera/muf.hpp"
#include "rt_internal.hpp"

using namespace chimera::muf;

namespace {

constexpr std::int64_t kMs = 1'000'000;

int rt_cpu() { return get_nprocs() - 1; }

// Threads that only sleep, so the dispatcher has real tids to give priorities to.
class Sleepers {
public:
    explicit Sleepers(int n) {
        for (int i = 0; i < n; ++i)
            threads_.emplace_back([this] {
                {
                    std::lock_guard<std::mutex> lock(mu_);
                    tid_list_.push_back(static_cast<int>(syscall(SYS_gettid)));
                }
                while (!stop_.load()) chimera::ipc::futex_wait(word_, 0, 50 * kMs);
            });
        while (true) {
            std::lock_guard<std::mutex> lock(mu_);
            if (static_cast<int>(tid_list_.size()) == n) break;
        }
    }
    ~Sleepers() {
        stop_.store(true);
        word_.store(1);
        chimera::ipc::futex_wake_all(word_);
        for (auto& t : threads_) t.join();
    }
    int tid(int i) const { return tid_list_[static_cast<std::size_t>(i)]; }

private:
    std::vector<std::thread> threads_;
    std::mutex mu_;
    std::vector<int> tid_list_;
    std::atomic<bool> stop_{false};
    std::atomic<std::uint32_t> word_{0};
};

// An RTPU with `n` attached, dispatched tasks whose threads sleep; no
// dispatcher thread (backend other): the benchmark drives dispatch_once itself.
struct Bench {
    explicit Bench(int n) : sleepers(n), impl(make_options()) {
        impl.dispatcher_running = true;
        for (int h = 0; h < n; ++h) {
            detail::TaskSlot& s = impl.slots[static_cast<std::size_t>(h)];
            s.params.name = "t" + std::to_string(h);
            s.params.period_ns = (h + 1) * kMs;
            s.params.wcet_ns = kMs / 100;
            s.period_ns = s.params.period_ns;
            s.rel_deadline_ns = s.params.period_ns;
            s.tid = sleepers.tid(h);
            s.pacing = detail::Pacing::dispatched;
            s.phase = detail::Phase::job;
            s.job_deadline_ns = clock_ns() + 10'000 * kMs + h * kMs;
            s.job_release_ns = 0;
            s.next_release_ns = infinity / 2;
            s.state = detail::SlotState::attached;
        }
        impl.slot_count_seen = n;
        impl.reassign();
        for (int h = 0; h < n; ++h) impl.slots[static_cast<std::size_t>(h)].phase = detail::Phase::job;
        impl.rank_and_apply(clock_ns());  // settle the priorities
    }
    ~Bench() {
        for (int h = 0; h < impl.slot_count_seen.load(); ++h)
            detail::set_other(impl.slots[static_cast<std::size_t>(h)].tid.load());
    }
    static RtpuOptions make_options() {
        RtpuOptions o;
        o.name = "bench";
        o.cpu = rt_cpu();
        o.backend = Backend::other;
        o.quiet = true;
        return o;
    }
    Sleepers sleepers;
    RtpuScheduler::Impl impl;
};

// One cycle of a task under dynamic ranking, the ranking work its own thread
// does (the calling thread is task 0): its job ends, it is released, and it
// looks at the ranking before its job begins. Its place does not change (its
// deadline stays the earliest), so the ranking holds and no priority moves:
// no system call. (Before issue #14 item 3, the task waited at fifo_high and
// ranked itself down at each release: two priority changes of its own per
// cycle; bench/results/muf.md has both, measured in one sitting.)
void BM_RankAtRelease(benchmark::State& state) {
    const int n = static_cast<int>(state.range(0));
    Bench b(n);
    detail::TaskSlot& s0 = b.impl.slots[0];
    s0.tid = static_cast<int>(syscall(SYS_gettid));
    detail::set_fifo(0, s0.fifo_prio.load());
    const std::int64_t period = s0.period_ns.load(), deadline = s0.rel_deadline_ns.load();
    const std::uint64_t changes0 = b.impl.priority_changes.load();
    for (auto _ : state) {
        const std::int64_t now = clock_ns();
        s0.phase.store(detail::Phase::waiting);
        s0.next_release_ns.store(now);
        s0.job_release_ns.store(now);
        s0.job_deadline_ns.store(now + deadline);
        s0.phase.store(detail::Phase::job);
        s0.next_release_ns.store(now + period);
        b.impl.rank_at_release(now, 0);
    }
    detail::set_other(0);
    state.counters["prio_changes/iter"] = benchmark::Counter(
        static_cast<double>(b.impl.priority_changes.load() - changes0) /
        static_cast<double>(state.iterations()));
    state.SetLabel(std::to_string(n) + " tasks");
}
BENCHMARK(BM_RankAtRelease)->Arg(1)->Arg(4)->Arg(16)->Arg(60);

// A criticality change that moves one task from the bottom of the ranking to
// the top and back: the re-rank plus the sched_setscheduler calls it makes.
void BM_DispatcherPriorityChange(benchmark::State& state) {
    const int n = static_cast<int>(state.range(0));
    Bench b(n);
    detail::TaskSlot& last = b.impl.slots[static_cast<std::size_t>(n - 1)];
    const int base = last.crit.load();
    const std::uint64_t changes0 = b.impl.priority_changes.load();
    bool up = false;
    for (auto _ : state) {
        up = !up;
        last.crit.store(up ? base + 1 : base);
        b.impl.rank_and_apply(clock_ns());
    }
    const double changes = static_cast<double>(b.impl.priority_changes.load() - changes0);
    state.counters["prio_changes/iter"] =
        benchmark::Counter(changes / static_cast<double>(state.iterations()));
    state.counters["ns/change"] = benchmark::Counter(
        changes, benchmark::Counter::kIsRate | benchmark::Counter::kInvert);
    state.SetLabel(std::to_string(n) + " tasks");
}
BENCHMARK(BM_DispatcherPriorityChange)->Arg(2)->Arg(4)->Arg(16)->UseRealTime();

// The bare system call the dispatcher makes per priority change.
void BM_SchedSetschedulerOnly(benchmark::State& state) {
    Sleepers one(1);
    int prio = 10;
    for (auto _ : state) {
        prio = prio == 10 ? 11 : 10;
        benchmark::DoNotOptimize(detail::set_fifo(one.tid(0), prio));
    }
    detail::set_other(one.tid(0));
}
BENCHMARK(BM_SchedSetschedulerOnly);

// Per cycle, in the thread of a task with a WCET: arm the MAXEXEC budget
// (thread CPU clock, relative) at the release. The one timer call of a cycle.
void BM_BudgetTimerArm(benchmark::State& state) {
    RtpuScheduler::Impl impl(Bench::make_options());
    detail::TaskSlot& s = impl.slots[0];
    s.phase = detail::Phase::waiting;
    detail::create_budget_timer(s);
    detail::bind_thread(&impl, &s, 0);
    for (auto _ : state) detail::arm_budget(s, 1000 * kMs);
    detail::arm_budget(s, infinity);
    detail::bind_thread(nullptr, nullptr, -1);
    detail::delete_budget_timer(s);
}
BENCHMARK(BM_BudgetTimerArm);

// Per cycle, in every task thread: the DEADLINE check at the job's end (a
// clock read against the job's deadline; no system call).
void BM_DeadlineCheckAtJobEnd(benchmark::State& state) {
    RtpuScheduler::Impl impl(Bench::make_options());
    detail::TaskSlot& s = impl.slots[0];
    detail::bind_thread(&impl, &s, 0);
    s.job_deadline_ns = clock_ns() + 1000 * kMs * kMs;
    for (auto _ : state) detail::job_ended(s);
    detail::bind_thread(nullptr, nullptr, -1);
}
BENCHMARK(BM_DeadlineCheckAtJobEnd);

// ------------------------------------------------------------------ jitter

struct Latencies {
    std::vector<std::int64_t> ns;
    void report(benchmark::State& state) {
        std::sort(ns.begin(), ns.end());
        if (ns.empty()) return;
        auto at = [&](double q) {
            return static_cast<double>(ns[std::min(ns.size() - 1, static_cast<std::size_t>(q * ns.size()))]) / 1e3;
        };
        state.counters["min_us"] = at(0);
        state.counters["median_us"] = at(0.5);
        state.counters["p99_us"] = at(0.99);
        state.counters["max_us"] = static_cast<double>(ns.back()) / 1e3;
        state.counters["samples"] = static_cast<double>(ns.size());
    }
};

constexpr int kJitterCycles = 5000;
constexpr std::int64_t kJitterPeriod = kMs;  // 1 kHz

// A 1 kHz task under the fifo backend: wake-up latency = the time wait_release
// returns minus the scheduled release (one task: static ranking, the task's own
// futex timeout). bench/muf/lateness.cpp is the longer, cyclictest-like run.
void BM_ReleaseJitterFifo1kHz(benchmark::State& state) {
    for (auto _ : state) {
        RtpuOptions o = Bench::make_options();
        o.backend = Backend::fifo;
        RtpuScheduler sch(o);
        if (!sch.privileged()) {
            state.SkipWithError("SCHED_FIFO refused");
            return;
        }
        RtTaskParams p;
        p.name = "jitter";
        p.period_ns = kJitterPeriod;
        p.wcet_ns = kJitterPeriod / 2;
        p.first_release_ns = clock_ns() + 20 * kMs;
        const TaskHandle h = sch.add_task(p);
        Latencies lat;
        lat.ns.reserve(kJitterCycles);
        std::thread th([&] {
            sch.attach_current_thread(h);
            std::int64_t next = 0;  // the release this wake-up is for
            while (static_cast<int>(lat.ns.size()) < kJitterCycles) {
                if (sch.wait_release(h) != Wake::release) continue;
                const std::int64_t now = clock_ns();
                // Every release is a sample, however late (no modulo): the
                // ones skipped since the last job count with their lateness.
                const std::int64_t due = (now - p.first_release_ns) / kJitterPeriod;
                for (; next <= due && static_cast<int>(lat.ns.size()) < kJitterCycles; ++next)
                    lat.ns.push_back(now - (p.first_release_ns + next * kJitterPeriod));
                sch.cycle_complete(h);
            }
            sch.detach_current_thread(h);
        });
        th.join();
        lat.report(state);
        state.counters["missed"] = static_cast<double>(sch.status(h).missed);
        state.counters["reschedules"] = static_cast<double>(sch.reschedules());
    }
}
BENCHMARK(BM_ReleaseJitterFifo1kHz)->Iterations(1)->Unit(benchmark::kMillisecond)->UseRealTime();

// The same-session baseline: what cyclictest measures, from this process: a
// thread at SCHED_FIFO 80 on the same CPU in clock_nanosleep(TIMER_ABSTIME).
void BM_ReleaseJitterNanosleep1kHz(benchmark::State& state) {
    for (auto _ : state) {
        Latencies lat;
        lat.ns.reserve(kJitterCycles);
        int rc = 0;
        std::thread th([&] {
            detail::pin_to_cpu(rt_cpu());
            rc = detail::set_fifo(0, 80);
            std::int64_t next = clock_ns() + 20 * kMs;
            for (int i = 0; i < kJitterCycles; ++i) {
                const timespec ts{static_cast<time_t>(next / 1'000'000'000), static_cast<long>(next % 1'000'000'000)};
                clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr);
                lat.ns.push_back(clock_ns() - next);
                next += kJitterPeriod;
            }
        });
        th.join();
        if (rc != 0) {
            state.SkipWithError("SCHED_FIFO refused");
            return;
        }
        lat.report(state);
    }
}
BENCHMARK(BM_ReleaseJitterNanosleep1kHz)->Iterations(1)->Unit(benchmark::kMillisecond)->UseRealTime();

}  // namespace

int main(int argc, char** argv) {
    mlockall(MCL_CURRENT | MCL_FUTURE);  // as a real-time process would
    benchmark::Initialize(&argc, argv);
    if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
    benchmark::RunSpecifiedBenchmarks();
    benchmark::Shutdown();
    return 0;
}
