// Several tasks, each on its own thread, issue calls and transfers into a
// small command buffer (so the ring wraps and fills often) while the others
// do the same: every task's commands must run in its order, exactly once, and
// every transfer must bring back its own bytes.
#include <gtest/gtest.h>

#include <array>
#include <atomic>
#include <cerrno>
#include <string>
#include <thread>
#include <vector>

#include "chimera/spp.hpp"

namespace spp = chimera::spp;

namespace {

constexpr int kTasks = 6;
constexpr int kLane = 8;  // doubles per task variable

// Written by the executive only; read after the tasks have joined.
std::array<std::int64_t, kTasks> g_last{};
std::array<std::int64_t, kTasks> g_out_of_order{};

// check(task, n): n must follow the task's previous n.
void check(spp::Memory&, const spp::Args& a) {
    const auto t = static_cast<std::size_t>(a.i(0));
    if (a.i(1) != g_last[t] + 1) ++g_out_of_order[t];
    g_last[t] = a.i(1);
}

// bump(lane): every double + 1.
void bump(spp::Memory& m, const spp::Args& a) {
    double* v = m.at<double>(a.h(0));
    for (int k = 0; k < kLane; ++k) v[k] += 1;
}

// Issues a command, making room with wait() while the buffer is full.
template <typename F>
bool issue(spp::Spp& s, F&& command) {
    for (;;) {
        const int rc = command();
        if (rc == 0) return true;
        if (rc != -ENOSPC || s.wait() != 0) return false;
    }
}

}  // namespace

TEST(SppStress, ConcurrentTasksKeepTheirOrderAndTheirBytes) {
    spp::Library lib;
    for (int t = 0; t < kTasks; ++t) lib.add_variable("lane" + std::to_string(t), kLane * sizeof(double));
    lib.add_routine("check", check);
    lib.add_routine("bump", bump);
    spp::Config c;
    c.name = "stress";
    c.memsize = 4096;
    c.queue = 4;
    c.tasks = kTasks;
    auto proc = spp::Processor::init(c, lib);
    g_last.fill(-1);
    g_out_of_order.fill(0);

    constexpr int kCommands = 3000;
    const int priorities[kTasks] = {1, 5, 5, 9, 20, 20};
    std::array<int, kTasks> bad_bytes{}, refused{};
    std::vector<std::thread> threads;
    for (int t = 0; t < kTasks; ++t) {
        threads.emplace_back([&, t] {
            auto s = spp::Spp::init(*proc, priorities[t]);
            const spp::Handle lane = s->translate("lane" + std::to_string(t)), check_fn = s->translate("check"),
                              bump_fn = s->translate("bump");
            double in[kLane], out[kLane];
            for (int n = 0; n < kCommands; ++n) {
                if (!issue(*s, [&] { return s->call(check_fn, spp::Args{}.add(t).add(n)); })) ++refused[t];
                if (n % 7 != 0) continue;
                for (int k = 0; k < kLane; ++k) in[k] = t * 1e6 + n * 10 + k;
                const bool issued = issue(*s, [&] { return s->write(lane, in, sizeof in); }) &&
                                    issue(*s, [&] { return s->call(bump_fn, spp::Args{}.add(lane)); }) &&
                                    issue(*s, [&] { return s->read(lane, out, sizeof out); });
                if (!issued || s->wait() != 0) {
                    ++refused[t];
                    continue;
                }
                for (int k = 0; k < kLane; ++k)
                    if (out[k] != in[k] + 1) ++bad_bytes[t];
            }
            if (s->wait() != 0) ++refused[t];
        });
    }
    for (auto& th : threads) th.join();
    for (int t = 0; t < kTasks; ++t) {
        EXPECT_EQ(refused[t], 0) << "task " << t;
        EXPECT_EQ(g_out_of_order[t], 0) << "task " << t;
        EXPECT_EQ(g_last[t], kCommands - 1) << "task " << t;
        EXPECT_EQ(bad_bytes[t], 0) << "task " << t;
    }
}
