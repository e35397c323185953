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

TEST(SppPlacement, WithoutPriorityTheExecutiveIsSchedOther) {
    auto proc = spp::Processor::init(make_config(), make_library());
    locate_executive(*proc);
    EXPECT_FALSE(proc->realtime());
    EXPECT_EQ(placement.policy.load(), SCHED_OTHER);
}

// In a child that gave up root and any real-time allowance (as tests/muf
// does): the executive runs SCHED_OTHER, realtime() says so, the work is
// done, and stderr says why.
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
        spp::Config c = make_config();
        c.priority = 30;
        auto proc = spp::Processor::init(c, make_library());
        auto s = spp::Spp::init(*proc, 1);
        placement.calls.store(0);
        if (s->call(s->translate("where")) != 0 || s->wait() != 0 || placement.calls.load() != 1) _exit(12);
        if (proc->realtime()) _exit(13);
        if (placement.policy.load() != SCHED_OTHER) _exit(14);
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
