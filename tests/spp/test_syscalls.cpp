// spp.hpp: call/write/read/wait/release "make a system call only to wake a
// sleeping executive or to sleep in wait()". Counted by the kernel: a
// per-thread perf counter on the raw_syscalls:sys_enter tracepoint (needs
// tracefs; the spp_syscalls test runs this under
// tests/prof/in_tracefs_namespace.sh, which mounts it privately, and in the
// PREEMPT_RT guest the test mounts it itself).
#include <gtest/gtest.h>

#include <linux/perf_event.h>
#include <sys/mount.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <array>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <thread>
#include <vector>

#include "executive_fixture.hpp"
#include "syscall_counter.hpp"

using namespace spp_test;
namespace spp = chimera::spp;

namespace {

using chimera::test::open_syscall_counter;
const auto read_counter = chimera::test::read_syscall_counter;

// Threads blocked in std::atomic<uint32_t>::wait on 16 consecutive words:
// libstdc++ keeps 16 buckets of waiters keyed by address, and these put a
// waiter in every one, as other code of a real program may.
class WaitersInEveryBucket {
public:
    WaitersInEveryBucket() {
        for (auto& w : words_) threads_.emplace_back([&w] { w.wait(0); });
    }
    ~WaitersInEveryBucket() {
        for (auto& w : words_) {
            w.store(1);
            w.notify_all();
        }
        for (auto& t : threads_) t.join();
    }

private:
    std::array<std::atomic<std::uint32_t>, 16> words_{};
    std::vector<std::thread> threads_;
};

}  // namespace

using SppSyscalls = ExecutiveTest;

TEST_F(SppSyscalls, IssuingCommandsWhileTheExecutiveIsBusyMakesNoSystemCall) {
    int fd = open_syscall_counter();
    if (fd < 0 && std::getenv("CHIMERA_RTGUEST")) {
        // The PREEMPT_RT guest is a throw-away machine whose init does not
        // mount tracefs: mount it there (never on the host).
        mount("nodev", "/sys/kernel/tracing", "tracefs", 0, nullptr);
        fd = open_syscall_counter();
    }
    if (fd < 0) {
        if (std::getenv("CHIMERA_REQUIRE_SYSCALL_COUNTER"))
            FAIL() << "raw_syscalls:sys_enter counter could not be opened";
        GTEST_SKIP() << "raw_syscalls:sys_enter not available (the spp_syscalls test provides it)";
    }
    WaitersInEveryBucket other_waiters;
    start(/*queue=*/64);
    spp::Spp& holder = task(1);
    spp::Spp& s = task(2);
    const spp::Handle rec = s.translate("record"), y = s.translate("y");
    unsigned char in[8] = {1, 2, 3, 4, 5, 6, 7, 8}, out[8] = {};
    hold_executive(holder, 0);  // busy in a routine: not asleep
    s.lock();                   // granted at once; so that release() is counted too
    // The read() of the counter is itself counted: calibrate it.
    const std::uint64_t c0 = read_counter(fd), c1 = read_counter(fd);
    const std::uint64_t a = read_counter(fd);
    int refused = 0;
    for (int k = 0; k < 20; ++k) {
        refused += s.call(rec, tag(k)) != 0;
        refused += s.write(y, in, sizeof in) != 0;
        refused += s.read(y, out, sizeof out) != 0;
    }
    refused += s.release() != 0;
    const std::uint64_t b = read_counter(fd);
    close(fd);
    EXPECT_EQ(refused, 0);
    EXPECT_EQ(b - a - (c1 - c0), 0u) << "system calls while issuing 61 commands to a busy executive";
    gates[0].open();
    ASSERT_EQ(s.wait(), 0);
    EXPECT_EQ(journal.size(), 21);
}
