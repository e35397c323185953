// ddsbridge end to end on this machine: two bridge tasks of one subsystem,
// one publishing X (JointState.position) and S (chimera_msgs/StateVar), the
// other subscribing them into Y and T, over Cyclone DDS on the loopback
// interface only (unicast discovery, no multicast), on a domain id chosen from
// the pid so concurrent runs do not meet.
//   - values arrive, with counters and stamps (get STATUS);
//   - an independent reader process (dds_echo: Cyclone's API + the IDL types
//     only) decodes the samples from the wire: ROS 2 type names, rt/ topics,
//     XCDR1, the QoS of each profile, the data;
//   - a sample of the wrong length is dropped and counted, never half-copied;
//   - a sample older than the newest taken (reordered, replayed) is refused,
//     counted and told; a restarted writer and equal stamps are taken;
//   - stale data: the publisher turned off, the subscriber's ports go to their
//     stale action (zeros; the illegal-configuration flag) with a warning, and
//     come back when it is turned on again;
//   - the bridge's thread and Cyclone's are SCHED_OTHER, the task threads not
//     touched;
//   - the task threads make no allocation and no system call beyond the
//     release wait (needs tracefs: run under tests/prof/in_tracefs_namespace.sh).
#include "chimera/ipc/segment.hpp"
#include "chimera/sbs.hpp"
#include "chimera/svar.hpp"

#include <dds/dds.h>
#include <gtest/gtest.h>
#include <linux/perf_event.h>
#include <sched.h>
#include <sys/ioctl.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <array>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "alloc_counter.hpp"
#include "ros2_msgs.h"
#include "syscall_counter.hpp"

namespace fs = std::filesystem;
using namespace std::chrono_literals;
using chimera::State;
using chimera::sbs::Control;
using chimera::sbs::Subsystem;
using chimera::sbs::TaskId;

namespace {

const char* kSvar =
    "NAME X\nTYPE double\nDESC joint positions published\nUNITS rad\nNELEM 6\n"
    "NAME Y\nTYPE double\nDESC joint positions received\nUNITS rad\nNELEM 6\n"
    "NAME S\nTYPE double\nDESC a plain array published\nUNITS none\nNELEM 3\n"
    "NAME T\nTYPE double\nDESC a plain array received\nUNITS none\nNELEM 3\n"
    "NAME T_RX\nTYPE double\nDESC T's counter, age and new/repeat/stale\nUNITS mixed\nNELEM 3\n"
    "NAME E\nTYPE double\nDESC joint torques received by name\nUNITS N m\nNELEM 6\n"
    "EOF\n";

// Loopback only, unicast discovery: nothing of the test leaves the machine.
const char* kCycloneConfig =
    "<CycloneDDS><Domain id=\"any\">"
    "<General><Interfaces><NetworkInterface name=\"lo\"/></Interfaces><AllowMulticast>false</AllowMulticast></General>"
    "<Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>30</MaxAutoParticipantIndex>"
    "<Peers><Peer address=\"127.0.0.1\"/></Peers></Discovery>"
    "</Domain></CycloneDDS>\n";

template <typename P>
bool eventually(P pred, std::chrono::milliseconds t = 10000ms) {
    const auto end = std::chrono::steady_clock::now() + t;
    while (std::chrono::steady_clock::now() < end) {
        if (pred()) return true;
        std::this_thread::sleep_for(5ms);
    }
    return pred();
}

std::string run(const std::string& command) {
    std::string out;
    if (FILE* p = ::popen(command.c_str(), "r")) {
        char buf[4096];
        while (std::fgets(buf, sizeof buf, p)) out += buf;
        ::pclose(p);
    }
    return out;
}

// The number after " KEY " on PORT's line of `get STATUS`; -1 when absent.
long status_count(const std::string& status, const std::string& port, const std::string& key) {
    std::istringstream lines(status);
    std::string line;
    while (std::getline(lines, line)) {
        if (line.rfind(port + " counter ", 0) != 0) continue;
        const auto at = line.find(" " + key + " ");
        return at == std::string::npos ? -1 : std::stol(line.substr(at + key.size() + 2));
    }
    return -1;
}

class Bridge : public ::testing::Test {
protected:
    void SetUp() override {
        static std::atomic<int> counter{0};
        const int n = counter++;
        name_ = "ddsb" + std::to_string(::getpid()) + "x" + std::to_string(n);
        domain_ = 1 + static_cast<int>((::getpid() * 7 + n) % 230);
        topic_ = "chimera_test/p" + std::to_string(::getpid()) + "_" + std::to_string(n);
        dir_ = fs::temp_directory_path() / name_;
        fs::create_directories(dir_);
        write("t.svar", kSvar);
        write("cyclone.xml", kCycloneConfig);
        write("t.sbs", "SUBSYSTEM " + name_ + "\nSVARFILE t.svar\nRTPU cpu0\nERRPRINT none\nEOF\n");
    }
    void TearDown() override {
        global_.reset();
        if (sbs_) sbs_->finish();
        sbs_.reset();
        fs::remove_all(dir_);
    }
    void write(const std::string& file, const std::string& text) { std::ofstream(dir_ / file) << text; }
    std::string config_path() const { return (dir_ / "cyclone.xml").string(); }

