#include <gtest/gtest.h>
#include <signal.h>
#include <sched.h>
#include <sys/mount.h>
#include <sys/wait.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <string>
#include <thread>
#include <vector>

#include "chimera/ipc/clock.hpp"
#include "chimera/ipc/lock.hpp"
#include "priority_inversion.hpp"
#include "sanitizer.hpp"
#include "test_util.hpp"

using namespace chimera::ipc;
using chimera::ipc::test::fork_child;
using chimera::ipc::test::shared_anon;
using chimera::ipc::test::wait_child;
using chimera::ipc::test::wait_for;

namespace {

struct Shared {
    LockWord lock;
    std::uint64_t counter = 0;       // plain: only the lock protects it
    std::atomic<int> holding{0};
    std::atomic<int> release{0};
};

struct Events {
    int recovered = 0, timed_out = 0, forced = 0, corrupt = 0;
    std::int32_t last_pid = 0, last_tid = 0;
};

void record(const LockEvent& ev, void* ctx) noexcept {
    auto* e = static_cast<Events*>(ctx);
    switch (ev.kind) {
        case LockEvent::Kind::recovered: ++e->recovered; break;
        case LockEvent::Kind::timed_out: ++e->timed_out; break;
        case LockEvent::Kind::forced: ++e->forced; break;
        case LockEvent::Kind::corrupt: ++e->corrupt; break;
    }
    e->last_pid = ev.previous_pid;
    e->last_tid = ev.previous_tid;
}

class IpcLock : public ::testing::Test {
protected:
    void SetUp() override { set_lock_event_handler(&record, &events); }
    void TearDown() override { set_lock_event_handler(nullptr); }
    Events events;
};

// A child process that takes the lock and holds it until killed; its pid once
// it holds it, -1 if it did not get there.
pid_t fork_holder(Shared& s) {
    const pid_t child = fork_child([&] {
        if (lock(s.lock) != LockStatus::acquired) return 2;
        s.holding = 1;
        for (;;) pause();
    });
    return wait_for([&] { return s.holding.load() == 1; }) ? child : -1;
}

}  // namespace

TEST_F(IpcLock, UncontendedLockUnlock) {
    LockWord l;
    EXPECT_EQ(lock(l), LockStatus::acquired);
    EXPECT_EQ(l.owner.load(), self_owner_id());
    EXPECT_EQ(owner_pid(l.owner.load()), getpid());
    EXPECT_EQ(owner_tid(l.owner.load()), gettid());
    EXPECT_EQ(lock(l), LockStatus::already_held);
    EXPECT_EQ(try_lock(l), LockStatus::already_held);
    EXPECT_TRUE(unlock(l));
    EXPECT_EQ(l.owner.load(), 0u);
    EXPECT_FALSE(unlock(l));  // not held
    EXPECT_EQ(try_lock(l), LockStatus::acquired);
    EXPECT_TRUE(unlock(l));
}

TEST_F(IpcLock, OwnerIdIsRefreshedInAForkedChild) {
    CHIMERA_NOT_UNDER_TSAN("a forked child");
    const std::uint64_t parent = self_owner_id();
    auto* seen = shared_anon<std::atomic<std::uint64_t>>();
    const pid_t child = fork_child([&] {
        seen->store(self_owner_id());
        return 0;
    });
    ASSERT_EQ(wait_child(child), 0);
    EXPECT_NE(seen->load(), parent);
    EXPECT_EQ(owner_pid(seen->load()), child);
}

