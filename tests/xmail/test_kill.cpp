// Robustness: senders and receivers of one queue are killed (SIGKILL) at
// random points, again and again, for a few seconds. After every kill the
// queue must be consistent; at the end every message must have been
// delivered exactly once, except one a killed receiver had already copied out
// (which must then be in its in-flight log slot) and one a killed sender may
// or may not have committed.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <map>
#include <random>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "chimera/ipc/clock.hpp"
#include "chimera/msg.hpp"
#include "chimera/shm.hpp"
#include "chimera/xmail.hpp"
#include "common.hpp"
#include "kill_log.hpp"

using namespace chimera;
using namespace kill_test;
using xm::Status;

TEST(Kill, RandomKillsNeverHangLoseOrDuplicate) {
    const std::string sys = test_sys("kill");
    xm::Rtpu host(sys, "host", 0);
    shm::Segment log_seg = shm::Segment::create(host, "host:klog", sizeof(Log));
    auto* log = static_cast<Log*>(log_seg.data());
    msg::Params p;
    p.blknum = 12;
    p.blksize = 16;  // 8..40-byte messages take 1..3 blocks
    p.policy = msg::Policy::hpf;
    msg::Queue q = msg::Queue::create(host, "host:kq", p);

    constexpr int kWorkers = kSenders + kReceivers;
    auto name = [](int w) { return (w < kSenders ? "s" : "r") + std::to_string(w); };
    auto start = [&](int w) {
        const std::string slot = std::to_string(w < kSenders ? w : w - kSenders);
        return spawn_helper({w < kSenders ? "kq-send" : "kq-recv", sys, name(w), std::to_string(w + 1), slot});
    };
    std::vector<pid_t> pids(kWorkers);
    for (int w = 0; w < kWorkers; ++w) pids[w] = start(w);

    std::set<std::uint64_t> maybe_sent;    // a killed sender's in-flight id
    std::set<std::uint64_t> maybe_taken;   // a killed receiver's in-flight slot
    std::mt19937 rng(static_cast<unsigned>(getpid()));
    int kills = 0, sender_kills = 0, receiver_kills = 0;
    // At least 3 s and at least 60 kills: on a loaded machine one kill round
    // (kill, reap, check, respawn) takes longer, so time alone may give few.
    const auto deadline = ipc::now_ns() + 3'000'000'000;
    const auto last_resort = ipc::now_ns() + 30'000'000'000;
    while (ipc::now_ns() < deadline || (kills < 60 && ipc::now_ns() < last_resort)) {
        std::this_thread::sleep_for(std::chrono::microseconds(2000 + rng() % 20000));
        const int w = static_cast<int>(rng() % kWorkers);
        kill(pids[w], SIGKILL);
        int st = 0;
        ASSERT_EQ(waitpid(pids[w], &st, 0), pids[w]);
        if (!(WIFSIGNALED(st) && WTERMSIG(st) == SIGKILL)) {
            ADD_FAILURE() << name(w) << " had already exited with " << st;
        }
        ++kills;
        // Its mailbox still says alive; its owner pid is gone.
        EXPECT_THROW(host.mailbox().peer(name(w)), xm::Error);
        // Record what the dead one may have had in flight.
        if (w < kSenders) {
            ++sender_kills;
            const std::uint64_t a = log->attempt[w].load();
            if (a >= log->sent[w].load()) maybe_sent.insert(make_id(w, a));
        } else {
            ++receiver_kills;
            const int r = w - kSenders;
            // The landing buffer holds what it had copied out and not yet
            // logged (or the last receipt again, which changes nothing).
            if (log->landing[r][0] != 0) maybe_taken.insert(log->landing[r][0]);
            log->landing[r][0] = 0;
        }
        // Never hangs, always consistent (the lock is recovered if it held it).
        const std::string problem = q.check();
        ASSERT_EQ(problem, "") << "after killing " << name(w) << " (kill " << kills << ")";
        pids[w] = start(w);
    }
    log->stop.store(1);
    for (int w = 0; w < kWorkers; ++w) {
        int st = 0;
        waitpid(pids[w], &st, 0);
        EXPECT_TRUE(WIFEXITED(st) && WEXITSTATUS(st) == 0) << name(w) << " status " << st;
    }
    ASSERT_EQ(q.check(), "");
    EXPECT_EQ(log->corrupt.load(), 0u);

    // Everything delivered: receipts plus what is still queued.
    std::map<std::uint64_t, int> delivered;
    for (int r = 0; r < kReceivers; ++r)
        for (std::uint64_t i = 0; i < log->count[r].load(); ++i) ++delivered[log->ids[r][i]];
    std::uint64_t buf[5];
    msg::Info info;
    while (q.receive(buf, sizeof buf, &info, 0) == Status::ok) ++delivered[buf[0]];
    std::uint64_t total = 0;
    for (auto& [id, n] : delivered) {
        EXPECT_EQ(n, 1) << "message " << std::hex << id << " delivered " << std::dec << n << " times";
        const int slot = static_cast<int>((id >> 40) - 1);
        const std::uint64_t seq = id & ((std::uint64_t{1} << 40) - 1);
        ASSERT_TRUE(slot >= 0 && slot < kSenders) << std::hex << id;
        EXPECT_TRUE(seq < log->sent[slot].load() || maybe_sent.count(id)) << "unknown message " << std::hex << id;
        ++total;
    }
    std::uint64_t lost_in_flight = 0;
    for (int s = 0; s < kSenders; ++s) {
        for (std::uint64_t seq = 0; seq < log->sent[s].load(); ++seq) {
            const std::uint64_t id = make_id(s, seq);
            if (delivered.count(id) || maybe_sent.count(id)) continue;
            // Only a receiver killed after copying it out may have it.
            EXPECT_TRUE(maybe_taken.count(id)) << "message " << std::hex << id << " lost";
            ++lost_in_flight;
        }
    }
    EXPECT_LE(lost_in_flight, static_cast<std::uint64_t>(receiver_kills));
    const msg::Stats s = q.stats();
    std::printf("kills %d (senders %d, receivers %d); messages delivered %llu, held by killed "
                "receivers %llu; lock recoveries %u, repairs %u, dead waiters reclaimed %u\n",
                kills, sender_kills, receiver_kills, static_cast<unsigned long long>(total),
                static_cast<unsigned long long>(lost_in_flight), s.lock_recoveries, s.recoveries,
                s.reclaimed_waiters);
    EXPECT_GT(kills, 50);
    EXPECT_GT(total, 1000u);
}