    std::string bridge_rmod(const std::string& name, const std::string& ports, const std::string& topics) {
        write(name + ".rmod", "MODULE ddsbridge\nDESC test bridge\n" + ports + "TASKTYPE periodic\nFREQ 200\nLOCAL\n" +
                                  "DOMAIN " + std::to_string(domain_) + "\nCONFIG " + config_path() + "\n" + topics + "EOF\n");
        return (dir_ / (name + ".rmod")).string();
    }
    // The publisher of X and S, the subscriber of Y and T, on topics of this run.
    void start(const std::string& y_action = "zero", const std::string& t_action = "illegal",
               const std::string& notify = "poll") {
        sbs_ = Subsystem::init((dir_ / "t.sbs").string());
        global_ = std::make_unique<chimera::svar::Table>(
            chimera::svar::Table::attach(chimera::ipc::segment_name(name_, "svar")));
        pub_ = sbs_->spawn(bridge_rmod("pub", "INVAR X S\nOUTVAR none\n",
                                       "NOTIFY " + notify + "\nJOINT_NAMES j1 j2 j3 j4 j5 j6\n"
                                       "TOPIC_X " + topic_ + "/joints pub JointState.position state\n"
                                       "TOPIC_S " + topic_ + "/array pub StateVar command\n"),
                           "cpu0");
        sub_ = sbs_->spawn(bridge_rmod("sub", "INVAR none\nOUTVAR Y T T_RX\n",
                                       "JOINT_NAMES j1 j2 j3 j4 j5 j6\n"
                                       "TOPIC_Y " + topic_ + "/joints sub JointState.position state 0.1 " + y_action + "\n"
                                       "TOPIC_T " + topic_ + "/array sub StateVar command 0.1 " + t_action + "\n"
                                       "STAMP_T T_RX\n"),
                           "cpu0");
        // One at a time: reconfig() would verify that a module produces X and S;
        // here the test writes them into the table itself.
        sbs_->control(pub_, Control::on);
        sbs_->control(sub_, Control::on);
    }
    template <std::size_t N>
    std::array<double, N> get(const std::string& var) {
        std::array<double, N> v{};
        EXPECT_EQ(global_->read(global_->index_of(var), v.data()), chimera::svar::Status::ok) << var;
        return v;
    }
    template <std::size_t N>
    void put(const std::string& var, const std::array<double, N>& v) {
        EXPECT_EQ(global_->write(global_->index_of(var), v.data()), chimera::svar::Status::ok) << var;
    }

    std::string name_, topic_;
    int domain_ = 0;
    fs::path dir_;
    std::unique_ptr<Subsystem> sbs_;
    std::unique_ptr<chimera::svar::Table> global_;
    TaskId pub_{}, sub_{};

    void count_task_threads(const std::string& notify);
    static bool syscall_counter_available() {
        const int probe = chimera::test::open_syscall_counter();
        if (probe >= 0) ::close(probe);
        return probe >= 0;
    }
};

const std::array<double, 6> kJoints{0.5, -1.25, 3.0, 0.0, 1e-3, -2.5};
const std::array<double, 3> kArray{7.0, 8.5, -9.0};

}  // namespace

TEST_F(Bridge, PublishedValuesArriveInTheSubscribersPortsWithCountersAndStamps) {
    start();
    put("X", kJoints);
    put("S", kArray);
    EXPECT_TRUE(eventually([&] { return get<6>("Y") == kJoints && get<3>("T") == kArray; }))
        << "Y and T never took the published values";
    const std::string status = sbs_->get(sub_, "STATUS");
    EXPECT_NE(status.find("Y counter "), std::string::npos) << status;
    EXPECT_NE(status.find("stale no received "), std::string::npos) << status;
    EXPECT_NE(status.find("rejected 0"), std::string::npos) << status;
    EXPECT_EQ(sbs_->status(sub_).state, State::ON);
    EXPECT_FALSE(sbs_->illegal_configuration());
    // STAMP_T: the sender's counter-stamps, growing; an age within the limit; new or a repeat.
    const auto rx0 = get<3>("T_RX");
    EXPECT_TRUE(eventually([&] { return get<3>("T_RX")[0] > rx0[0] + 10; })) << "the counter did not advance";
    const auto rx = get<3>("T_RX");
    EXPECT_GE(rx[1], 0.0);
    EXPECT_LE(rx[1], 0.1);
    EXPECT_TRUE(rx[2] == 0.0 || rx[2] == 1.0) << rx[2];
}

