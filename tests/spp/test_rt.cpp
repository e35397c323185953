// Where the executive runs: pinned to its CPU, SCHED_FIFO at its PRIORITY
// where the process may, and best effort with one warning where it may not.
// The executive reports its own placement through the `where` routine.
#include <gtest/gtest.h>

#include <fcntl.h>
#include <pthread.h>
#include <sched.h>
#include <sys/resource.h>
#include <sys/utsname.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <functional>
#include <sstream>
#include <string>
#include <thread>

#include "executive_fixture.hpp"

using namespace spp_test;
namespace spp = chimera::spp;

namespace {

// The CPUs this process may run on.
std::vector<int> allowed_cpus() {
    cpu_set_t set;
    CPU_ZERO(&set);
    std::vector<int> cpus;
    if (sched_getaffinity(0, sizeof set, &set) != 0) return cpus;
    for (int c = 0; c < CPU_SETSIZE; ++c)
        if (CPU_ISSET(c, &set)) cpus.push_back(c);
    return cpus;
}

// Whether a thread of this process may take SCHED_FIFO (tried on a scratch thread).
bool fifo_allowed() {
    int rc = -1;
    std::thread([&] {
        sched_param sp{};
        sp.sched_priority = 1;
        rc = pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp);
    }).join();
    return rc == 0;
}

// Runs `where` on the executive and returns once it has.
void locate_executive(spp::Processor& proc) {
    auto s = spp::Spp::init(proc, 1);
    placement.calls.store(0);
    ASSERT_EQ(s->call(s->translate("where")), 0);
    ASSERT_EQ(s->wait(), 0);
    ASSERT_EQ(placement.calls.load(), 1);
}

// Runs `body` on a thread pinned to `cpu` at SCHED_FIFO `priority`; false
// when the thread could not get them (then `body` did not run).
bool run_fifo_on(int cpu, int priority, const std::function<void()>& body) {
    bool placed = false;
    std::thread t([&] {
        cpu_set_t set;
        CPU_ZERO(&set);
        CPU_SET(static_cast<unsigned>(cpu), &set);
        sched_param sp{};
        sp.sched_priority = priority;
        if (pthread_setaffinity_np(pthread_self(), sizeof set, &set) != 0 ||
            pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp) != 0)
            return;
        placed = true;
        body();
    });
    t.join();
    return placed;
}

std::string read_file(const std::string& path) {
    std::ifstream f(path);
    std::stringstream ss;
    ss << f.rdbuf();
    return ss.str();
}

}  // namespace

TEST(SppPlacement, TheExecutiveRunsOnlyOnItsConfiguredCpu) {
    const std::vector<int> cpus = allowed_cpus();
    ASSERT_FALSE(cpus.empty());
    for (int cpu : {cpus.front(), cpus.back()}) {
        spp::Config c = make_config();
        c.cpu = cpu;
        auto proc = spp::Processor::init(c, make_library());
        locate_executive(*proc);
        EXPECT_EQ(placement.cpu.load(), cpu);
        EXPECT_EQ(placement.allowed_cpus.load(), 1);
    }
}

TEST(SppPlacement, WithoutCpuTheExecutiveIsNotPinned) {
    auto proc = spp::Processor::init(make_config(), make_library());
    locate_executive(*proc);
    EXPECT_EQ(placement.allowed_cpus.load(), static_cast<int>(allowed_cpus().size()));
}

TEST(SppPlacement, TheExecutiveRunsSchedFifoAtItsPriorityWhereAllowed) {
    if (!fifo_allowed()) GTEST_SKIP() << "this process may not use SCHED_FIFO (see the no-privilege test)";
    spp::Config c = make_config();
    c.priority = 37;
    auto proc = spp::Processor::init(c, make_library());
    locate_executive(*proc);
    EXPECT_TRUE(proc->realtime());
    EXPECT_EQ(placement.policy.load(), SCHED_FIFO);
    EXPECT_EQ(placement.priority.load(), 37);
}

