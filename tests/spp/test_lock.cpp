// lock() / release() (§7.4.1, §7.4.2's open question): a job holds the SPP
// exclusively, waiting lockers get it in priority order (ties: the earlier
// request), release() is buffered so the job's commands all run before the
// next holder's. Lockers are known to be waiting through lock_waiters(), not
// by sleeping.
#include <gtest/gtest.h>

#include <sys/resource.h>

#include <cerrno>
#include <thread>
#include <vector>

#include "executive_fixture.hpp"

using namespace spp_test;
namespace spp = chimera::spp;
using Entries = std::vector<std::int64_t>;

using SppLock = ExecutiveTest;

TEST_F(SppLock, ALockedJobRunsWholeBeforeAHigherPriorityTasksCommands) {
    start();
    spp::Spp& job = task(1);
    spp::Spp& urgent = task(99);
    job.lock();
    hold_executive(job, 1);  // the job's first command
    record_all(urgent, {50});
    record_all(job, {2, 3});
    EXPECT_EQ(job.release(), 0);  // buffered: returns with the executive still held
    gates[0].open();
    ASSERT_EQ(urgent.wait(), 0);
    // Without the lock 50 would run right after the hold (priority 99 > 1).
    EXPECT_EQ(journal.entries(), (Entries{1, 2, 3, 50}));
}

TEST_F(SppLock, WaitingLockersGetTheSppInPriorityOrderTiesByRequestOrder) {
    start();
    spp::Spp& first = task(1);
    spp::Spp& b = task(5);
    spp::Spp& c = task(20);
    spp::Spp& d = task(20);
    first.lock();
    hold_executive(first, 1);
    // Each locker runs a two-command job: 100 + its tags.
    auto job = [](spp::Spp& s, std::int64_t base) {
        s.lock();
        record_all(s, {base + 1, base + 2});
        EXPECT_EQ(s.release(), 0);
        EXPECT_EQ(s.wait(), 0);
    };
    std::vector<std::thread> lockers;
    lockers.emplace_back(job, std::ref(b), 100);
    ASSERT_TRUE(eventually([&] { return proc().lock_waiters() == 1; }));
    lockers.emplace_back(job, std::ref(c), 200);
    ASSERT_TRUE(eventually([&] { return proc().lock_waiters() == 2; }));
    lockers.emplace_back(job, std::ref(d), 300);
    ASSERT_TRUE(eventually([&] { return proc().lock_waiters() == 3; }));
    record_all(first, {2});
    EXPECT_EQ(first.release(), 0);
    gates[0].open();
    for (auto& t : lockers) t.join();
    // First-come-first-served would give b's job right after first's.
    EXPECT_EQ(journal.entries(), (Entries{1, 2, 201, 202, 301, 302, 101, 102}));
    EXPECT_EQ(proc().lock_waiters(), 0);
}

TEST_F(SppLock, ReleaseWithoutTheLockIsRefused) {
    start();
    spp::Spp& s = task(1);
    EXPECT_EQ(s.release(), -EINVAL);
    s.lock();
    EXPECT_EQ(s.release(), 0);
    EXPECT_EQ(s.release(), -EINVAL);
    ASSERT_EQ(s.wait(), 0);
}

TEST_F(SppLock, AReleaseRefusedByAFullBufferKeepsTheLock) {
    start(/*queue=*/2);
    spp::Spp& job = task(1);
    spp::Spp& next = task(2);
    job.lock();
    hold_executive(job, 1);
    record_all(job, {2});  // QUEUE 2: full
    EXPECT_EQ(job.release(), -ENOSPC);
    std::thread locker([&] {
        next.lock();
        record_all(next, {9});
        EXPECT_EQ(next.release(), 0);
        EXPECT_EQ(next.wait(), 0);
    });
    ASSERT_TRUE(eventually([&] { return proc().lock_waiters() == 1; }));
    gates[0].open();
    ASSERT_EQ(job.wait(), 0);
    // Still held: a second release is accepted, not "not locked".
    EXPECT_EQ(job.release(), 0);
    locker.join();
    EXPECT_EQ(journal.entries(), (Entries{1, 2, 9}));
}

TEST_F(SppLock, FinishReleasesAHeldLock) {
    start();
    std::unique_ptr<spp::Spp> job = spp::Spp::init(proc(), 1);
    spp::Spp& next = task(2);
    job->lock();
    record_all(*job, {1});
    job.reset();  // finish: runs 1, releases
    next.lock();  // would block forever if the lock were still held
    record_all(next, {2});
    EXPECT_EQ(next.release(), 0);
    ASSERT_EQ(next.wait(), 0);
    EXPECT_EQ(journal.entries(), (Entries{1, 2}));
}