TEST_F(Bridge, AnIndependentReaderDecodesTheSamplesAsRos2Types) {
    start();
    put("X", kJoints);
    put("S", kArray);
    const std::string echo = std::string(DDS_ECHO) + " " + std::to_string(domain_) + " " + config_path() + " rt/";
    const std::string joints = run(echo + topic_ + "/joints JointState 3 20");
    EXPECT_NE(joints.find("writer type=sensor_msgs::msg::dds_::JointState_ representation=XCDR1 reliability=best_effort\n"),
              std::string::npos) << joints;
    EXPECT_NE(joints.find(" frame_id= name=[j1,j2,j3,j4,j5,j6] position=[0.5,-1.25,3,0,0.001,-2.5] velocity=[] effort=[]\n"),
              std::string::npos) << joints;
    // The stamp is ROS time (CLOCK_REALTIME) of the task's write: within seconds of now.
    const auto at = joints.find("JointState stamp=");
    ASSERT_NE(at, std::string::npos) << joints;
    const long sec = std::stol(joints.substr(at + 17));
    EXPECT_LE(std::labs(sec - static_cast<long>(std::time(nullptr))), 5) << joints;

    const std::string array = run(echo + topic_ + "/array StateVar 3 20");
    EXPECT_NE(array.find("writer type=chimera_msgs::msg::dds_::StateVar_ representation=XCDR1 reliability=reliable\n"),
              std::string::npos) << array;
    EXPECT_NE(array.find(" frame_id=S counter="), std::string::npos) << array;
    EXPECT_NE(array.find(" data=[7,8.5,-9]\n"), std::string::npos) << array;
    // Counters: the sender's counter-stamps, increasing (keep-last-1 may skip some).
    std::istringstream lines(array);
    std::string line;
    long last = -1, seen = 0;
    while (std::getline(lines, line)) {
        const auto c = line.find(" counter=");
        if (c == std::string::npos) continue;
        const long counter = std::stol(line.substr(c + 9));
        EXPECT_GT(counter, last) << array;
        last = counter;
        ++seen;
    }
    EXPECT_EQ(seen, 3) << array;
}

TEST_F(Bridge, ASampleOfTheWrongLengthIsDroppedAndCounted) {
    start();
    put("X", kJoints);
    ASSERT_TRUE(eventually([&] { return get<6>("Y") == kJoints; }));
    sbs_->control(pub_, Control::off);
    // A foreign writer on the same topic, with five positions for six joints.
    const dds_entity_t pp = dds_create_participant(static_cast<dds_domainid_t>(domain_), nullptr, nullptr);
    ASSERT_GT(pp, 0);
    const std::string topic = "rt/" + topic_ + "/joints";
    const dds_entity_t tp = dds_create_topic(pp, &sensor_msgs_msg_dds__JointState__desc, topic.c_str(), nullptr, nullptr);
    const dds_entity_t w = dds_create_writer(pp, tp, nullptr, nullptr);
    ASSERT_GT(w, 0);
    double five[5] = {9, 9, 9, 9, 9};
    char empty[] = "";
    char j1[] = "j1", j2[] = "j2", j3[] = "j3", j4[] = "j4", j5[] = "j5", j6[] = "j6";
    char* six_names[6] = {j1, j2, j3, j4, j5, j6};
    sensor_msgs_msg_dds__JointState_ s{};
    s.header.frame_id = empty;
    s.name = {6, 6, six_names, false};
    s.position = {5, 5, five, false};
    EXPECT_TRUE(eventually([&] {
        (void)dds_write(w, &s);
        return status_count(sbs_->get(sub_, "STATUS"), "Y", "length") > 0;
    })) << sbs_->get(sub_, "STATUS");
    const std::string status = sbs_->get(sub_, "STATUS");
    EXPECT_EQ(status_count(status, "Y", "rejected"), status_count(status, "Y", "length")) << status;
    dds_delete(pp);
    EXPECT_NE(get<6>("Y")[0], 9.0) << "the bad sample reached the port";
}

TEST_F(Bridge, StaleDataGoesToEachPortsStaleActionAndRecovers) {
    start("zero", "illegal");
    put("X", kJoints);
    put("S", kArray);
    ASSERT_TRUE(eventually([&] { return get<6>("Y") == kJoints && get<3>("T") == kArray; }));
    (void)sbs_->status(sub_);  // hands over the first warning so far
    sbs_->control(pub_, Control::off);  // the link goes quiet
    // Y: zeros; T: keeps its last value and raises the illegal-configuration flag.
    EXPECT_TRUE(eventually([&] { return get<6>("Y") == std::array<double, 6>{} && sbs_->illegal_configuration(); }));
    EXPECT_EQ(get<3>("T"), kArray);
    EXPECT_TRUE(eventually([&] { return get<3>("T_RX")[2] == -1.0; })) << "STAMP_T says stale";
    EXPECT_GT(get<3>("T_RX")[1], 0.1) << "and its age is past the limit";
    const auto st = sbs_->status(sub_);
    EXPECT_EQ(st.state, State::ON) << "stale data never stops the task";
    EXPECT_NE(st.warning.find(": stale (no value newer than 0.1 s; "), std::string::npos) << st.warning;
    EXPECT_NE(sbs_->get(sub_, "STATUS").find("stale yes"), std::string::npos);
    const auto cycles = st.cycles;
    EXPECT_TRUE(eventually([&] { return sbs_->status(sub_).cycles > cycles + 20; })) << "the task kept its rate";

    sbs_->control(pub_, Control::on);  // the link is back
    EXPECT_TRUE(eventually([&] { return get<6>("Y") == kJoints && !sbs_->illegal_configuration(); }));
    EXPECT_EQ(sbs_->get(sub_, "STATUS").find("stale yes"), std::string::npos);
}

TEST_F(Bridge, StaleDataWithTheErrorActionPutsTheTaskInError) {
    start("error", "warn");
    put("X", kJoints);
    ASSERT_TRUE(eventually([&] { return get<6>("Y") == kJoints; }));
    sbs_->control(pub_, Control::off);
    EXPECT_TRUE(eventually([&] { return sbs_->status(sub_).state == State::ERROR; }));
    EXPECT_NE(sbs_->status(sub_).error.find("Y from rt/" + topic_ + "/joints: stale (no value newer than 0.1 s; error)"),
              std::string::npos);
}