// realtime() is for the caller of init to check its configuration took: it
// must be right when init returns, not once the executive thread got going.
TEST(SppPlacement, RealtimeIsSettledWhenInitReturns) {
    const bool allowed = fifo_allowed();
    spp::Config c = make_config();
    c.priority = 20;
    c.cpu = allowed_cpus().back();
    for (int attempt = 0; attempt < 20; ++attempt) {
        auto proc = spp::Processor::init(c, make_library());
        ASSERT_EQ(proc->realtime(), allowed) << "attempt " << attempt;
    }
}

// A CPU the executive cannot run on is a configuration error, reported by
// init like the others, not an executive quietly running elsewhere.
TEST(SppPlacement, ACpuTheExecutiveCannotRunOnIsAnInitErrorNamingTheSppAndLine) {
    spp::Config c = make_config();
    c.cpu = 4095;  // the largest CPU the file format takes; no test machine has it
    c.file = "lab.spp";
    c.line = 12;
    try {
        spp::Processor::init(c, make_library());
        ADD_FAILURE() << "init accepted CPU 4095";
    } catch (const spp::Error& e) {
        EXPECT_EQ(std::string(e.what()), "SPP fpa0 (lab.spp:12): cannot pin the executive to CPU 4095: Invalid argument");
    }
}

TEST(SppPlacement, WithoutPriorityTheExecutiveIsSchedOther) {
    auto proc = spp::Processor::init(make_config(), make_library());
    locate_executive(*proc);
    EXPECT_FALSE(proc->realtime());
    EXPECT_EQ(placement.policy.load(), SCHED_OTHER);
}

// In a child that gave up root and any real-time allowance (as tests/muf
// does): the executives run SCHED_OTHER, realtime() says so, the work is
// done, and stderr says why once for the process (as the MUF scheduler
// does), not once per SPP.
TEST(SppPlacement, WithoutRealTimePrivilegeItSaysSoAndRunsBestEffort) {
    char log_path[] = "/tmp/chimera-spp-stderr-XXXXXX";
    const int log_fd = mkstemp(log_path);
    ASSERT_GE(log_fd, 0);
    fflush(stderr);
    const pid_t child = fork();
    ASSERT_GE(child, 0);
    if (child == 0) {
        dup2(log_fd, STDERR_FILENO);
        rlimit none{0, 0};
        setrlimit(RLIMIT_RTPRIO, &none);
        if (getuid() == 0 && setresuid(65534, 65534, 65534) != 0) _exit(10);
        if (fifo_allowed()) _exit(11);
        for (const char* name : {"fpa0", "fpa1"}) {
            spp::Config c = make_config();
            c.name = name;
            c.priority = 30;
            auto proc = spp::Processor::init(c, make_library());
            auto s = spp::Spp::init(*proc, 1);
            placement.calls.store(0);
            if (s->call(s->translate("where")) != 0 || s->wait() != 0 || placement.calls.load() != 1) _exit(12);
            if (proc->realtime()) _exit(13);
            if (placement.policy.load() != SCHED_OTHER) _exit(14);
        }
        _exit(0);
    }
    close(log_fd);
    int status = 0;
    ASSERT_EQ(waitpid(child, &status, 0), child);
    const std::string log = read_file(log_path);
    std::remove(log_path);
    ASSERT_TRUE(WIFEXITED(status));
    EXPECT_EQ(WEXITSTATUS(status), 0) << "10 setresuid, 11 still privileged, 12 the work was not done, "
                                         "13 realtime() true, 14 not SCHED_OTHER; stderr: "
                                      << log;
    EXPECT_NE(log.find("spp fpa0: no real-time privilege"), std::string::npos) << log;
    int lines = 0;
    for (char ch : log) lines += ch == '\n';
    EXPECT_EQ(lines, 1) << log;
}

// In the PREEMPT_RT guest (tests/rtguest sets CHIMERA_RTGUEST): the kernel is
// the real-time one and the executive gets its priority there.
TEST(SppPlacement, InTheRtGuestTheKernelIsPreemptRtAndTheExecutiveRealTime) {
    if (!std::getenv("CHIMERA_RTGUEST")) GTEST_SKIP() << "not in the PREEMPT_RT guest";
    utsname u{};
    ASSERT_EQ(uname(&u), 0);
    EXPECT_NE(std::string(u.version).find("PREEMPT_RT"), std::string::npos) << u.version;
    spp::Config c = make_config();
    c.priority = 50;
    c.cpu = allowed_cpus().back();
    auto proc = spp::Processor::init(c, make_library());
    locate_executive(*proc);
    EXPECT_TRUE(proc->realtime());
    EXPECT_EQ(placement.policy.load(), SCHED_FIFO);
    EXPECT_EQ(placement.priority.load(), 50);
    EXPECT_EQ(placement.cpu.load(), c.cpu);
}

