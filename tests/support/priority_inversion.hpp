// priority_inversion.hpp — the classic three-thread priority inversion, on
// one CPU under SCHED_FIFO, for any lock with lock()/unlock(): a low-priority
// thread L holds the lock, a high-priority H waits for it, a medium-priority M
// hogs the CPU. With priority inheritance the kernel boosts L above M, L
// releases, H takes the lock before M is done; without it M runs until it
// gives up (a bound, not an asserted time) and only then do L and H move. A
// test asserts the order of events, never a time:
//   with inheritance    {l_released, h_acquired, m_saw_h_done}
//   without             {m_gave_up, l_released, h_acquired}
// three_threads() returns {} when SCHED_FIFO is not allowed (the caller skips).
#pragma once

#include "chimera/ipc/clock.hpp"

#include <atomic>
#include <pthread.h>
#include <sched.h>
#include <unistd.h>
#include <vector>

namespace chimera::test::inversion {

enum Event : int { l_released = 1, h_acquired, m_gave_up, m_saw_h_done };

struct Scene {
    std::atomic<int> log[8] = {};
    std::atomic<int> n{0};
    std::atomic<bool> l_holds{false}, h_trying{false}, h_done{false};
    void record(Event e) { log[n.fetch_add(1)].store(e); }
    std::vector<int> events() const {
        std::vector<int> v;
        for (int i = 0; i < n.load(); ++i) v.push_back(log[i].load());
        return v;
    }
};

// M's bound: long enough that L could never get the CPU under it without a
// boost, short against RT throttling (950 ms of every second).
constexpr std::int64_t kHogBoundNs = 300'000'000;

template <typename Lock>
struct Run {
    Lock& lock;
    Scene s;
};

template <typename Lock>
void* low(void* p) {
    auto& r = *static_cast<Run<Lock>*>(p);
    r.lock.lock();
    r.s.l_holds.store(true);
    while (!r.s.h_trying.load()) {}  // hold until H is about to wait
    r.s.record(l_released);
    r.lock.unlock();
    return nullptr;
}

template <typename Lock>
void* medium(void* p) {
    auto& r = *static_cast<Run<Lock>*>(p);
    const std::int64_t until = chimera::ipc::now_ns() + kHogBoundNs;
    while (!r.s.h_done.load()) {
        if (chimera::ipc::now_ns() > until) {
            r.s.record(m_gave_up);
            return nullptr;
        }
    }
    r.s.record(m_saw_h_done);
    return nullptr;
}

template <typename Lock>
void* high(void* p) {
    auto& r = *static_cast<Run<Lock>*>(p);
    r.s.h_trying.store(true);
    r.lock.lock();
    r.s.record(h_acquired);
    r.lock.unlock();
    r.s.h_done.store(true);
    return nullptr;
}

inline bool start(pthread_t& t, void* (*fn)(void*), void* arg, int prio, int cpu) {
    pthread_attr_t a;
    pthread_attr_init(&a);
    pthread_attr_setinheritsched(&a, PTHREAD_EXPLICIT_SCHED);
    pthread_attr_setschedpolicy(&a, SCHED_FIFO);
    sched_param sp{};
    sp.sched_priority = prio;
    pthread_attr_setschedparam(&a, &sp);
    cpu_set_t set;
    CPU_ZERO(&set);
    CPU_SET(cpu, &set);
    pthread_attr_setaffinity_np(&a, sizeof set, &set);
    const int rc = pthread_create(&t, &a, fn, arg);
    pthread_attr_destroy(&a);
    return rc == 0;
}

// Runs the scene with `lock` on one CPU; the events in the order they happened.
// Empty when SCHED_FIFO is not allowed here.
template <typename Lock>
std::vector<int> three_threads(Lock& lock) {
    cpu_set_t allowed;
    sched_getaffinity(0, sizeof allowed, &allowed);
    int cpu = 0;
    while (!CPU_ISSET(cpu, &allowed)) ++cpu;
    // The test thread itself runs above the three, on their CPU, so it
    // places each one before any of them can move on.
    sched_param sp{};
    sp.sched_priority = 40;
    cpu_set_t one;
    CPU_ZERO(&one);
    CPU_SET(cpu, &one);
    sched_param old_sp{};
    const int old_policy = sched_getscheduler(0);
    sched_getparam(0, &old_sp);
    cpu_set_t old_set = allowed;
    if (sched_setscheduler(0, SCHED_FIFO, &sp) != 0) return {};
    sched_setaffinity(0, sizeof one, &one);

    Run<Lock> r{lock, {}};
    pthread_t l{}, m{}, h{};
    bool ok = start(l, &low<Lock>, &r, 10, cpu);
    while (ok && !r.s.l_holds.load()) usleep(1000);  // sleeping lets L (below us) run
    ok = ok && start(m, &medium<Lock>, &r, 20, cpu);
    ok = ok && start(h, &high<Lock>, &r, 30, cpu);
    if (ok) {
        pthread_join(h, nullptr);
        pthread_join(m, nullptr);
        pthread_join(l, nullptr);
    }
    sched_setscheduler(0, old_policy, &old_sp);
    sched_setaffinity(0, sizeof old_set, &old_set);
    return r.s.events();
}

}  // namespace chimera::test::inversion