namespace {

std::set<long> thread_ids() {
    std::set<long> out;
    for (const auto& e : fs::directory_iterator("/proc/self/task")) out.insert(std::stol(e.path().filename().string()));
    return out;
}

}  // namespace

TEST_F(Bridge, TheBridgeThreadAndCycloneThreadsAreNotRealTime) {
    const std::set<long> before = thread_ids();
    start();
    const std::set<long> tasks{sbs_->status(pub_).tid, sbs_->status(sub_).tid};
    int others = 0;
    for (const long tid : thread_ids()) {
        if (before.count(tid) || tasks.count(tid)) continue;
        std::ifstream comm("/proc/self/task/" + std::to_string(tid) + "/comm");
        std::string name;
        std::getline(comm, name);
        const int policy = sched_getscheduler(static_cast<pid_t>(tid));
        if (name.rfind("ddsbridge", 0) != 0 && name.find("recv") == std::string::npos &&
            name.find("tev") == std::string::npos && name.find("gc") == std::string::npos &&
            name.find("dq.") == std::string::npos && name.find("lease") == std::string::npos)
            continue;  // the runtime's own threads (reporter, dispatchers) are not the bridge's business
        ++others;
        EXPECT_EQ(policy, SCHED_OTHER) << "thread " << tid << " (" << name << ")";
    }
    EXPECT_GE(others, 3) << "the bridge threads and Cyclone's receive and event threads";
}

namespace {

// A kernel counter of every system call of one thread of this process.
int open_thread_counter(long tid) {
    const long id = chimera::test::tracepoint_id("raw_syscalls/sys_enter");
    if (id < 0) return -1;
    perf_event_attr a{};
    a.size = sizeof a;
    a.type = PERF_TYPE_TRACEPOINT;
    a.config = static_cast<std::uint64_t>(id);
    return static_cast<int>(::syscall(SYS_perf_event_open, &a, static_cast<pid_t>(tid), -1, -1, PERF_FLAG_FD_CLOEXEC));
}

}  // namespace

// The real-time path never touches the network (issue #19.3): while samples
// flow both ways, each bridge task thread makes no allocation and no system
// call but the release wait (plus, as for every task, a futex(2) when the
// table lock is found busy and a profiler read in a cycle switched out).
// NOTIFY poll: the release wait alone. NOTIFY wake: the publishing task adds
// one futex(2) wake per cycle (counted and stated: 2 system calls per cycle),
// the subscribing one none.
void Bridge::count_task_threads(const std::string& notify) {
    start("warn", "warn", notify);
    put("X", kJoints);
    put("S", kArray);
    ASSERT_TRUE(eventually([&] { return get<6>("Y") == kJoints && get<3>("T") == kArray; }));
    std::this_thread::sleep_for(500ms);  // warm-up
    for (const TaskId id : {pub_, sub_}) {
        const auto received0 = sbs_->get(sub_, "STATUS");  // get() runs on the task thread: not while counting
        const auto st0 = sbs_->status(id);
        const int all = open_thread_counter(st0.tid), futex = chimera::test::open_other_futex_counter(st0.tid);
        ASSERT_GE(all, 0);
        ASSERT_GE(futex, 0);
        const std::uint64_t calls0 = chimera::test::read_syscall_counter(all);
        const std::uint64_t futex0 = chimera::test::read_syscall_counter(futex);
        // Cycles counted inside the counters' window (opening a filtered
        // tracepoint counter can take tens of milliseconds).
        const auto started = sbs_->status(id);
        chimera::test::alloc_count_start(chimera::test::AllocScope::thread, st0.tid);
        std::this_thread::sleep_for(1s);
        const long allocations = chimera::test::alloc_count_stop();
        const auto st = sbs_->status(id);
        const std::uint64_t calls = chimera::test::read_syscall_counter(all) - calls0;
        const std::uint64_t locks = chimera::test::read_syscall_counter(futex) - futex0;
        ::close(all);
        ::close(futex);
        const std::uint64_t cycles = st.cycles - started.cycles;
        const std::uint64_t switched = st.profile.switched - started.profile.switched;
        std::printf("NOTIFY %s, %s: cycles %llu system calls %llu (futex %llu, switched %llu) allocations %ld\n", notify.c_str(),
                    st.rmod.c_str(), static_cast<unsigned long long>(cycles), static_cast<unsigned long long>(calls),
                    static_cast<unsigned long long>(locks), static_cast<unsigned long long>(switched), allocations);
        EXPECT_GT(cycles, 50u) << st.rmod;
        EXPECT_EQ(allocations, 0) << st.rmod;
        // The status reads bracket the counting window: a cycle more at each end.
        EXPECT_GE(calls + 2, cycles) << st.rmod << ": the release wait alone is one per cycle";
        // futex(2) but the release wait: the table lock found busy and, NOTIFY wake, the wake.
        EXPECT_LE(calls, cycles + locks + switched + 2) << st.rmod;
        if (notify == "wake" && id == pub_) {
            EXPECT_GE(locks + 2, cycles) << "one wake per cycle";
            EXPECT_LE(locks, cycles + 2 + cycles / 5) << "one wake per cycle, and the lock found busy now and then";
        } else {
            EXPECT_LE(locks, cycles / 5) << st.rmod << ": the table lock found busy now and then, nothing else";
        }
        EXPECT_NE(sbs_->get(sub_, "STATUS"), received0) << "samples kept flowing while counted";
    }
}