TEST_F(IpcLock, MutualExclusionAcrossProcesses) {
    CHIMERA_NOT_UNDER_TSAN("forked lockers");
    auto* s = shared_anon<Shared>();
    constexpr int kProcs = 3, kIters = 20000;
    std::vector<pid_t> kids;
    for (int p = 0; p < kProcs; ++p)
        kids.push_back(fork_child([&] {
            for (int i = 0; i < kIters; ++i) {
                if (!holds(lock(s->lock, LockOptions{.timeout_ns = 5'000'000'000}))) return 2;
                // a non-atomic read-modify-write that loses updates without the lock
                const std::uint64_t v = s->counter;
                if (i % 64 == 0) std::this_thread::yield();
                s->counter = v + 1;
                if (!unlock(s->lock)) return 3;
            }
            return 0;
        }));
    for (pid_t k : kids) EXPECT_EQ(wait_child(k), 0);
    EXPECT_EQ(s->counter, std::uint64_t{kProcs} * kIters);
    EXPECT_EQ(s->lock.owner.load(), 0u);
    EXPECT_EQ(s->lock.recoveries.load(), 0u);
    EXPECT_EQ(s->lock.timeouts.load(), 0u);
}

TEST_F(IpcLock, HolderKilledWithSigkillIsRecoveredAndReported) {
    CHIMERA_NOT_UNDER_TSAN("a forked holder killed with SIGKILL");
    auto* s = shared_anon<Shared>();
    const pid_t child = fork_holder(*s);
    ASSERT_GT(child, 0);
    EXPECT_EQ(try_lock(s->lock), LockStatus::busy);
    // Alive holder: a short wait times out, the lock is left alone.
    EXPECT_EQ(lock(s->lock, LockOptions{.timeout_ns = 2'000'000}), LockStatus::timed_out);
    EXPECT_EQ(owner_pid(s->lock.owner.load()), child);
    kill(child, SIGKILL);
    EXPECT_EQ(wait_child(child), 128 + SIGKILL);
    EXPECT_EQ(lock(s->lock), LockStatus::recovered);
    EXPECT_EQ(s->lock.owner.load(), self_owner_id());
    EXPECT_EQ(s->lock.recoveries.load(), 1u);
    EXPECT_EQ(s->lock.timeouts.load(), 1u);
    EXPECT_EQ(events.recovered, 1);
    EXPECT_EQ(events.timed_out, 1);
    EXPECT_EQ(events.last_pid, child);
    EXPECT_TRUE(unlock(s->lock));
}

TEST_F(IpcLock, ZombieHolderCountsAsDead) {
    CHIMERA_NOT_UNDER_TSAN("a forked holder left a zombie");
    auto* s = shared_anon<Shared>();
    const pid_t child = fork_child([&] {
        if (lock(s->lock) != LockStatus::acquired) return 2;
        return 0;  // exits holding the lock
    });
    // Not reaped yet: the child is a zombie.
    ASSERT_TRUE(wait_for([&] {
        const std::uint64_t o = s->lock.owner.load();
        return o != 0 && !owner_alive(o);
    }));
    EXPECT_EQ(lock(s->lock), LockStatus::recovered);
    EXPECT_EQ(wait_child(child), 0);
    EXPECT_TRUE(unlock(s->lock));
}

// Without /proc (a chroot or container that does not mount it) a live holder
// is still alive: only tgkill can answer there, and it says so. Taking its lock
// over would let two holders in.
TEST_F(IpcLock, ALiveHolderIsAliveWhereProcIsNotMounted) {
    CHIMERA_NOT_UNDER_TSAN("a forked child in its own mount namespace");
    if (geteuid() != 0) GTEST_SKIP() << "hiding /proc needs a mount namespace (root)";
    const pid_t child = fork_child([] {
        if (unshare(CLONE_NEWNS) != 0) return 77;
        if (mount(nullptr, "/", nullptr, MS_REC | MS_PRIVATE, nullptr) != 0) return 77;
        if (mount("none", "/proc", "tmpfs", 0, nullptr) != 0) return 77;  // an empty /proc
        if (access("/proc/self/stat", F_OK) == 0) return 3;
        return owner_alive(self_owner_id()) ? 0 : 4;
    });
    const int rc = wait_child(child);
    if (rc == 77) GTEST_SKIP() << "no mount namespace here";
    EXPECT_EQ(rc, 0) << "3: /proc still visible; 4: the live holder was taken for dead";
}

namespace {

// The thread named by `holder` has ended, or is ending, while its process
// `child` lives on: owner_alive() turns false, the lock is recovered, and the
// process, told to end by `release` = `end`, exits with 0.
void expect_ended_holder_of_a_live_process(Shared& s, pid_t child, std::uint64_t holder, int end) {
    EXPECT_TRUE(wait_for([&] { return !owner_alive(holder); })) << "an ended thread taken for alive";
    EXPECT_EQ(kill(child, 0), 0) << "the process itself lives on";
    EXPECT_EQ(lock(s.lock), LockStatus::recovered);
    EXPECT_TRUE(unlock(s.lock));
    s.release.store(end);
    EXPECT_EQ(wait_child(child), 0);
}

}  // namespace

// owner_alive() asks through pidfds where it can (reading a process's /proc
// stat would hold its memory, and so its segment locks, past its death); the
// leader of several threads still needs /proc: it can end alone while the
// process lives on, and the kernel holds back its pidfd until all have ended.
TEST_F(IpcLock, AHolderWhoseMainThreadEndedAloneIsDeadWhileItsProcessLives) {
    CHIMERA_NOT_UNDER_TSAN("a forked child");
    auto* s = shared_anon<Shared>();
    const pid_t child = fork();
    if (child == 0) {
        if (lock(s->lock) != LockStatus::acquired) _exit(2);
        std::thread([s] {
            while (s->release.load() == 0) std::this_thread::sleep_for(std::chrono::milliseconds(1));
            _exit(0);
        }).detach();
        s->holding.store(1);
        // The main thread ends holding the lock: the exit system call ends one
        // thread, without the unwinding of pthread_exit() (gtest would catch it).
        syscall(SYS_exit, 0);
    }
    ASSERT_TRUE(wait_for([&] { return s->holding.load() == 1; }));
    const std::uint64_t holder = s->lock.owner.load();
    ASSERT_NE(holder, 0u);
    expect_ended_holder_of_a_live_process(*s, child, holder, 1);
}

// A holder that is one thread of another process: alive while it runs, dead
// once it has ended, though its process lives on (the pidfd of the thread,
// PIDFD_THREAD, where the kernel has it; /proc/PID/task/TID/stat before).
TEST_F(IpcLock, AHolderThreadOfAnotherProcessIsDeadOnceItEndsThoughItsProcessLives) {
    CHIMERA_NOT_UNDER_TSAN("a forked child with a thread");
    auto* s = shared_anon<Shared>();
    const pid_t child = fork_child([s] {
        std::thread([s] {
            if (lock(s->lock) != LockStatus::acquired) return;
            s->holding.store(1);
            while (s->release.load() == 0) std::this_thread::sleep_for(std::chrono::milliseconds(1));
        }).join();  // the thread ends holding the lock
        while (s->release.load() != 2) std::this_thread::sleep_for(std::chrono::milliseconds(1));
        return 0;
    });
    ASSERT_TRUE(wait_for([&] { return s->holding.load() == 1; }));
    const std::uint64_t holder = s->lock.owner.load();
    ASSERT_NE(owner_tid(holder), child);
    EXPECT_TRUE(owner_alive(holder));
    s->release.store(1);  // the thread ends
    expect_ended_holder_of_a_live_process(*s, child, holder, 2);
}

TEST_F(IpcLock, ALiveHolderOfOneThreadIsAliveAndDeadOnceKilledUnreaped) {
    CHIMERA_NOT_UNDER_TSAN("a forked holder");
    auto* s = shared_anon<Shared>();
    const pid_t child = fork_holder(*s);
    const std::uint64_t holder = s->lock.owner.load();
    EXPECT_TRUE(owner_alive(holder));
    kill(child, SIGKILL);
    siginfo_t info{};
    ASSERT_EQ(waitid(P_PID, static_cast<id_t>(child), &info, WEXITED | WNOWAIT), 0);  // a zombie now
    EXPECT_FALSE(owner_alive(holder));
    EXPECT_EQ(wait_child(child), 128 + SIGKILL);
    EXPECT_FALSE(owner_alive(holder));
}

TEST_F(IpcLock, HolderThreadThatExitedIsRecovered) {
    LockWord l;
    std::thread t([&] { (void)lock(l); });
    t.join();
    // join() returns when the kernel clears the thread's tid, early in its
    // exit: the task lingers until the exit completes (the guest under load
    // showed it alive there), then it is gone.
    ASSERT_TRUE(wait_for([&] { return !owner_alive(l.owner.load()); }));
    EXPECT_EQ(lock(l), LockStatus::recovered);
    EXPECT_EQ(events.recovered, 1);
    EXPECT_TRUE(unlock(l));
}

TEST_F(IpcLock, TimeoutIsReportedAndBlindResetOnlyWhenAsked) {
    CHIMERA_NOT_UNDER_TSAN("a forked holder");
    auto* s = shared_anon<Shared>();
    const pid_t child = fork_child([&] {
        if (lock(s->lock) != LockStatus::acquired) return 2;
        s->holding = 1;
        while (s->release.load() == 0) std::this_thread::sleep_for(std::chrono::milliseconds(1));
        return unlock(s->lock) ? 0 : 7;  // reset by the parent: unlock must say so
    });
    ASSERT_TRUE(wait_for([&] { return s->holding.load() == 1; }));
    const std::int64_t t0 = now_ns();
    EXPECT_EQ(lock(s->lock, LockOptions{.timeout_ns = 20'000'000}), LockStatus::timed_out);
    EXPECT_GE(now_ns() - t0, 20'000'000);
    EXPECT_EQ(s->lock.timeouts.load(), 1u);
    EXPECT_EQ(events.timed_out, 1);
    EXPECT_EQ(lock(s->lock, LockOptions{.timeout_ns = 5'000'000, .reset_on_timeout = true}),
              LockStatus::forced);
    EXPECT_EQ(s->lock.forced.load(), 1u);
    EXPECT_EQ(events.forced, 1);
    EXPECT_EQ(events.last_pid, child);
    s->release = 1;
    EXPECT_EQ(wait_child(child), 7);
    EXPECT_TRUE(unlock(s->lock));
}

TEST_F(IpcLock, WaiterGetsTheLockWhenTheHolderReleases) {
    CHIMERA_NOT_UNDER_TSAN("a forked holder");
    auto* s = shared_anon<Shared>();
    const pid_t child = fork_child([&] {
        if (lock(s->lock) != LockStatus::acquired) return 2;
        s->holding = 1;
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
        s->counter = 11;
        return unlock(s->lock) ? 0 : 3;
    });
    ASSERT_TRUE(wait_for([&] { return s->holding.load() == 1; }));
    EXPECT_EQ(lock(s->lock, LockOptions{.timeout_ns = 2'000'000'000}), LockStatus::acquired);
    EXPECT_EQ(s->counter, 11u);
    EXPECT_TRUE(unlock(s->lock));
    EXPECT_EQ(wait_child(child), 0);
    EXPECT_EQ(events.recovered + events.timed_out + events.forced, 0);
}

// A holder killed while a waiter is blocked in FUTEX_LOCK_PI: the kernel hands
// the lock to the waiter at the holder's exit, and the waiter is told it was a
// recovery (the holder's pid was still in the word), not a release.
TEST_F(IpcLock, HolderKilledWhileAWaiterBlocksInTheKernelIsRecovered) {
    CHIMERA_NOT_UNDER_TSAN("a forked holder killed with SIGKILL");
    auto* s = shared_anon<Shared>();
    const pid_t child = fork_holder(*s);
    ASSERT_GT(child, 0);
    LockStatus got = LockStatus::busy;
    bool released = false;
    std::thread waiter([&] {
        got = lock(s->lock, LockOptions{.timeout_ns = 10'000'000'000});
        released = holds(got) && unlock(s->lock);
    });
    // FUTEX_WAITERS in the word: the waiter is queued in the kernel.
    ASSERT_TRUE(wait_for([&] { return (s->lock.owner.load() & kFutexWaiters) != 0; }));
    kill(child, SIGKILL);
    waiter.join();
    EXPECT_EQ(wait_child(child), 128 + SIGKILL);
    EXPECT_EQ(got, LockStatus::recovered);
    EXPECT_EQ(events.recovered, 1);
    EXPECT_EQ(events.last_pid, child);
    EXPECT_EQ(s->lock.recoveries.load(), 1u);
    EXPECT_TRUE(released);
    EXPECT_EQ(s->lock.owner.load(), 0u);
}

// A waiter queued in the kernel is handed the lock by FUTEX_UNLOCK_PI when the
// holder releases: a clean release, not a recovery.
TEST_F(IpcLock, ReleaseToAWaiterBlockedInTheKernelIsClean) {
    LockWord l;
    ASSERT_EQ(lock(l), LockStatus::acquired);
    LockStatus got = LockStatus::busy;
    std::thread waiter([&] {
        got = lock(l, LockOptions{.timeout_ns = 10'000'000'000});
        if (holds(got)) (void)unlock(l);
    });
    ASSERT_TRUE(wait_for([&] { return (l.owner.load() & kFutexWaiters) != 0; }));
    EXPECT_TRUE(unlock(l));  // through FUTEX_UNLOCK_PI
    waiter.join();
    EXPECT_EQ(got, LockStatus::acquired);
    EXPECT_EQ(events.recovered + events.corrupt + events.timed_out, 0);
    EXPECT_EQ(l.owner.load(), 0u);
}

namespace {
bool kthreadd_is_tid_2() {
    char comm[32] = {};
    FILE* f = std::fopen("/proc/2/comm", "r");
    if (!f) return false;
    const bool ok = std::fgets(comm, sizeof comm, f) && std::string(comm) == "kthreadd\n";
    std::fclose(f);
    return ok;
}
}  // namespace

// A word overwritten with an owner no holder could have written — here our pid
// with the TID of the namespace's init, a thread of another process — is
// refused within two liveness periods even by a caller that waits forever,
// counted and reported; the word is left as it was.
TEST_F(IpcLock, ACorruptWordIsRefusedEvenWithoutATimeout) {
    LockWord l;
    const std::uint64_t garbage = std::uint64_t(std::uint32_t(getpid())) << 32 | 1u;
    l.owner.store(garbage);
    EXPECT_EQ(lock(l, LockOptions{.timeout_ns = -1, .liveness_check_ns = 2'000'000}), LockStatus::corrupt);
    EXPECT_EQ(owner_of(l.owner.load()), garbage);
    EXPECT_EQ(l.corruptions.load(), 1u);
    EXPECT_EQ(events.corrupt, 1);
    EXPECT_EQ(events.recovered + events.timed_out + events.forced, 0);
    // A word the kernel refuses (EPERM: the TID of a kernel thread, kthreadd)
    // is refused too, after kRefusedBoundNs (50 ms) of looking again.
    if (!kthreadd_is_tid_2()) GTEST_SKIP() << "no kthreadd at TID 2 in this PID namespace";
    const std::uint64_t kthread = std::uint64_t(std::uint32_t(getpid())) << 32 | 2u;
    l.owner.store(kthread);
    EXPECT_EQ(lock(l, LockOptions{.timeout_ns = -1}), LockStatus::corrupt);
    EXPECT_EQ(events.corrupt, 2);
    EXPECT_EQ(owner_of(l.owner.load()), kthread);  // left alone (the kernel may add FUTEX_WAITERS)
}

// The three-thread scene (tests/support/priority_inversion.hpp) with the table
// lock: H blocks in FUTEX_LOCK_PI, the kernel boosts L past M.
namespace {
struct TableLock {
    LockWord word;
    void lock() {
        if (!holds(chimera::ipc::lock(word, LockOptions{.timeout_ns = -1}))) std::abort();
    }
    void unlock() {
        if (!chimera::ipc::unlock(word)) std::abort();
    }
};
}  // namespace

TEST(IpcLockPi, BoostsTheHolderPastAMediumHog) {
    using namespace chimera::test::inversion;
    TableLock lock;
    const std::vector<int> ev = three_threads(lock);
    if (ev.empty()) GTEST_SKIP() << "SCHED_FIFO is not allowed here";
    EXPECT_EQ(ev, (std::vector<int>{l_released, h_acquired, m_saw_h_done}));
    EXPECT_EQ(lock.word.owner.load(), 0u);
}
