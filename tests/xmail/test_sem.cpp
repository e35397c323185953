// Remote semaphores over a plain memory block (§5.4.2): values, timed P,
// blocking without spinning, waiter priority order, repair after a death.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/mman.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <mutex>
#include <stdexcept>
#include <thread>
#include <vector>

#include "chimera/ipc/clock.hpp"
#include "chimera/ipc/futex.hpp"
#include "chimera/ipc/lock.hpp"
#include "chimera/sem.hpp"
#include "detail.hpp"
#include "sanitizer.hpp"

using namespace chimera;
using sem::Kind;
using sem::Semaphore;
using xm::Status;

namespace {
struct alignas(64) Mem {
    unsigned char bytes[Semaphore::memory_size()];
};
}  // namespace

TEST(Sem, BinaryAndCountingValues) {
    Mem m;
    Semaphore b = Semaphore::over(&m, Kind::binary, 1);
    EXPECT_EQ(b.try_p(), Status::ok);
    EXPECT_EQ(b.try_p(), Status::would_block);
    EXPECT_EQ(b.v(), Status::ok);
    EXPECT_EQ(b.v(), Status::ok);  // binary: stays 1
    EXPECT_EQ(b.value(), 1);
    Mem m2;
    Semaphore c = Semaphore::over(&m2, Kind::counting, 2);
    EXPECT_EQ(c.try_p(), Status::ok);
    EXPECT_EQ(c.try_p(), Status::ok);
    EXPECT_EQ(c.try_p(), Status::would_block);
    for (int i = 0; i < 3; ++i) EXPECT_EQ(c.v(), Status::ok);
    EXPECT_EQ(c.value(), 3);
    Semaphore again = Semaphore::bind(&m2);
    EXPECT_EQ(again.value(), 3);
    EXPECT_EQ(again.kind(), Kind::counting);
}

TEST(Sem, BadInitialValuesAreRefused) {
    Mem m;
    EXPECT_THROW(Semaphore::over(&m, Kind::binary, 2), xm::Error);
    EXPECT_THROW(Semaphore::over(&m, Kind::counting, -1), xm::Error);
    EXPECT_THROW(Semaphore::over(&m, static_cast<Kind>(5), 0), xm::Error);
}

TEST(Sem, TimedPTimesOut) {
    Mem m;
    Semaphore s = Semaphore::over(&m, Kind::binary, 0);
    const auto t0 = ipc::now_ns();
    EXPECT_EQ(s.p(25'000'000), Status::timed_out);
    EXPECT_GE(ipc::now_ns() - t0, 25'000'000);
    EXPECT_EQ(s.waiting(), 0u);
}