TEST_F(Bridge, TaskThreadsMakeNoAllocationAndNoSystemCallButTheReleaseWait) {
    if (!syscall_counter_available()) GTEST_SKIP() << "no raw_syscalls tracepoint: tracefs not mounted (see tests/prof/in_tracefs_namespace.sh)";
    count_task_threads("poll");
}

TEST_F(Bridge, WithNotifyWakeThePublishingTaskAddsOneWakePerCycle) {
    if (!syscall_counter_available()) GTEST_SKIP() << "no raw_syscalls tracepoint: tracefs not mounted (see tests/prof/in_tracefs_namespace.sh)";
    count_task_threads("wake");
}

// NOTIFY spin keeps the task thread's count of NOTIFY poll: the busy wait is
// the bridge thread's alone.
TEST_F(Bridge, WithNotifySpinTheTaskThreadsStillMakeOnlyTheReleaseWait) {
    if (!syscall_counter_available()) GTEST_SKIP() << "no raw_syscalls tracepoint: tracefs not mounted (see tests/prof/in_tracefs_namespace.sh)";
    count_task_threads("spin");
}

// NOTIFY spin and poll: the bridge thread of a publisher keeps off the CPU the
// task is pinned to, while another one is left, so that the task never
// preempts its looks; OFF, it may use every CPU again. A bridge that only
// subscribes has nothing to look for and leaves its thread free.
class BridgeLooking : public Bridge, public ::testing::WithParamInterface<const char*> {};

TEST_P(BridgeLooking, ThePublishersThreadKeepsOffTheTasksCpu) {
    cpu_set_t process;
    ASSERT_EQ(sched_getaffinity(0, sizeof process, &process), 0);
    if (!CPU_ISSET(0, &process) || CPU_COUNT(&process) < 2) GTEST_SKIP() << "needs CPU 0 and another one";
    write("t.sbs", "SUBSYSTEM " + name_ + "\nSVARFILE t.svar\nRTPU cpu0 0\nERRPRINT none\nEOF\n");
    const std::string notify = GetParam();
    const std::set<long> before = thread_ids();
    start("warn", "warn", notify);
    std::vector<long> bridges;
    for (const long tid : thread_ids()) {
        std::ifstream comm("/proc/self/task/" + std::to_string(tid) + "/comm");
        std::string name;
        std::getline(comm, name);
        if (!before.count(tid) && name == "ddsbridge") bridges.push_back(tid);
    }
    ASSERT_EQ(bridges.size(), 2u) << "one per bridge (pub and sub)";
    auto uses_cpu0 = [](long tid) {
        cpu_set_t cpus;
        return sched_getaffinity(static_cast<pid_t>(tid), sizeof cpus, &cpus) == 0 && CPU_ISSET(0, &cpus);
    };
    auto off_cpu0 = [&] {
        int n = 0;
        for (const long tid : bridges) n += uses_cpu0(tid) ? 0 : 1;
        return n;
    };
    // The publisher's bridge keeps off; the subscriber's does not.
    EXPECT_TRUE(eventually([&] { return off_cpu0() == 1; })) << off_cpu0() << " bridge threads off CPU 0";
    std::this_thread::sleep_for(50ms);
    EXPECT_EQ(off_cpu0(), 1) << "a bridge that only subscribes leaves its thread on every CPU";
    sbs_->control(pub_, Control::off);
    sbs_->control(sub_, Control::off);
    for (const long tid : bridges) EXPECT_TRUE(eventually([&] { return uses_cpu0(tid); })) << "thread " << tid << " OFF";
}
INSTANTIATE_TEST_SUITE_P(PollAndSpin, BridgeLooking, ::testing::Values("poll", "spin"));

