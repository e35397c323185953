// Shared fixtures of the SPP tests: a journal of what the executive ran, gates
// that hold the executive inside a routine until the test opens them, and the
// routines of the test library.
//
// Routines are plain function pointers (spp::Routine), so they reach the test
// through these globals. Ordering is made deterministic by holding the
// executive in a gate while commands are queued, never by sleeping.
#pragma once

#include <gtest/gtest.h>

#include <pthread.h>
#include <sched.h>

#include <array>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "chimera/spp.hpp"

namespace spp_test {

namespace spp = chimera::spp;

// What the executive did, in order. One writer (the executive of the one
// Processor a test runs at a time), readers anywhere; allocation-free so the
// routines that write it can run inside the no-allocation window.
class Journal {
public:
    static constexpr int kCapacity = 1 << 16;

    void add(std::int64_t v) noexcept {
        const int n = n_.load(std::memory_order_relaxed);
        if (n >= kCapacity) {
            overflowed_.store(true);
            return;
        }
        v_[static_cast<std::size_t>(n)] = v;
        n_.store(n + 1, std::memory_order_release);
    }
    std::vector<std::int64_t> entries() const {
        const int n = n_.load(std::memory_order_acquire);
        return {v_.begin(), v_.begin() + n};
    }
    int size() const noexcept { return n_.load(std::memory_order_acquire); }
    bool overflowed() const noexcept { return overflowed_.load(); }
    void reset() noexcept {
        n_.store(0);
        overflowed_.store(false);
    }

private:
    std::array<std::int64_t, kCapacity> v_{};
    std::atomic<int> n_{0};
    std::atomic<bool> overflowed_{false};
};

inline Journal journal;

// Holds the executive inside a routine (pass) until the test opens it.
class Gate {
public:
    void pass() noexcept {
        std::unique_lock<std::mutex> lk(m_);
        entered_ = true;
        cv_.notify_all();
        cv_.wait(lk, [&] { return open_; });
    }
    /// Blocks until the executive is inside pass().
    void await_entered() {
        std::unique_lock<std::mutex> lk(m_);
        cv_.wait(lk, [&] { return entered_; });
    }
    bool entered() {
        std::lock_guard<std::mutex> lk(m_);
        return entered_;
    }
    void open() {
        std::lock_guard<std::mutex> lk(m_);
        open_ = true;
        cv_.notify_all();
    }
    void reset() {
        std::lock_guard<std::mutex> lk(m_);
        entered_ = open_ = false;
    }

private:
    std::mutex m_;
    std::condition_variable cv_;
    bool entered_ = false;
    bool open_ = false;
};

inline std::array<Gate, 4> gates;

// Where and how the executive ran the `where` routine.
struct Placement {
    std::atomic<int> cpu{-1};
    std::atomic<int> allowed_cpus{0};   // CPUs in its affinity mask
    std::atomic<int> policy{-1};
    std::atomic<int> priority{-1};
    std::atomic<int> calls{0};
};
inline Placement placement;

// --- routines of the test library ------------------------------------------

// record(tag): journal the tag.
inline void record(spp::Memory&, const spp::Args& a) { journal.add(a.i(0)); }

// hold(tag, gate): journal the tag, then wait in the gate.
inline void hold(spp::Memory&, const spp::Args& a) {
    journal.add(a.i(0));
    gates[static_cast<std::size_t>(a.i(1))].pass();
}

// bracket(tag, gate): journal +tag, wait in the gate, journal -tag: a command
// preempted by another would show the other's entry between the two.
inline void bracket(spp::Memory&, const spp::Args& a) {
    journal.add(a.i(0));
    gates[static_cast<std::size_t>(a.i(1))].pass();
    journal.add(-a.i(0));
}

// scale(variable, factor): every double of the variable times factor.
inline void scale(spp::Memory& m, const spp::Args& a) {
    double* x = m.at<double>(a.h(0));
    const std::size_t n = m.size_of(a.h(0)) / sizeof(double);
    for (std::size_t k = 0; k < n; ++k) x[k] *= a.d(1);
}

// add_to(variable, index, value): x[index] += value (a result left in SPP memory).
inline void add_to(spp::Memory& m, const spp::Args& a) {
    m.at<double>(a.h(0))[a.i(1)] += a.d(2);
}

// probe_args(...): copies what arrived into the "probe" variable (variable 2
// of make_library, so no argument is spent on it): the count, then each
// argument's bits read as int64.
constexpr spp::Handle kProbe{spp::Handle::Kind::variable, 2};
inline void probe_args(spp::Memory& m, const spp::Args& a) {
    auto* out = m.at<std::int64_t>(kProbe);
    out[0] = a.size();
    for (int k = 0; k < spp::Args::kMaxArgs; ++k) out[1 + k] = a.i(k);
}

inline void throw_runtime_error(spp::Memory&, const spp::Args&) { throw std::runtime_error("routine failed"); }
inline void throw_int(spp::Memory&, const spp::Args&) { throw 42; }

// where(): records the executive thread's CPU, affinity and policy.
inline void where(spp::Memory&, const spp::Args&) {
    placement.cpu.store(sched_getcpu());
    cpu_set_t set;
    CPU_ZERO(&set);
    if (pthread_getaffinity_np(pthread_self(), sizeof set, &set) == 0) placement.allowed_cpus.store(CPU_COUNT(&set));
    int policy = -1;
    sched_param sp{};
    if (pthread_getschedparam(pthread_self(), &policy, &sp) == 0) {
        placement.policy.store(policy);
        placement.priority.store(sp.sched_priority);
    }
    placement.calls.fetch_add(1);
}

// Variable indices are fixed by the order of make_library.
constexpr std::size_t kXDoubles = 8;

inline spp::Library make_library() {
    spp::Library lib;
    lib.add_variable("x", kXDoubles * sizeof(double));            // variable 0
    lib.add_variable("y", 64, 8);                                  // variable 1
    lib.add_variable("probe", (1 + spp::Args::kMaxArgs) * 8, 8);   // variable 2
    lib.add_routine("record", record);
    lib.add_routine("hold", hold);
    lib.add_routine("bracket", bracket);
    lib.add_routine("scale", scale);
    lib.add_routine("add_to", add_to);
    lib.add_routine("probe_args", probe_args);
    lib.add_routine("throw_runtime_error", throw_runtime_error);
    lib.add_routine("throw_int", throw_int);
    lib.add_routine("where", where);
    return lib;
}

inline spp::Config make_config(int queue = 64, int tasks = 8) {
    spp::Config c;
    c.name = "fpa0";
    c.memsize = 4096;
    c.queue = queue;
    c.tasks = tasks;
    c.file = "test.spp";
    c.line = 1;
    return c;
}

// Resets the globals; every test that uses the journal or gates starts here.
inline void reset_fixtures() {
    journal.reset();
    for (Gate& g : gates) g.reset();
}

inline spp::Args tag(std::int64_t t) { return spp::Args{}.add(t); }
inline spp::Args tag_gate(std::int64_t t, int gate) { return spp::Args{}.add(t).add(gate); }

// Polls a state that another thread moves (not a timing assumption: it waits
// as long as it takes, up to the test's own time limit).
inline bool eventually(const std::function<bool()>& pred, std::chrono::seconds limit = std::chrono::seconds(60)) {
    const auto end = std::chrono::steady_clock::now() + limit;
    while (!pred()) {
        if (std::chrono::steady_clock::now() > end) return false;
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    return true;
}

}  // namespace spp_test
