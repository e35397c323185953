// Named objects across processes (fork + exec of xm_helper): the XM server
// as name server, SHM, SEM, MSG, raw express mail between processes.
#include "sanitizer.hpp"
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
#include <tuple>
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
    CHIMERA_NOT_UNDER_TSAN("helper processes");
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
    CHIMERA_NOT_UNDER_TSAN("helper processes");
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
    CHIMERA_NOT_UNDER_TSAN("helper processes");
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
    CHIMERA_NOT_UNDER_TSAN("helper processes");
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
    CHIMERA_NOT_UNDER_TSAN("helper processes");
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
    CHIMERA_NOT_UNDER_TSAN("helper processes");
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

// --- memory another process writes is bounded before use (issue #15.3) ------------

namespace {

// A second mapping of a named object's segment, as any process that may
// write it has: the corrupting side.
ipc::Segment raw_mapping(xm::Rtpu& self, const std::string& object, ipc::ObjectType type, std::uint32_t version) {
    return ipc::Segment::attach(self.attach_object(object, type).segment, {type, version});
}

}  // namespace

// Every link, index and size of a live queue, corrupted: the operation that
// would follow it refuses (Status::corrupt) before changing anything, its
// fault names the segment and the field, and with the field restored the
// queue is whole (check()) and works on.
TEST(Msg, CorruptLinksAndSizesAreRefusedNamingTheSegment) {
    const std::string sys = test_sys("msgbad");
    xm::Rtpu host(sys, "host", 0);
    msg::Params p;
    p.blknum = 4;
    p.blksize = 16;
    p.policy = msg::Policy::hpf;
    msg::Queue q = msg::Queue::create(host, "host:q", p);
    ipc::Segment raw = raw_mapping(host, "host:q", ipc::ObjectType::xmail_msg, msg::layout::kQueueVersion);
    const std::string seg = raw.name();
    auto* h = static_cast<msg::layout::QueueHeader*>(raw.base());
    auto head = [&](std::uint32_t off) {
        return reinterpret_cast<msg::layout::MsgHead*>(static_cast<std::byte*>(raw.base()) + off);
    };
    auto block = [&](std::uint32_t off) {
        return reinterpret_cast<msg::layout::MsgBHead*>(static_cast<std::byte*>(raw.base()) + off);
    };
    char buf[64];
    const std::string two_blocks(20, 'm');  // 20 bytes: two 16-byte blocks
    auto refused = [&](Status s, const char* field) {
        EXPECT_EQ(s, Status::corrupt) << field;
        EXPECT_NE(q.fault_message().find("segment " + seg + ": " + field), std::string::npos)
            << q.fault_message();
    };
    struct Case {
        const char* field;
        bool by_send;                          // else by receive (one message queued first)
        std::function<std::uint32_t&()> word;  // the field
        std::uint32_t bad;
    };
    const std::uint32_t outside = static_cast<std::uint32_t>(raw.size()) + 64;
    const Case cases[] = {
        {"headfree", true, [&]() -> std::uint32_t& { return h->headfree; }, outside},
        {"headfree", true, [&]() -> std::uint32_t& { return h->headfree; }, h->off_heads + 3},  // mid-header
        {"headfree link", true, [&]() -> std::uint32_t& { return head(h->headfree)->link; }, 8},
        {"blkfree", true, [&]() -> std::uint32_t& { return h->blkfree; }, h->off_heads},  // a header, not a block
        {"blkfree link", true, [&]() -> std::uint32_t& { return block(h->blkfree)->link; }, outside},
        {"headused", false, [&]() -> std::uint32_t& { return h->headused; }, outside},
        {"headused link", false, [&]() -> std::uint32_t& { return head(h->headused)->link; }, 12},
        {"message block link", false, [&]() -> std::uint32_t& { return head(h->headused)->blk; }, outside},
        {"message block link", false, [&]() -> std::uint32_t& { return block(head(h->headused)->blk)->link; }, 0},
        {"message block count", false, [&]() -> std::uint32_t& { return head(h->headused)->nblk; }, 1000},
        {"message size", false, [&]() -> std::uint32_t& { return head(h->headused)->size; }, 33},
    };
    for (const Case& c : cases) {
        if (!c.by_send) {
            ASSERT_EQ(q.send(two_blocks.data(), two_blocks.size(), 7, 1, 0), Status::ok);
        }
        std::uint32_t& f = c.word();
        const std::uint32_t good = f;
        f = c.bad;
        if (c.by_send)
            refused(q.send(two_blocks.data(), two_blocks.size(), 7, 1, 0), c.field);
        else
            refused(q.receive(buf, sizeof buf, nullptr, 0), c.field);
        f = good;
        EXPECT_EQ(q.check(), "") << c.field << ": nothing was changed by the refusal";
        if (!c.by_send) {
            ASSERT_EQ(q.receive(buf, sizeof buf, nullptr, 0), Status::ok) << c.field;
        }
    }
    // A HPF insertion walks headused: a bad link on the way is refused too.
    ASSERT_EQ(q.send("a", 1, 0, 5, 0), Status::ok);
    ASSERT_EQ(q.send("b", 1, 0, 3, 0), Status::ok);
    std::uint32_t& link = head(h->headused)->link;
    const std::uint32_t good = link;
    link = outside;
    refused(q.send("c", 1, 0, 1, 0), "headused link");
    link = good;
    EXPECT_EQ(q.check(), "");
    // The fixed part is checked on attach.
    const std::uint32_t stride = h->block_stride;
    h->block_stride = 4096;
    const std::string e = error_of([&] { msg::Queue::attach(host, "host:q"); });
    EXPECT_TRUE(contains(e, "segment " + seg + ": block stride")) << e;
    h->block_stride = stride;
    EXPECT_EQ(error_of([&] { msg::Queue::attach(host, "host:q"); }), "<no error>");
    EXPECT_FALSE(msg::validate(raw.base(), raw.size()));
    raw.detach();
}

