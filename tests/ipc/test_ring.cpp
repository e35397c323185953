// ipc::Ring and ipc::Doorbell: what a task thread hands to the master.
#include "chimera/ipc/ring.hpp"

#include <gtest/gtest.h>

#include <atomic>
#include <thread>
#include <vector>

using chimera::ipc::Doorbell;
using chimera::ipc::Ring;

TEST(Ring, KeepsOrderAndRefusesWhenFullWithoutWaiting) {
    Ring<int, 4> r;
    for (int i = 0; i < 4; ++i) EXPECT_TRUE(r.push(i));
    EXPECT_FALSE(r.push(99));  // full: refused at once, the queued items untouched
    int v = -1;
    for (int i = 0; i < 4; ++i) {
        ASSERT_TRUE(r.pop(v));
        EXPECT_EQ(v, i);
    }
    EXPECT_FALSE(r.pop(v));
    EXPECT_TRUE(r.push(4));  // the slots are reused after a wrap
    ASSERT_TRUE(r.pop(v));
    EXPECT_EQ(v, 4);
}

// Several producers, one consumer sleeping on the doorbell: every item pushed
// arrives exactly once, each producer's in its order, and no ring is missed.
TEST(Ring, ManyProducersOneSleepingConsumerLoseNothing) {
    constexpr int kProducers = 3, kEach = 20000;
    Ring<std::uint32_t, 64> r;
    Doorbell bell;
    std::atomic<int> refused{0};
    std::vector<std::thread> producers;
    for (int p = 0; p < kProducers; ++p)
        producers.emplace_back([&, p] {
            for (int i = 0; i < kEach; ++i) {
                const std::uint32_t item = static_cast<std::uint32_t>(p) << 24 | static_cast<std::uint32_t>(i);
                while (!r.push(item)) {
                    refused.fetch_add(1);
                    std::this_thread::yield();
                }
                bell.ring();
            }
        });
    std::vector<int> next(kProducers, 0);
    int received = 0;
    while (received < kProducers * kEach) {
        const std::uint32_t seen = bell.read();
        std::uint32_t item = 0;
        bool any = false;
        while (r.pop(item)) {
            const int p = static_cast<int>(item >> 24), i = static_cast<int>(item & 0xffffff);
            ASSERT_LT(p, kProducers);
            ASSERT_EQ(i, next[p]) << "producer " << p;
            ++next[p];
            ++received;
            any = true;
        }
        if (!any) bell.wait(seen);  // would hang here if a ring were lost
    }
    for (auto& t : producers) t.join();
    EXPECT_EQ(received, kProducers * kEach);
}

TEST(Doorbell, AWaitWithADeadlineReturnsFalseWhenNothingRang) {
    Doorbell bell;
    const std::uint32_t seen = bell.read();
    EXPECT_FALSE(bell.wait(seen, 0));  // a deadline already past
    bell.ring();
    EXPECT_TRUE(bell.wait(seen, 0));   // rang since `seen`: no sleep at all
}