TEST_F(SppLock, CommandsIssuedBeforeTheLockOfAnotherTaskWaitForItsJob) {
    // The lock is exclusive use of the executive, not of later commands only:
    // a command already queued by another task waits until the job ends.
    start();
    spp::Spp& holder = task(1);
    spp::Spp& other = task(50);
    spp::Spp& job = task(2);
    hold_executive(holder, 1);
    record_all(other, {50});
    job.lock();  // granted at once: nobody holds it
    record_all(job, {2, 3});
    EXPECT_EQ(job.release(), 0);
    gates[0].open();
    ASSERT_EQ(other.wait(), 0);
    EXPECT_EQ(journal.entries(), (Entries{1, 2, 3, 50}));
}

// release() only queues the RELEASE: a task that locks again right after must
// wait for it to run (and for any higher-priority locker it hands over to),
// not find itself still the owner and go on as if granted.
TEST_F(SppLock, LockingAgainWaitsUntilTheTasksBufferedReleaseHasRun) {
    start();
    spp::Spp& holder = task(1);
    spp::Spp& s = task(2);
    hold_executive(holder, 0);
    s.lock();  // free: granted at once
    record_all(s, {1});
    ASSERT_EQ(s.release(), 0);  // queued behind the hold
    std::atomic<bool> relocked{false};
    int journal_at_relock = -1;
    std::thread relocker([&] {
        s.lock();
        journal_at_relock = journal.size();
        relocked.store(true);
        EXPECT_EQ(s.release(), 0);
        EXPECT_EQ(s.wait(), 0);
    });
    // Either lock() came back at once, or it is blocked until the RELEASE runs.
    ASSERT_TRUE(eventually([&] { return relocked.load() || proc().lock_waiters() == 1; }));
    gates[0].open();
    relocker.join();
    EXPECT_EQ(journal_at_relock, 2) << "lock() returned before the task's own RELEASE had run";
}

// A task sleeping in wait() is woken by its own WAKEUP only: every other
// task's WAKEUP that woke it as well would cost it a switch in and out, at its
// (possibly high) priority. Each round one task holds the lock, so the others'
// commands stay queued and they sleep in wait() while the holder waits 200
// times; whatever wait() sleeps on must not be shared between tasks (with 8
// tasks, any sharing between two of them shows in some round).
TEST_F(SppLock, AnotherTasksWakeupDoesNotWakeATaskSleepingInWait) {
    // A wait() that sleeps once switches about 5 times (the sleep, and the
    // yields of libstdc++'s spin before it); one woken by every WAKEUP of a
    // task sharing its word switches hundreds of times.
    constexpr int kTasks = 8, kHolderWaits = 200, kMostSwitches = 20;
    start(/*queue=*/4, kTasks);
    std::vector<spp::Spp*> tasks;
    for (int t = 0; t < kTasks; ++t) tasks.push_back(&task(t + 1));
    for (int holder = 0; holder < kTasks; ++holder) {
        tasks[static_cast<std::size_t>(holder)]->lock();
        std::vector<std::thread> sleepers;
        std::vector<long> switches(kTasks, 0);
        for (int t = 0; t < kTasks; ++t) {
            if (t == holder) continue;
            sleepers.emplace_back([&, t] {
                spp::Spp& s = *tasks[static_cast<std::size_t>(t)];
                record_all(s, {t});
                rusage before{}, after{};
                getrusage(RUSAGE_THREAD, &before);
                EXPECT_EQ(s.wait(), 0);
                getrusage(RUSAGE_THREAD, &after);
                // Both kinds: a spurious wake-up may end in sleeping again
                // (voluntary) or in spinning and yielding (involuntary).
                switches[static_cast<std::size_t>(t)] =
                    after.ru_nvcsw - before.ru_nvcsw + after.ru_nivcsw - before.ru_nivcsw;
            });
        }
        // Every sleeper has issued its record and WAKEUP.
        ASSERT_TRUE(eventually([&] { return proc().queued() == 2u * (kTasks - 1); }));
        spp::Spp& h = *tasks[static_cast<std::size_t>(holder)];
        for (int k = 0; k < kHolderWaits; ++k) ASSERT_EQ(h.wait(), 0);
        ASSERT_EQ(h.release(), 0);
        for (auto& th : sleepers) th.join();
        for (int t = 0; t < kTasks; ++t)
            EXPECT_LE(switches[static_cast<std::size_t>(t)], kMostSwitches)
                << "task " << t << " slept in wait() while task " << holder << " waited " << kHolderWaits << " times";
    }
}
