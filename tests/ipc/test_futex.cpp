#include <gtest/gtest.h>

#include "chimera/ipc/clock.hpp"
#include "chimera/ipc/futex.hpp"
#include "sanitizer.hpp"
#include "test_util.hpp"

using namespace chimera::ipc;
using chimera::ipc::test::fork_child;
using chimera::ipc::test::shared_anon;
using chimera::ipc::test::wait_child;

TEST(IpcFutex, WaitTimesOutAndSeesChangedValue) {
    std::atomic<std::uint32_t> w{5};
    const std::int64_t t0 = now_ns();
    EXPECT_EQ(futex_wait(w, 5, 3'000'000), FutexResult::timed_out);
    EXPECT_GE(now_ns() - t0, 3'000'000);
    EXPECT_EQ(futex_wait(w, 6, 3'000'000), FutexResult::value_changed);
    EXPECT_EQ(futex_wait_until(w, 5, now_ns() + 2'000'000), FutexResult::timed_out);
    EXPECT_EQ(futex_wake(w), 0);  // nobody waiting
}

TEST(IpcFutex, WakeAcrossProcesses) {
    CHIMERA_NOT_UNDER_TSAN("a forked waiter");
    struct S {
        std::atomic<std::uint32_t> word{0};
        std::atomic<std::uint32_t> waiting{0};
    };
    auto* s = shared_anon<S>();
    const pid_t child = fork_child([&] {
        s->waiting = 1;
        const std::int64_t deadline = now_ns() + 5'000'000'000;
        while (s->word.load() == 0) {
            if (futex_wait_until(s->word, 0, deadline) == FutexResult::timed_out) return 2;
        }
        return s->word.load() == 9 ? 0 : 3;
    });
    while (s->waiting.load() == 0) futex_wait(s->waiting, 0, 1'000'000);
    std::this_thread::sleep_for(std::chrono::milliseconds(10));  // let it block
    s->word.store(9);
    futex_wake_all(s->word);
    EXPECT_EQ(wait_child(child), 0);
}