TEST(Sem, BlockedPSleepsAndIsWokenByV) {
    Mem m;
    Semaphore s = Semaphore::over(&m, Kind::binary, 0);
    rusage before{}, after{};
    std::thread t([&] {
        getrusage(RUSAGE_THREAD, &before);
        EXPECT_EQ(s.p(-1), Status::ok);
        getrusage(RUSAGE_THREAD, &after);
    });
    while (s.waiting() == 0) std::this_thread::yield();
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    EXPECT_EQ(s.v(), Status::ok);
    t.join();
    // A spinning waiter would have burnt ~200 ms of CPU; a sleeping one almost none.
    const long cpu_us = (after.ru_utime.tv_sec - before.ru_utime.tv_sec) * 1'000'000 +
                        (after.ru_utime.tv_usec - before.ru_utime.tv_usec) +
                        (after.ru_stime.tv_sec - before.ru_stime.tv_sec) * 1'000'000 +
                        (after.ru_stime.tv_usec - before.ru_stime.tv_usec);
    EXPECT_LT(cpu_us, 50'000);
    EXPECT_EQ(s.value(), 0);  // the unit went to the waiter
}

TEST(Sem, WaitersAreServedHighestPriorityFirst) {
    Mem m;
    Semaphore s = Semaphore::over(&m, Kind::counting, 0);
    std::mutex mu;
    std::vector<int> order;
    std::vector<std::thread> ts;
    for (int prio : {2, 7, 4, 7}) {
        ts.emplace_back([&, prio] {
            EXPECT_EQ(s.p(5'000'000'000, prio), Status::ok);
            std::lock_guard lock(mu);
            order.push_back(prio);
        });
        while (s.waiting() < ts.size()) std::this_thread::yield();
    }
    for (int i = 0; i < 4; ++i) {
        EXPECT_EQ(s.v(), Status::ok);
        // Let the woken one record itself before the next V.
        while (true) {
            std::lock_guard lock(mu);
            if (order.size() == static_cast<std::size_t>(i + 1)) break;
        }
    }
    for (auto& t : ts) t.join();
    EXPECT_EQ(order, (std::vector<int>{7, 7, 4, 2}));
}

// A child process blocked in P on `mem` (shared memory), returned once it waits.
pid_t child_waiting_in_p(void* mem, Semaphore& s, std::int32_t priority = 10) {
    const std::uint32_t before = s.waiting();
    const pid_t child = fork();
    if (child == 0) {
        Semaphore c = Semaphore::bind(mem);
        _exit(c.p(-1, priority) == Status::ok ? 0 : 2);
    }
    while (s.waiting() <= before) std::this_thread::yield();
    return child;
}

TEST(Sem, GrantToADeadWaiterIsPassedOn) {
    CHIMERA_NOT_UNDER_TSAN("a forked waiter killed");
    // Shared memory so a child process can wait on it.
    void* mem = mmap(nullptr, Semaphore::memory_size(), PROT_READ | PROT_WRITE,
                     MAP_SHARED | MAP_ANONYMOUS, -1, 0);
    ASSERT_NE(mem, MAP_FAILED);
    Semaphore s = Semaphore::over(mem, Kind::binary, 0);
    const pid_t child = child_waiting_in_p(mem, s);
    // The child dies while waiting; V must not give the unit to it.
    kill(child, SIGKILL);
    waitpid(child, nullptr, 0);
    EXPECT_EQ(s.v(), Status::ok);
    EXPECT_EQ(s.try_p(), Status::ok);
    munmap(mem, Semaphore::memory_size());
}

TEST(Sem, AUnitGrantedToAKilledUnreapedWaiterIsTakenBack) {
    CHIMERA_NOT_UNDER_TSAN("a forked waiter killed");
    // As above, but the child is not reaped: a zombie passes tgkill's "does it
    // exist" test, so V may grant it the unit; the next P must take it back.
    void* mem = mmap(nullptr, Semaphore::memory_size(), PROT_READ | PROT_WRITE,
                     MAP_SHARED | MAP_ANONYMOUS, -1, 0);
    ASSERT_NE(mem, MAP_FAILED);
    Semaphore s = Semaphore::over(mem, Kind::binary, 0);
    const pid_t child = child_waiting_in_p(mem, s);
    kill(child, SIGKILL);
    siginfo_t info{};
    ASSERT_EQ(waitid(P_PID, static_cast<id_t>(child), &info, WEXITED | WNOWAIT), 0);  // a zombie now
    EXPECT_EQ(s.v(), Status::ok);
    EXPECT_EQ(s.p(200'000'000), Status::ok) << "the unit stayed with the dead waiter";
    EXPECT_EQ(s.try_p(), Status::would_block);  // and it was one unit, not two
    waitpid(child, nullptr, 0);
    munmap(mem, Semaphore::memory_size());
}

// A binary semaphore at 0 in shared memory (so children can use it) and a
// thread blocked in P without a time limit: alone, so asleep without a timer.
// The tests below take the unit away from it in some way and check that it
// still gets it.
class LoneWaiter {
public:
    explicit LoneWaiter(std::int32_t priority)
        : mem_(mmap(nullptr, Semaphore::memory_size(), PROT_READ | PROT_WRITE, MAP_SHARED | MAP_ANONYMOUS, -1, 0)),
          s_(mem_ != MAP_FAILED ? Semaphore::over(mem_, Kind::binary, 0)
                                : throw std::runtime_error("mmap of the semaphore failed")) {
        waiter_ = std::thread([this, priority] {
            EXPECT_EQ(s_.p(-1, priority), Status::ok);
            got_it_ = true;
        });
        while (s_.waiting() == 0) std::this_thread::yield();
        std::this_thread::sleep_for(std::chrono::milliseconds(50));  // asleep, alone, untimed
    }
    ~LoneWaiter() { munmap(mem_, Semaphore::memory_size()); }
    LoneWaiter(const LoneWaiter&) = delete;
    LoneWaiter& operator=(const LoneWaiter&) = delete;
    void* memory() const { return mem_; }
    Semaphore& sem() { return s_; }
    // True when the waiter got the unit within 2 s. Either way the thread is
    // joined: `release` is called first to let it go if it did not.
    template <typename Release>
    bool got_it_in_time(Release&& release) {
        const std::int64_t deadline = ipc::now_ns() + 2'000'000'000;
        while (!got_it_ && ipc::now_ns() < deadline) std::this_thread::sleep_for(std::chrono::milliseconds(5));
        const bool in_time = got_it_;
        if (!in_time) release();
        waiter_.join();
        return in_time;
    }

private:
    void* mem_;
    Semaphore s_;
    std::atomic<bool> got_it_{false};
    std::thread waiter_;
};

// As Msg.AMessageLostWithALaterReceiverReachesTheOneThatWaitedAlone: a P
// without a time limit sleeps untimed while alone; the waiter that joins
// kicks it into slices, so a unit granted to the newcomer (stopped, then
// killed) is passed on to it.
TEST(Sem, AUnitLostWithALaterWaiterReachesTheOneThatWaitedAlone) {
    CHIMERA_NOT_UNDER_TSAN("a forked waiter stopped and killed");
    LoneWaiter first(1);
    Semaphore& s = first.sem();
    const pid_t second = child_waiting_in_p(first.memory(), s, 5);
    kill(second, SIGSTOP);
    siginfo_t info{};
    ASSERT_EQ(waitid(P_PID, static_cast<id_t>(second), &info, WSTOPPED | WNOWAIT), 0);
    EXPECT_EQ(s.v(), Status::ok);  // granted to the higher priority: the stopped child
    kill(second, SIGKILL);
    waitpid(second, nullptr, 0);
    const bool in_time = first.got_it_in_time([&] { EXPECT_EQ(s.v(), Status::ok); });
    EXPECT_TRUE(in_time) << "the lone waiter slept on while the unit stayed with the dead one";
    EXPECT_EQ(s.try_p(), Status::would_block);  // one unit, not two
}

// A V caller that dies after handing the unit to the lone waiter and before
// its futex wake (the hand-off is stored under the lock, the wake comes after
// letting it go) must not leave that waiter asleep: it slept without a timer,
// so nothing of its own would look again. The child does what V does up to
// the wake, with the library's own hand-off (waiter_signal), then exits: the
// kernel, finding the hand-off pending in the exiting thread's robust list,
// must wake the waiter.
TEST(Sem, TheLoneWaiterGetsAUnitWhoseGiverDiedBeforeWakingIt) {
    CHIMERA_NOT_UNDER_TSAN("a forked giver");
    LoneWaiter waiter(0);
    auto* h = static_cast<sem::layout::SemHeader*>(waiter.memory());
    const pid_t giver = fork();
    if (giver == 0) {
        if (!ipc::holds(ipc::lock(h->mutex))) _exit(2);
        xm::layout::Waiter* w = xm::detail::waiter_pick(h->waiters, sem::layout::kMaxWaiters);
        if (w == nullptr) _exit(3);
        xm::detail::waiter_signal(*w);  // the unit goes to the waiter, as in Semaphore::v()
        if (!ipc::unlock(h->mutex)) _exit(4);
        _exit(0);  // gone before its wake-up, as if killed there
    }
    int status = 0;
    ASSERT_EQ(waitpid(giver, &status, 0), giver);
    ASSERT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << status;
    const bool in_time = waiter.got_it_in_time([&] {
        for (auto& w : h->waiters) ipc::futex_wake_all(w.word);
    });
    EXPECT_TRUE(in_time) << "the lone waiter slept on with the unit it was given";
    EXPECT_EQ(waiter.sem().try_p(), Status::would_block);  // the one unit, taken by the waiter
}

TEST(Sem, MutualExclusionAcrossProcesses) {
    CHIMERA_NOT_UNDER_TSAN("forked lockers");
    struct Shared {
        alignas(64) unsigned char sem[Semaphore::memory_size()];
        long counter;
        int inside;
        int violations;
    };
    auto* sh = static_cast<Shared*>(mmap(nullptr, sizeof(Shared), PROT_READ | PROT_WRITE,
                                         MAP_SHARED | MAP_ANONYMOUS, -1, 0));
    ASSERT_NE(sh, MAP_FAILED);
    Semaphore::over(sh->sem, Kind::binary, 1);
    constexpr int kProcs = 3, kIters = 3000;
    std::vector<pid_t> kids;
    for (int k = 0; k < kProcs; ++k) {
        const pid_t pid = fork();
        if (pid == 0) {
            Semaphore s = Semaphore::bind(sh->sem);
            for (int i = 0; i < kIters; ++i) {
                if (s.p(-1) != Status::ok) _exit(2);
                if (++sh->inside != 1) ++sh->violations;
                const long c = sh->counter;
                if (i % 64 == 0) sched_yield();
                sh->counter = c + 1;
                --sh->inside;
                if (s.v() != Status::ok) _exit(3);
            }
            _exit(0);
        }
        kids.push_back(pid);
    }
    for (pid_t pid : kids) {
        int st = 0;
        waitpid(pid, &st, 0);
        EXPECT_TRUE(WIFEXITED(st) && WEXITSTATUS(st) == 0);
    }
    EXPECT_EQ(sh->counter, kProcs * kIters);
    EXPECT_EQ(sh->violations, 0);
    munmap(sh, sizeof(Shared));
}