// Joint data by name (issue #29.7) and the consumer's torque-rate limit (issue
// #29.6), end to end: a subscribing bridge of E (JointState.effort, joints
// joint1 .. joint6 by default), and an independent writer — Cyclone's API and
// the IDL types only, no line of the bridge, a participant of its own — that
// sends what a ROS 2 node might: names in another order, a subset, a name the
// port does not have, no names. Each sample is sent once, after the previous
// one has been counted (a reliable keep-last-1 reader would otherwise merge
// them), so the counts are exact.
namespace {

// A participant of its own (a DDS writer GUID of its own) and one reliable writer.
class Writer {
public:
    Writer(int domain, const std::string& topic, const dds_topic_descriptor_t* type) {
        participant_ = dds_create_participant(static_cast<dds_domainid_t>(domain), nullptr, nullptr);
        const dds_entity_t t = dds_create_topic(participant_, type, topic.c_str(), nullptr, nullptr);
        dds_qos_t* q = dds_create_qos();
        dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_SECS(1));
        writer_ = dds_create_writer(participant_, t, q, nullptr);
        dds_delete_qos(q);
    }
    ~Writer() { dds_delete(participant_); }
    Writer(const Writer&) = delete;
    Writer& operator=(const Writer&) = delete;
    bool ok() const { return participant_ > 0 && writer_ > 0; }
    bool matched() const {
        dds_publication_matched_status_t st{};
        return dds_get_publication_matched_status(writer_, &st) == DDS_RETCODE_OK && st.current_count > 0;
    }
    // Until every sample written is in the bridge's reader (and so through its
    // listener, which Cyclone calls on delivery, before the reader acknowledges).
    bool delivered() const { return dds_wait_for_acks(writer_, DDS_SECS(10)) == DDS_RETCODE_OK; }

protected:
    static void set_stamp(std_msgs_msg_dds__Header_& h, std::int64_t ns) {
        h.stamp.sec = static_cast<int32_t>(ns / 1'000'000'000);
        h.stamp.nanosec = static_cast<uint32_t>(ns % 1'000'000'000);
    }
    dds_entity_t participant_ = 0, writer_ = 0;
};

// JointStates with the efforts, stamped `stamp_ns` (header.stamp; 0 unless given).
class JointWriter : public Writer {
public:
    JointWriter(int domain, const std::string& topic) : Writer(domain, topic, &sensor_msgs_msg_dds__JointState__desc) {}
    void send(const std::vector<std::string>& names, std::vector<double> efforts, std::int64_t stamp_ns = 0) {
        std::vector<char*> n;
        for (const std::string& name : names) n.push_back(const_cast<char*>(name.c_str()));
        char empty[] = "";
        sensor_msgs_msg_dds__JointState_ s{};
        s.header.frame_id = empty;
        set_stamp(s.header, stamp_ns);
        s.name = {static_cast<uint32_t>(n.size()), static_cast<uint32_t>(n.size()), n.data(), false};
        s.effort = {static_cast<uint32_t>(efforts.size()), static_cast<uint32_t>(efforts.size()), efforts.data(), false};
        ASSERT_EQ(dds_write(writer_, &s), DDS_RETCODE_OK);
    }
};

// chimera_msgs/StateVar samples, as another machine's bridge sends them.
class StateWriter : public Writer {
public:
    StateWriter(int domain, const std::string& topic) : Writer(domain, topic, &chimera_msgs_msg_dds__StateVar__desc) {}
    void send(std::uint64_t counter, std::int64_t stamp_ns, std::vector<double> data) {
        char frame[] = "T";
        chimera_msgs_msg_dds__StateVar_ s{};
        s.header.frame_id = frame;
        set_stamp(s.header, stamp_ns);
        s.counter = counter;
        s.data = {static_cast<uint32_t>(data.size()), static_cast<uint32_t>(data.size()), data.data(), false};
        ASSERT_EQ(dds_write(writer_, &s), DDS_RETCODE_OK);
    }
};

const std::vector<std::string> kAllJoints{"joint1", "joint2", "joint3", "joint4", "joint5", "joint6"};

}  // namespace

class BridgeByName : public Bridge {
protected:
    // A bridge subscribing E from an independent writer; `local`: more LOCAL keys.
    void start_by_name(const std::string& local) {
        sbs_ = Subsystem::init((dir_ / "t.sbs").string());
        global_ = std::make_unique<chimera::svar::Table>(
            chimera::svar::Table::attach(chimera::ipc::segment_name(name_, "svar")));
        sub_ = sbs_->spawn(bridge_rmod("byname", "INVAR none\nOUTVAR E\n",
                                       local + "TOPIC_E " + topic_ + "/torques sub JointState.effort command 30 warn\n"),
                           "cpu0");
        sbs_->control(sub_, Control::on);
        writer_ = std::make_unique<JointWriter>(domain_, "rt/" + topic_ + "/torques");
        ASSERT_TRUE(writer_->ok());
        ASSERT_TRUE(eventually([&] { return writer_->matched(); })) << "the writer never matched the bridge";
        // Until the reader has matched the writer too, a sample may be lost:
        // an all-zero torque, sent until one is counted, opens the link; once
        // every one sent is delivered, what they added to the counts is the
        // baseline of the test.
        ASSERT_TRUE(eventually([&] {
            writer_->send(kAllJoints, {0, 0, 0, 0, 0, 0});
            return count("received") > 0;
        }));
        ASSERT_TRUE(writer_->delivered());
        (void)sbs_->status(sub_);  // hands over any warning so far
    }
    long count(const std::string& key) { return status_count(sbs_->get(sub_, "STATUS"), "E", key); }
    // Sends one sample and waits until the bridge has counted it under `key`.
    void send(const std::vector<std::string>& names, const std::vector<double>& efforts, const std::string& key,
              std::int64_t stamp_ns = 0) {
        const long before = count(key);
        writer_->send(names, efforts, stamp_ns);
        ASSERT_TRUE(eventually([&] { return count(key) == before + 1; }))
            << "not counted as " << key << ": " << sbs_->get(sub_, "STATUS");
    }
    // The next warning of the task, as the cycle handed it on.
    std::string next_warning() {
        std::string w;
        (void)eventually([&] { return !(w = sbs_->status(sub_).warning).empty(); });
        return w;
    }
    std::unique_ptr<JointWriter> writer_;
};

TEST_F(BridgeByName, ReversedNamesSubsetsUnknownNamesAndNoNamesFromAnIndependentWriter) {
    start_by_name("");  // the defaults: joint1 .. joint6, JOINT_SUBSET update, UNNAMED refuse
    const long received = count("received");
    send({"joint6", "joint5", "joint4", "joint3", "joint2", "joint1"}, {6, 5, 4, 3, 2, 1}, "received");
    EXPECT_TRUE(eventually([&] { return get<6>("E") == std::array<double, 6>{1, 2, 3, 4, 5, 6}; }))
        << "joint 1 takes the torque named joint1: " << get<6>("E")[0];

    send({"joint2", "joint5"}, {20, 50}, "received");
    EXPECT_TRUE(eventually([&] { return get<6>("E") == std::array<double, 6>{1, 20, 3, 4, 50, 6}; }))
        << "a subset updates the joints it names, the others keep theirs";

    send({"joint1", "joint7"}, {10, 70}, "unknown");
    const std::string unknown = next_warning();
    EXPECT_EQ(unknown.rfind("E refused a sample: unknown joint 'joint7' (1 unknown so far), publisher ", 0), 0u)
        << unknown;
    EXPECT_NE(unknown.find(", topic rt/" + topic_ + "/torques"), std::string::npos) << unknown;

    send({}, {9, 9, 9, 9, 9, 9}, "unnamed");
    const std::string unnamed = next_warning();
    EXPECT_EQ(unnamed.rfind("E refused a sample: no joint names (UNNAMED refuse) (1 unnamed so far), publisher ", 0), 0u)
        << unnamed;

    std::this_thread::sleep_for(50ms);  // cycles after the refusals
    EXPECT_EQ(get<6>("E"), (std::array<double, 6>{1, 20, 3, 4, 50, 6})) << "nothing of a refused sample reached E";
    EXPECT_EQ(count("received"), received + 2);
    EXPECT_EQ(count("rejected"), 2);
    EXPECT_EQ(count("unknown"), 1);
    EXPECT_EQ(count("unnamed"), 1);
    EXPECT_EQ(count("partial"), 0);
    EXPECT_EQ(count("length"), 0);
    EXPECT_EQ(count("held"), 0);
    EXPECT_EQ(sbs_->status(sub_).state, State::ON) << "bad samples never stop the task";
}

TEST_F(BridgeByName, WhenTheRmodRequiresEveryJointASubsetIsRefusedAndUnnamedIsTakenByPosition) {
    start_by_name("JOINT_SUBSET refuse\nUNNAMED positional\n");
    send({"joint6", "joint5", "joint4", "joint3", "joint2", "joint1"}, {6, 5, 4, 3, 2, 1}, "received");
    EXPECT_TRUE(eventually([&] { return get<6>("E") == std::array<double, 6>{1, 2, 3, 4, 5, 6}; }));

    send({"joint2", "joint5"}, {20, 50}, "partial");
    const std::string partial = next_warning();
    EXPECT_EQ(partial.rfind("E refused a sample: 2 of 6 joints named (JOINT_SUBSET refuse) (1 partial so far)", 0), 0u)
        << partial;
    std::this_thread::sleep_for(50ms);
    EXPECT_EQ(get<6>("E"), (std::array<double, 6>{1, 2, 3, 4, 5, 6})) << "the refused subset changed nothing";

    send({}, {7, 8, 9, 10, 11, 12}, "received");
    EXPECT_TRUE(eventually([&] { return get<6>("E") == std::array<double, 6>{7, 8, 9, 10, 11, 12}; }))
        << "UNNAMED positional: value j is joint j";
    EXPECT_EQ(count("rejected"), 1);
    EXPECT_EQ(count("partial"), 1);
}

// TRATE_E 100 N m/s at 200 Hz: a step of 0.5 N m per cycle. A torque of 10 on
// joint 1 from the zero after on() is reached in 20 cycles, 19 of them clamped;
// the table never sees a value outside the ramp.
TEST_F(BridgeByName, ATorqueRateLimitRampsWhatTheBridgeWritesAndCountsTheClampedValues) {
    start_by_name("TRATE_E 100\n");
    ASSERT_EQ(count("clamped"), 0) << "the all-zero sample needs no ramp";
    send({"joint1"}, {10}, "received");
    std::vector<double> seen;
    ASSERT_TRUE(eventually([&] {
        seen.push_back(get<6>("E")[0]);
        return seen.back() == 10.0;
    }, 10000ms)) << "the ramp never reached 10";
    for (std::size_t i = 1; i < seen.size(); ++i) EXPECT_LE(seen[i - 1], seen[i]) << "the ramp only rises";
    for (const double v : seen) EXPECT_EQ(v, 0.5 * static_cast<int>(v / 0.5)) << "a whole number of steps: " << v;
    EXPECT_EQ(count("clamped"), 19);
    EXPECT_EQ(get<6>("E"), (std::array<double, 6>{10, 0, 0, 0, 0, 0}));
}

// A reordered sample (issue #29, "safe in operation"): one older than the
// newest the port took — by the network, or an old command replayed — is
// refused whole, counted and told; the port keeps the newer value. A
// JointState is compared by header.stamp (equal stamps are taken); a
// StateVar by counter from the writer of the newest, by stamp from another
// (a writer restarted from counter 0 is taken). The writers are independent:
// Cyclone's API and the IDL types only.
namespace {

constexpr std::int64_t kEpoch = 1'700'000'000'000'000'000;  // ns: 1700000000.000000000, ROS time

}  // namespace

TEST_F(BridgeByName, AJointStateOlderThanTheNewestTakenIsRefusedAndEqualStampsAreTaken) {
    start_by_name("");  // its baseline: zero torques stamped 0
    const long received = count("received");
    send(kAllJoints, {1, 2, 3, 4, 5, 6}, "received", kEpoch + 300);
    send(kAllJoints, {9, 9, 9, 9, 9, 9}, "reordered", kEpoch + 200);
    const std::string reordered = next_warning();
    EXPECT_EQ(reordered.rfind("E refused a sample: stamp 1700000000.000000200 older than 1700000000.000000300 "
                              "(1 reordered so far), topic rt/" + topic_ + "/torques",
                              0),
              0u)
        << reordered;
    std::this_thread::sleep_for(50ms);  // cycles after the refusal
    EXPECT_EQ(get<6>("E"), (std::array<double, 6>{1, 2, 3, 4, 5, 6})) << "the older sample reached E";

    send({"joint1"}, {10}, "received", kEpoch + 300);  // equal: taken (a publisher's joints split over messages)
    EXPECT_TRUE(eventually([&] { return get<6>("E") == std::array<double, 6>{10, 2, 3, 4, 5, 6}; }));
    EXPECT_EQ(count("received"), received + 2);
    EXPECT_EQ(count("rejected"), 1);
    EXPECT_EQ(count("reordered"), 1);
    EXPECT_EQ(sbs_->status(sub_).state, State::ON);
}

class BridgeOrder : public BridgeByName {
protected:
    // A bridge subscribing T (StateVar) only, and `writer` opened onto it.
    void start_state(std::unique_ptr<StateWriter>& writer) {
        sbs_ = Subsystem::init((dir_ / "t.sbs").string());
        global_ = std::make_unique<chimera::svar::Table>(
            chimera::svar::Table::attach(chimera::ipc::segment_name(name_, "svar")));
        sub_ = sbs_->spawn(bridge_rmod("order", "INVAR none\nOUTVAR T\n",
                                       "TOPIC_T " + topic_ + "/array sub StateVar command 30 warn\n"),
                           "cpu0");
        sbs_->control(sub_, Control::on);
        open_writer(writer, 0, kEpoch, {0, 0, 0});
    }
    // A new writer (a participant of its own: another GUID) whose first
    // sample, sent until one is counted, is `counter`, `stamp`, `value`.
    void open_writer(std::unique_ptr<StateWriter>& writer, std::uint64_t counter, std::int64_t stamp,
              const std::vector<double>& value) {
        writer = std::make_unique<StateWriter>(domain_, "rt/" + topic_ + "/array");
        ASSERT_TRUE(writer->ok());
        ASSERT_TRUE(eventually([&] { return writer->matched(); })) << "the writer never matched the bridge";
        const long before = state("received");
        ASSERT_TRUE(eventually([&] {
            writer->send(counter, stamp, value);
            return state("received") > before;
        }));
        ASSERT_TRUE(writer->delivered());
        (void)sbs_->status(sub_);  // hands over any warning so far
    }
    long state(const std::string& key) { return status_count(sbs_->get(sub_, "STATUS"), "T", key); }
    void send(StateWriter& w, std::uint64_t counter, std::int64_t stamp, const std::vector<double>& value,
              const std::string& key) {
        const long before = state(key);
        w.send(counter, stamp, value);
        ASSERT_TRUE(eventually([&] { return state(key) == before + 1; }))
            << "not counted as " << key << ": " << sbs_->get(sub_, "STATUS");
    }
};

TEST_F(BridgeOrder, AStateVarIsComparedByCounterFromItsWriterAndByStampFromARestartedOrForeignOne) {
    std::unique_ptr<StateWriter> a, b, c;
    start_state(a);  // a's counter 0, stamped kEpoch
    send(*a, 5, kEpoch + 300, {5, 5, 5}, "received");
    // A newer stamp, an older counter of the same writer: refused by counter.
    send(*a, 4, kEpoch + 400, {4, 4, 4}, "reordered");
    const std::string reordered = next_warning();
    EXPECT_EQ(reordered.rfind("T refused a sample: counter 4 older than 5 (stamps 1700000000.000000400, "
                              "1700000000.000000300) (1 reordered so far), topic rt/" + topic_ + "/array",
                              0),
              0u)
        << reordered;
    std::this_thread::sleep_for(50ms);
    EXPECT_EQ(get<3>("T"), (std::array<double, 3>{5, 5, 5})) << "the older sample reached T";

    a.reset();  // the sender restarts: another writer, from counter 0, with newer stamps
    open_writer(b, 0, kEpoch + 500, {6, 6, 6});
    EXPECT_TRUE(eventually([&] { return get<3>("T") == std::array<double, 3>{6, 6, 6}; }));
    open_writer(c, 0, kEpoch + 500, {6, 6, 6});  // another writer, the same stamp as b's newest: taken
    send(*b, 1, kEpoch + 600, {7, 7, 7}, "received");  // newer by stamp than c's
    // c replaying an old command: a higher counter than c's, an older stamp than b's newest.
    send(*c, 99, kEpoch + 450, {9, 9, 9}, "reordered");
    std::this_thread::sleep_for(50ms);
    EXPECT_EQ(get<3>("T"), (std::array<double, 3>{7, 7, 7})) << "the replayed sample reached T";
    EXPECT_EQ(state("rejected"), 2);
    EXPECT_EQ(state("reordered"), 2);
    EXPECT_EQ(state("length"), 0);
}
