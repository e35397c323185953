// The SPP round trip (thesis §7.4): one call + wait through the executive,
// next to the bare hand-off a Linux programmer would otherwise write, in the
// same run:
//
//   SppCallWait        Spp::call(noop) + Spp::wait(): two commands (CALL,
//                      WAKEUP) through the task's ring; the executive sleeps
//                      between round trips and is woken by the call, the task
//                      sleeps in wait() and is woken by the WAKEUP
//   CondvarHandoff     the same work with a mutex and one condition variable:
//                      the requester sets a flag and notifies, a worker thread
//                      runs noop and notifies back (baseline)
//   AtomicWaitHandoff  the same with two std::atomic<uint32_t> wait/notify
//                      words, i.e. bare futexes (baseline, the floor)
//
// Argument: 0 = threads unpinned; 1 = the executive (worker) pinned to the
// first allowed CPU and the requester to the last, so every hand-off crosses
// CPUs as it would to a real SPP. Times are one round trip, wall clock.
#include <benchmark/benchmark.h>
#include <pthread.h>
#include <sched.h>

#include <atomic>
#include <condition_variable>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <mutex>
#include <thread>

#include "chimera/spp.hpp"

namespace {

namespace spp = chimera::spp;

void noop(spp::Memory&, const spp::Args&) {}

// The baselines call the routine as the executive does: through a pointer the
// compiler cannot see through, with a Memory and an Args.
spp::Routine volatile g_routine = noop;

struct Cpus {
    int first = -1, last = -1;
};

Cpus allowed_cpus() {
    cpu_set_t set;
    CPU_ZERO(&set);
    Cpus c;
    if (sched_getaffinity(0, sizeof set, &set) != 0) return c;
    for (int k = 0; k < CPU_SETSIZE; ++k)
        if (CPU_ISSET(k, &set)) {
            if (c.first < 0) c.first = k;
            c.last = k;
        }
    return c;
}

void pin_self(int cpu) {
    if (cpu < 0) return;
    cpu_set_t set;
    CPU_ZERO(&set);
    CPU_SET(static_cast<unsigned>(cpu), &set);
    if (pthread_setaffinity_np(pthread_self(), sizeof set, &set) != 0) {
        std::perror("pthread_setaffinity_np");
        std::abort();
    }
}

// Pins the calling (requester) thread for one benchmark, then restores it.
class PinnedRequester {
public:
    explicit PinnedRequester(bool pinned) {
        pthread_getaffinity_np(pthread_self(), sizeof saved_, &saved_);
        if (pinned) pin_self(allowed_cpus().last);
    }
    ~PinnedRequester() { pthread_setaffinity_np(pthread_self(), sizeof saved_, &saved_); }

private:
    cpu_set_t saved_{};
};

void SppCallWait(benchmark::State& state) {
    const bool pinned = state.range(0) != 0;
    PinnedRequester requester(pinned);
    spp::Library lib;
    lib.add_routine("noop", noop);
    spp::Config c;
    c.name = "bench";
    c.memsize = 64;
    c.cpu = pinned ? allowed_cpus().first : -1;
    auto proc = spp::Processor::init(c, lib);
    {
        auto s = spp::Spp::init(*proc, 1);
        const spp::Handle fn = s->translate("noop");
        for (auto _ : state) {
            if (s->call(fn) != 0 || s->wait() != 0) {
                state.SkipWithError("call/wait refused");
                break;
            }
        }
    }
    state.SetItemsProcessed(state.iterations());
}

void CondvarHandoff(benchmark::State& state) {
    const bool pinned = state.range(0) != 0;
    PinnedRequester requester(pinned);
    std::mutex m;
    std::condition_variable cv;
    bool request = false, done = false, stop = false;
    std::thread worker([&] {
        if (pinned) pin_self(allowed_cpus().first);
        spp::Memory memory;
        const spp::Args args;
        std::unique_lock<std::mutex> lk(m);
        for (;;) {
            cv.wait(lk, [&] { return request || stop; });
            if (stop) return;
            request = false;
            g_routine(memory, args);
            done = true;
            cv.notify_all();
        }
    });
    for (auto _ : state) {
        std::unique_lock<std::mutex> lk(m);
        request = true;
        cv.notify_all();
        cv.wait(lk, [&] { return done; });
        done = false;
    }
    {
        std::lock_guard<std::mutex> lk(m);
        stop = true;
        cv.notify_all();
    }
    worker.join();
    state.SetItemsProcessed(state.iterations());
}

void AtomicWaitHandoff(benchmark::State& state) {
    const bool pinned = state.range(0) != 0;
    PinnedRequester requester(pinned);
    std::atomic<std::uint32_t> requests{0}, replies{0};
    std::atomic<bool> stop{false};
    std::thread worker([&] {
        if (pinned) pin_self(allowed_cpus().first);
        spp::Memory memory;
        const spp::Args args;
        std::uint32_t seen = 0;
        for (;;) {
            requests.wait(seen);
            seen = requests.load();
            if (stop.load()) return;
            g_routine(memory, args);
            replies.fetch_add(1);
            replies.notify_one();
        }
    });
    std::uint32_t replied = 0;
    for (auto _ : state) {
        requests.fetch_add(1);
        requests.notify_one();
        replies.wait(replied);
        replied = replies.load();
    }
    stop.store(true);
    requests.fetch_add(1);
    requests.notify_one();
    worker.join();
    state.SetItemsProcessed(state.iterations());
}

}  // namespace

BENCHMARK(SppCallWait)->Arg(0)->Arg(1)->UseRealTime();
BENCHMARK(CondvarHandoff)->Arg(0)->Arg(1)->UseRealTime();
BENCHMARK(AtomicWaitHandoff)->Arg(0)->Arg(1)->UseRealTime();

BENCHMARK_MAIN();