// --- a task above the executive on its CPU -----------------------------------
//
// The deployment the executive's PRIORITY is for: a control task at a higher
// SCHED_FIFO priority on the executive's own CPU. The executive runs only
// while that task sleeps, and the task preempts it the instant it is woken.

class SppAboveTheExecutive : public ::testing::Test {
protected:
    void SetUp() override {
        if (!fifo_allowed()) GTEST_SKIP() << "SCHED_FIFO refused: no task can be placed above the executive";
        reset_fixtures();
        cpu_ = allowed_cpus().back();
    }
    std::unique_ptr<spp::Processor> start(int queue) {
        spp::Config c = make_config(queue);
        c.cpu = cpu_;
        c.priority = 10;
        return spp::Processor::init(c, make_library());
    }
    int cpu_ = 0;
};

// The task fills its command buffer and waits. It is above the executive on
// the executive's CPU, so the executive can make room only while the task
// sleeps: wait() must sleep at once, never spin until room appears.
TEST_F(SppAboveTheExecutive, WaitOnAFullBufferSleepsAndLetsTheExecutiveRun) {
    if (allowed_cpus().size() < 2) GTEST_SKIP() << "one CPU: nothing could open the gate";
    auto proc = start(/*queue=*/4);
    auto holder = spp::Spp::init(*proc, 1);
    ASSERT_EQ(holder->call(holder->translate("hold"), tag_gate(0, 0)), 0);
    gates[0].await_entered();
    // Opens the gate (from any other CPU) once the task's buffer is full.
    std::atomic<bool> full{false};
    std::thread opener([&] {
        while (!full.load()) std::this_thread::yield();
        gates[0].open();
    });
    int wait_rc = -1;
    ASSERT_TRUE(run_fifo_on(cpu_, 20, [&] {
        auto s = spp::Spp::init(*proc, 2);
        const spp::Handle rec = s->translate("record");
        for (std::int64_t t : {1, 2, 3, 4}) EXPECT_EQ(s->call(rec, tag(t)), 0);
        EXPECT_EQ(s->call(rec, tag(5)), -ENOSPC);
        full.store(true);
        wait_rc = s->wait();
    }));
    opener.join();
    EXPECT_EQ(wait_rc, 0);
    EXPECT_EQ(journal.entries(), (std::vector<std::int64_t>{0, 1, 2, 3, 4}));
}

// The task is woken by its WAKEUP and runs before the executive takes
// another step: by then the WAKEUP must be retired (buffer room, queued(),
// executed()), not still in the buffer.
TEST_F(SppAboveTheExecutive, WhenWaitReturnsItsWakeupIsAlreadyRetired) {
    auto proc = start(/*queue=*/2);
    int refused = 0, left_queued = 0, miscounted = 0;
    ASSERT_TRUE(run_fifo_on(cpu_, 20, [&] {
        auto s = spp::Spp::init(*proc, 1);
        const spp::Handle rec = s->translate("record");
        for (int round = 0; round < 50; ++round) {
            const std::uint64_t ran = proc->executed();
            refused += s->call(rec, tag(round)) != 0;
            if (s->wait() != 0) ++refused;
            left_queued += proc->queued() != 0;
            miscounted += proc->executed() - ran != 2;  // the record and the WAKEUP
            // QUEUE 2: both fit only if the WAKEUP's entry is free.
            refused += s->call(rec, tag(round)) != 0;
            refused += s->call(rec, tag(round)) != 0;
            if (s->wait() != 0) ++refused;
        }
    }));
    EXPECT_EQ(refused, 0);
    EXPECT_EQ(left_queued, 0);
    EXPECT_EQ(miscounted, 0);
    EXPECT_EQ(journal.size(), 150);
}