TEST(Shm, ACorruptUsableAreaOrNameIsRefusedOnAttach) {
    const std::string sys = test_sys("shmbad");
    xm::Rtpu host(sys, "host", 0);
    shm::Segment s = shm::Segment::create(host, "host:m", 100);
    ipc::Segment raw = raw_mapping(host, "host:m", ipc::ObjectType::xmail_shm, shm::layout::kShmVersion);
    auto* h = static_cast<shm::layout::ShmHeader*>(raw.base());
    const std::uint64_t offset = h->data_offset, size = h->size;
    for (auto [field, bad_offset, bad_size] :
         {std::tuple{"usable size", offset, std::uint64_t{1} << 40}, std::tuple{"data offset", std::uint64_t{8}, size},
          std::tuple{"data offset", std::uint64_t{1} << 40, size}, std::tuple{"usable size", offset, std::uint64_t{0}}}) {
        h->data_offset = bad_offset;
        h->size = bad_size;
        const std::string e = error_of([&] { shm::Segment::attach(host, "host:m"); });
        EXPECT_TRUE(contains(e, "segment " + raw.name() + ": " + field)) << e;
        EXPECT_TRUE(shm::validate(raw.base(), raw.size()));
    }
    h->data_offset = offset;
    h->size = size;
    std::memset(h->name, 'x', sizeof h->name);
    EXPECT_TRUE(contains(error_of([&] { shm::Segment::attach(host, "host:m"); }), ": name length"));
    h->name[5] = '\0';
    EXPECT_EQ(error_of([&] { shm::Segment::attach(host, "host:m"); }), "<no error>");
    EXPECT_EQ(s.size(), 100u);  // the mapping kept what it checked
    raw.detach();
}

// Found by fuzz/fuzz_sem: a segment whose header claims the short size it
// has passed the segment checks, and the semaphore's fields were read past
// its end. (fuzz/corpus/sem/short-segment holds the fuzzer's input.)
TEST(Sem, ASegmentTooShortForASemaphoreIsRefused) {
    alignas(64) std::byte memory[sem::Semaphore::memory_size()];
    sem::Semaphore s = sem::Semaphore::over(memory, sem::Kind::binary, 1);
    auto* h = reinterpret_cast<sem::layout::SemHeader*>(memory);
    const std::size_t short_size = sizeof(ipc::SegmentHeader) + 8;
    h->segment.total_size = short_size;
    const ipc::Fault f = sem::validate(memory, short_size);
    ASSERT_TRUE(f);
    EXPECT_STREQ(f.field, "segment size");
    EXPECT_EQ(f.limit, sem::Semaphore::memory_size());
    EXPECT_THROW(sem::Semaphore::bind(memory), xm::Error);  // bind reads the whole header: its own size
}

TEST(Sem, ACorruptKindOrNameIsRefusedOnAttach) {
    const std::string sys = test_sys("sembad");
    xm::Rtpu host(sys, "host", 0);
    sem::Semaphore s = sem::Semaphore::create(host, "host:s", sem::Kind::binary, 1);
    ipc::Segment raw = raw_mapping(host, "host:s", ipc::ObjectType::xmail_sem, sem::layout::kSemVersion);
    auto* h = static_cast<sem::layout::SemHeader*>(raw.base());
    h->kind = 7;
    EXPECT_TRUE(contains(error_of([&] { sem::Semaphore::attach(host, "host:s"); }),
                         "segment " + raw.name() + ": kind is 7"));
    h->kind = 0;
    std::memset(h->name, 'x', sizeof h->name);
    EXPECT_TRUE(contains(error_of([&] { sem::Semaphore::attach(host, "host:s"); }), ": name length"));
    h->name[3] = '\0';
    h->value = -4;  // not an offset: P and V keep it in range (the validator names it)
    EXPECT_TRUE(contains(ipc::describe(raw.name(), sem::validate(raw.base(), raw.size())), "value"));
    h->value = 1;
    EXPECT_FALSE(sem::validate(raw.base(), raw.size()));
    EXPECT_EQ(s.try_p(), Status::ok);
    raw.detach();
}
