// Runs inside the PREEMPT_RT guest (tests/rtguest): the kernel facilities the
// scheduler's deadline backend relies on (docs/architecture.md §9, §10) —
// SCHED_DEADLINE admission control and the SCHED_FLAG_DL_OVERRUN → SIGXCPU
// overrun signal — and that the guest really is a PREEMPT_RT kernel.
// Behaviour only: timing measured under TCG means nothing and is neither
// asserted nor printed.
#include <gtest/gtest.h>

#include <atomic>
#include <cerrno>
#include <chrono>
#include <condition_variable>
#include <csignal>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <mutex>
#include <pthread.h>
#include <sched.h>
#include <string>
#include <sys/syscall.h>
#include <sys/utsname.h>
#include <thread>
#include <unistd.h>
#include <vector>

namespace {

// glibc 2.36 has no sched_setattr wrapper and <linux/sched/types.h> clashes
// with <sched.h>, so the kernel's struct is declared here.
struct SchedAttr {
    std::uint32_t size;
    std::uint32_t sched_policy;
    std::uint64_t sched_flags;
    std::int32_t sched_nice;
    std::uint32_t sched_priority;
    std::uint64_t sched_runtime;
    std::uint64_t sched_deadline;
    std::uint64_t sched_period;
};
static_assert(sizeof(SchedAttr) == 48, "SCHED_ATTR_SIZE_VER0");

constexpr std::uint32_t kSchedDeadline = 6;
constexpr std::uint64_t kFlagDlOverrun = 0x04;

int set_deadline(std::uint64_t runtime_ns, std::uint64_t period_ns, std::uint64_t flags = 0) {
    SchedAttr attr{};
    attr.size = sizeof attr;
    attr.sched_policy = kSchedDeadline;
    attr.sched_flags = flags;
    attr.sched_runtime = runtime_ns;
    attr.sched_deadline = period_ns;
    attr.sched_period = period_ns;
    return static_cast<int>(syscall(SYS_sched_setattr, 0, &attr, 0));
}

long read_long(const char* path) {
    std::ifstream in(path);
    long v = -1;
    in >> v;
    return v;
}

TEST(RtGuest, KernelIsPreemptRt) {
    utsname u{};
    ASSERT_EQ(uname(&u), 0);
    EXPECT_NE(std::string(u.version).find("PREEMPT_RT"), std::string::npos) << u.version;
    EXPECT_EQ(read_long("/sys/kernel/realtime"), 1);
}

TEST(RtGuest, SchedFifoIsAvailable) {
    int policy = -1;
    std::thread t([&] {
        sched_param p{};
        p.sched_priority = 10;
        if (pthread_setschedparam(pthread_self(), SCHED_FIFO, &p) == 0) {
            sched_param q{};
            pthread_getschedparam(pthread_self(), &policy, &q);
        }
    });
    t.join();
    EXPECT_EQ(policy, SCHED_FIFO);
}

// Admission control: reservations of utilisation u are accepted while their sum
// stays within sched_rt_runtime_us/sched_rt_period_us of every CPU of the root
// domain; the first one past it is refused with EBUSY.
TEST(RtGuest, DeadlineAdmissionRefusesOverload) {
    const long rt_runtime = read_long("/proc/sys/kernel/sched_rt_runtime_us");
    const long rt_period = read_long("/proc/sys/kernel/sched_rt_period_us");
    ASSERT_GT(rt_runtime, 0);
    ASSERT_GT(rt_period, 0);
    const long cpus = sysconf(_SC_NPROCESSORS_ONLN);
    const std::uint64_t period = 10'000'000;  // 10 ms
    const std::uint64_t runtime = 6'000'000;  // u = 0.6
    // Largest n with n * 0.6 <= cpus * rt_runtime / rt_period.
    const long expected = (cpus * rt_runtime * 10) / (rt_period * 6);

    std::mutex m;
    std::condition_variable cv;
    bool release = false;
    std::vector<int> results;
    std::vector<std::thread> threads;
    for (long i = 0; i < expected + 2; ++i) {
        threads.emplace_back([&] {
            int rc = set_deadline(runtime, period);
            {
                std::lock_guard<std::mutex> lock(m);
                results.push_back(rc == 0 ? 0 : errno);
            }
            cv.notify_all();
            // A reservation that sleeps keeps its bandwidth reserved.
            std::unique_lock<std::mutex> lock(m);
            cv.wait(lock, [&] { return release; });
        });
        std::unique_lock<std::mutex> lock(m);
        cv.wait(lock, [&] { return results.size() == static_cast<std::size_t>(i + 1); });
    }
    {
        std::lock_guard<std::mutex> lock(m);
        release = true;
    }
    cv.notify_all();
    for (auto& t : threads) t.join();

    long accepted = 0;
    for (std::size_t i = 0; i < results.size(); ++i) {
        if (results[i] == 0) {
            ++accepted;
            EXPECT_EQ(static_cast<long>(i), accepted - 1) << "acceptance after a refusal";
        } else {
            EXPECT_EQ(results[i], EBUSY) << std::strerror(results[i]);
        }
    }
    EXPECT_EQ(accepted, expected) << cpus << " cpu(s), rt " << rt_runtime << "/" << rt_period;
}

std::atomic<int> g_xcpu_tid{0};
// The first receiver only: a later overrun signal, delivered to the main
// thread once the worker has gone, must not overwrite who got the first.
void on_xcpu(int) {
    int none = 0;
    g_xcpu_tid.compare_exchange_strong(none, static_cast<int>(gettid()), std::memory_order_relaxed);
}

// A reservation that runs past its runtime with SCHED_FLAG_DL_OVERRUN gets
// SIGXCPU (a timing-failure source, docs/architecture.md §10). The signal is
// process-directed, so every other thread blocks it and the worker receives it.
TEST(RtGuest, DeadlineOverrunRaisesSigxcpu) {
    struct sigaction sa{};
    sa.sa_handler = on_xcpu;
    sigemptyset(&sa.sa_mask);
    ASSERT_EQ(sigaction(SIGXCPU, &sa, nullptr), 0);
    sigset_t xcpu;
    sigemptyset(&xcpu);
    sigaddset(&xcpu, SIGXCPU);
    ASSERT_EQ(pthread_sigmask(SIG_BLOCK, &xcpu, nullptr), 0);
    g_xcpu_tid = 0;

    int set_rc = -1, worker_tid = 0;
    bool signalled = false;
    std::thread worker([&] {
        worker_tid = static_cast<int>(gettid());
        pthread_sigmask(SIG_UNBLOCK, &xcpu, nullptr);
        set_rc = set_deadline(1'000'000, 50'000'000, kFlagDlOverrun);  // 1 ms every 50 ms
        if (set_rc != 0) return;
        // Spin well past the 1 ms budget; stop at the signal (or give up after
        // 20 s of wall time, which only a broken kernel would reach).
        const auto give_up = std::chrono::steady_clock::now() + std::chrono::seconds(20);
        while (g_xcpu_tid.load(std::memory_order_relaxed) == 0 &&
               std::chrono::steady_clock::now() < give_up) {
        }
        signalled = g_xcpu_tid.load() != 0;
    });
    worker.join();
    pthread_sigmask(SIG_UNBLOCK, &xcpu, nullptr);
    ASSERT_EQ(set_rc, 0) << std::strerror(errno);
    EXPECT_TRUE(signalled);
    EXPECT_EQ(g_xcpu_tid.load(), worker_tid);
    signal(SIGXCPU, SIG_DFL);
}

}  // namespace
