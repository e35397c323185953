// Named objects across processes (fork + exec of xm_helper): the XM server
// as name server, SHM, SEM, MSG, raw express mail between processes.
#include "segment_guard.hpp"
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cstring>
#include <functional>
#include <chrono>
#include <map>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "chimera/msg.hpp"
#include "chimera/sem.hpp"
#include "chimera/shm.hpp"
#include "chimera/xmail.hpp"
#include "common.hpp"

using namespace chimera;
using xm::Status;

namespace {

std::string error_of(const std::function<void()>& f) {
    try {
        f();
    } catch (const xm::Error& e) {
        return e.what();
    }
    return "<no error>";
}

bool contains(const std::string& s, const std::string& part) {
    return s.find(part) != std::string::npos;
}

// A helper process whose stdout we read line by line.
template <typename F>
bool eventually(F&& f, int ms = 5000) {
    for (int i = 0; i < ms; ++i) {
        if (f()) return true;
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    return false;
}

}  // namespace

TEST(NameServer, ClearErrorsForBadNamesTypesAndRtpus) {
    const std::string sys = test_sys("ns");
    xm::Rtpu host(sys, "host", 0);
    host.set_request_timeout(1'000'000'000);
    EXPECT_TRUE(contains(error_of([&] { host.attach_object("host:nothing", ipc::ObjectType::xmail_sem); }),
                         "no such object")) ;
    EXPECT_TRUE(contains(error_of([&] { host.attach_object("ghost:x", ipc::ObjectType::xmail_sem); }),
                         "no such RTPU"));
    EXPECT_TRUE(contains(error_of([&] { xm::split_name("nocolon"); }), "rtpu:name"));
    EXPECT_TRUE(contains(error_of([&] { xm::split_name("a:b/c"); }), "none of"));
    auto s = sem::Semaphore::create(host, "host:s", sem::Kind::binary, 1);
    EXPECT_TRUE(contains(error_of([&] { msg::Queue::attach(host, "host:s"); }),
                         "'host:s' is a xmail_sem, not a xmail_msg"));
    EXPECT_TRUE(contains(error_of([&] { sem::Semaphore::create(host, "host:s", sem::Kind::binary, 0); }),
                         "already exists"));
    EXPECT_TRUE(contains(error_of([&] { shm::Segment::create(host, "host:zero", 0); }), "size 0"));
    EXPECT_TRUE(contains(error_of([&] { sem::Semaphore::create(host, "host:b2", sem::Kind::binary, 2); }),
                         "initial value 2"));
    s.destroy(host);
    EXPECT_TRUE(contains(error_of([&] { sem::Semaphore::attach(host, "host:s"); }), "no such object"));
}

// A segment written by a build with another layout is refused by name, for
// every kind of named object and for a peer's mailbox, before anything in it
// is used.
TEST(NameServer, LayoutVersionMismatchNamesTheObject) {
    const std::string sys = test_sys("ver");
    xm::Rtpu host(sys, "host", 0);
    xm::Rtpu other(sys, "other", 1);
    xm::Mailbox fresh(sys, "fresh", 2);  // has not attached to host's mailbox yet
    auto s = sem::Semaphore::create(host, "host:s", sem::Kind::counting, 0);
    auto q = msg::Queue::create(host, "host:q", msg::Params{});
    auto m = shm::Segment::create(host, "host:m", 64);
    struct Case {
        std::string object, segment;
        ipc::ObjectType type;
        std::uint32_t version;
        std::function<void()> attach;
        std::string named;
    };
    const std::vector<Case> cases{
        {"host:s", host.attach_object("host:s", ipc::ObjectType::xmail_sem).segment, ipc::ObjectType::xmail_sem,
         sem::layout::kSemVersion, [&] { sem::Semaphore::attach(other, "host:s"); }, "semaphore 'host:s'"},
        {"host:q", host.attach_object("host:q", ipc::ObjectType::xmail_msg).segment, ipc::ObjectType::xmail_msg,
         msg::layout::kQueueVersion, [&] { msg::Queue::attach(other, "host:q"); }, "message queue 'host:q'"},
        {"host:m", host.attach_object("host:m", ipc::ObjectType::xmail_shm).segment, ipc::ObjectType::xmail_shm,
         shm::layout::kShmVersion, [&] { shm::Segment::attach(other, "host:m"); }, "shared segment 'host:m'"},
        {"host", xm::Mailbox::segment_name(sys, "host"), ipc::ObjectType::xmail_mailbox,
         xm::layout::kMailboxVersion, [&] { fresh.peer("host"); }, "RTPU 'host'"},
    };
    for (const Case& c : cases) {
        ipc::Segment raw = ipc::Segment::attach(c.segment, {c.type, c.version});
        raw.header().layout_version = c.version + 1;
        const std::string e = error_of(c.attach);
        EXPECT_TRUE(contains(e, c.named)) << c.object << ": " << e;
        EXPECT_TRUE(contains(e, "layout version " + std::to_string(c.version + 1))) << c.object << ": " << e;
        raw.header().layout_version = c.version;  // and with the right one it works again
        EXPECT_EQ(error_of(c.attach), "<no error>") << c.object;
        raw.detach();
    }
}

TEST(Shm, CreateAttachAcrossProcessesAndLastUserFrees) {
    const std::string sys = test_sys("shm");
    xm::Rtpu host(sys, "host", 0);
    shm::Segment seg = shm::Segment::create(host, "host:buf", 4096);
    ASSERT_EQ(seg.size(), 4096u);
    std::strcpy(static_cast<char*>(seg.data()), "hello");
    auto [rc, out] = run_helper({"shm-rw", sys, "p1", "1", "host:buf", "hello", "world"});
    EXPECT_EQ(rc, 0);
    EXPECT_EQ(out, "ok 4096\n");
    EXPECT_STREQ(static_cast<char*>(seg.data()), "world");
    EXPECT_EQ(seg.users(), 1u);  // the helper detached
    const std::string segname = host.attach_object("host:buf", ipc::ObjectType::xmail_shm).segment;
    EXPECT_TRUE(ipc::Segment::exists(segname));
    EXPECT_TRUE(seg.detach());  // last user: freed
    EXPECT_FALSE(ipc::Segment::exists(segname));
    EXPECT_TRUE(contains(error_of([&] { shm::Segment::attach(host, "host:buf"); }), "no such object"));
}

TEST(Shm, ObjectsLiveOnTheNamedRtpuAndItsServerResolvesThem) {
    const std::string sys = test_sys("remote");
    const chimera::test::SegmentGuard cleanup("chimera." + sys + ".");  // killed users' segments too
    xm::Rtpu host(sys, "host", 0);
    Child r1({"serve", sys, "r1", "1"});
    ASSERT_EQ(r1.line(), "ready");
    // p2 creates "r1:seg": the request goes to r1's XM server.
    auto [rc, out] = run_helper({"shm-create", sys, "p2", "2", "r1:seg", "1000"});
    EXPECT_EQ(rc, 0) << out;
    // It is unknown on host, known on r1.
    EXPECT_TRUE(contains(error_of([&] { shm::Segment::attach(host, "host:seg"); }), "no such object"));
    // p2 detached as the last user: the segment was freed and r1 forgot the name.
    EXPECT_TRUE(contains(error_of([&] { shm::Segment::attach(host, "r1:seg"); }),
                         "no such object on RTPU 'r1'"));
    shm::Segment s = shm::Segment::create(host, "r1:seg2", 64);
    std::strcpy(static_cast<char*>(s.data()), "abc");
    auto [rc2, out2] = run_helper({"shm-rw", sys, "p2", "2", "r1:seg2", "abc", "xyz"});
    EXPECT_EQ(out2, "ok 64\n");
    EXPECT_STREQ(static_cast<char*>(s.data()), "xyz");
    EXPECT_TRUE(contains(host.attach_object("r1:seg2", ipc::ObjectType::xmail_shm).segment, ".obj.r1.seg2"));
    // The owner dies: its names can no longer be resolved, with a clear error.
    kill(r1.pid, SIGKILL);
    r1.wait();
    EXPECT_TRUE(contains(error_of([&] { shm::Segment::attach(host, "r1:seg2"); }), "not alive"));
    // Our mapping stays usable.
    EXPECT_STREQ(static_cast<char*>(s.data()), "xyz");
}

TEST(Sem, PAndVAcrossProcessesHighestPriorityFirst) {
    const std::string sys = test_sys("semx");
    xm::Rtpu host(sys, "host", 0);
    sem::Semaphore s = sem::Semaphore::create(host, "host:go", sem::Kind::counting, 0);
    std::vector<std::unique_ptr<Child>> kids;
    const int prios[] = {1, 3, 2};
    for (int i = 0; i < 3; ++i) {
        kids.push_back(std::make_unique<Child>(std::vector<std::string>{
            "sem-p", sys, "w" + std::to_string(i), std::to_string(i + 1), "host:go",
            std::to_string(prios[i]), "-1"}));
        ASSERT_TRUE(eventually([&] { return s.waiting() == static_cast<std::uint32_t>(i + 1); }));
    }
    std::vector<std::string> order;
    for (int n = 0; n < 3; ++n) {
        ASSERT_EQ(s.v(), Status::ok);
        // Exactly one waiter wakes per V: find which.
        int woken = -1;
        ASSERT_TRUE(eventually([&] {
            for (int i = 0; i < 3; ++i) {
                if (kids[i]->pid <= 0) continue;
                if (waitpid(kids[i]->pid, nullptr, WNOHANG) == kids[i]->pid) {
                    kids[i]->pid = -1;
                    woken = i;
                    return true;
                }
            }
            return false;
        }));
        order.push_back(kids[woken]->line());
    }
    EXPECT_EQ(order, (std::vector<std::string>{"got 3", "got 2", "got 1"}));
    // Timed P in another process; and V from another process.
    auto [rc, out] = run_helper({"sem-p", sys, "w9", "5", "host:go", "0", "50"});
    EXPECT_EQ(out, "timed out\n");
    auto [rc2, out2] = run_helper({"sem-v", sys, "w9", "5", "host:go", "2"});
    EXPECT_EQ(out2, "ok\n");
    EXPECT_EQ(s.value(), 2);
}

TEST(Msg, HpfAndMultiBlockAcrossProcesses) {
    const std::string sys = test_sys("msgx");
    xm::Rtpu host(sys, "host", 0);
    msg::Params p;
    p.blknum = 16;
    p.blksize = 16;
    p.policy = msg::Policy::hpf;
    msg::Queue q = msg::Queue::create(host, "host:q", p);
    // The helper sends priorities 10, 11, 12 (types 0, 1, 2); HPF returns 12 first.
    const std::string long_text(200, 'L');
    auto [rc, out] = run_helper({"msg-send", sys, "s1", "1", "host:q", "10", "first", "second", long_text});
    ASSERT_EQ(out, "ok\n");
    EXPECT_EQ(q.check(), "");
    EXPECT_EQ(q.stats().free_blocks, 16u - 13u - 1u - 1u);  // 200 bytes: 13 blocks
    std::vector<char> buf(512);
    msg::Info info;
    ASSERT_EQ(q.receive(buf.data(), buf.size(), &info, 0), Status::ok);
    EXPECT_EQ(info.priority, 12);
    EXPECT_EQ(std::string(buf.data(), info.size), long_text);
    ASSERT_EQ(q.receive(buf.data(), buf.size(), &info, 0), Status::ok);
    EXPECT_EQ(std::string(buf.data(), info.size), "second");
    ASSERT_EQ(q.receive(buf.data(), buf.size(), &info, 0), Status::ok);
    EXPECT_EQ(std::string(buf.data(), info.size), "first");
    // Received in another process, sent here.
    ASSERT_EQ(q.send("to child", 8, 4, 1, 0), Status::ok);
    auto [rc2, out2] = run_helper({"msg-recv", sys, "r1", "2", "host:q", "0", "1", "1000"});
    EXPECT_EQ(out2, "1 4 to child\n");
    auto [rc3, out3] = run_helper({"msg-recv", sys, "r1", "2", "host:q", "0", "1", "30"});
    EXPECT_EQ(out3, "timed out\n");
}

TEST(Msg, WaitingReceiversInOtherProcessesServedByPriority) {
    const std::string sys = test_sys("msgw");
    const chimera::test::SegmentGuard cleanup("chimera." + sys + ".");  // killed users' segments too
    xm::Rtpu host(sys, "host", 0);
    msg::Params p;
    p.policy = msg::Policy::fifo;
    msg::Queue q = msg::Queue::create(host, "host:w", p);
    std::vector<std::unique_ptr<Child>> kids;
    const int prios[] = {1, 5, 3};
    for (int i = 0; i < 3; ++i) {
        kids.push_back(std::make_unique<Child>(std::vector<std::string>{
            "msg-recv", sys, "r" + std::to_string(i), std::to_string(i + 1), "host:w",
            std::to_string(prios[i]), "1", "-1"}));
        ASSERT_TRUE(eventually([&] { return q.stats().receive_waiters == static_cast<std::uint32_t>(i + 1); }));
    }
    for (const char* m : {"A", "B", "C"}) ASSERT_EQ(q.send(m, 1, 0, 0, 0), Status::ok);
    std::map<int, std::string> got;
    for (int i = 0; i < 3; ++i) got[prios[i]] = kids[i]->line();
    EXPECT_EQ(got[5], "0 0 A");
    EXPECT_EQ(got[3], "0 0 B");
    EXPECT_EQ(got[1], "0 0 C");
    EXPECT_EQ(q.check(), "");
}

TEST(Mailbox, ExpressMailBetweenProcessesAndDeathDetected) {
    const std::string sys = test_sys("xmx");
    const chimera::test::SegmentGuard cleanup("chimera." + sys + ".");  // killed users' segments too
    xm::Mailbox me(sys, "me", 0);
    Child echo({"xm-echo", sys, "echo", "1"});
    ASSERT_EQ(echo.line(), "ready");
    auto& peer = me.peer("echo");
    for (int i = 0; i < 200; ++i) {
        const std::string m = "me|payload " + std::to_string(i);
        ASSERT_EQ(me.write(peer, m.data(), m.size()), Status::ok);
        char buf[64];
        xm::ReadInfo info;
        Status s;
        while ((s = me.read(buf, sizeof buf, &info)) == Status::would_block) me.wait_interrupts(100'000'000);
        ASSERT_EQ(s, Status::ok);
        EXPECT_EQ(std::string(buf, info.length), "payload " + std::to_string(i));
        EXPECT_EQ(info.from_bid, 1u);
    }
    kill(echo.pid, SIGKILL);
    echo.wait();
    EXPECT_FALSE(me.alive(peer));
    EXPECT_EQ(me.write(peer, "x", 1), Status::not_alive);
}
