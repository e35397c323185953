// Express mail: mailboxes, rings, interrupts, wakeups, alive status (§5.3.1).
#include "sanitizer.hpp"
#include "segment_guard.hpp"
#include <gtest/gtest.h>
#include <pwd.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include "as_user.hpp"
#include "chimera/ipc/clock.hpp"
#include "chimera/xmail.hpp"
#include "common.hpp"

using namespace chimera;
using xm::Mailbox;
using xm::Status;

namespace {

xm::MailboxConfig small(std::uint32_t bufsize = 256) {
    xm::MailboxConfig c;
    c.nrtpu = 4;
    c.ntasks = 8;
    c.bufsize = bufsize;
    c.nmbox = 8;
    return c;
}

}  // namespace

TEST(Mailbox, LayoutFollowsFigure51) {
    const std::string sys = test_sys("layout");
    Mailbox a(sys, "r0", 0, small(1024));
    auto& h = a.header();
    EXPECT_EQ(h.bid, 0u);
    EXPECT_STREQ(h.rtpu, "r0");
    EXPECT_EQ(h.alive.load(), 1u);
    EXPECT_EQ(h.owner_pid.load(), getpid());
    EXPECT_EQ(h.nrtpu, 4u);
    EXPECT_EQ(h.ntasks, 8u);
    EXPECT_EQ(h.nmbox, 8u);
    EXPECT_EQ(h.bufsize, 1024u);
    // header, 8 wakeup words, 8 mbox words, then 4 rings of (128-byte header + 1024).
    EXPECT_EQ(h.off_wakeup, sizeof(xm::layout::MailboxHeader));
    EXPECT_EQ(h.off_mbox, h.off_wakeup + 8 * 4);
    EXPECT_EQ(h.ring_stride, 128u + 1024u);
    EXPECT_EQ(xm::layout::mailbox_size(small(1024)), h.off_rings + 4 * h.ring_stride);
}

TEST(Mailbox, WriteThenReadInOrderWithSender) {
    const std::string sys = test_sys("order");
    Mailbox a(sys, "a", 1, small()), b(sys, "b", 2, small());
    auto& to_b = a.peer("b");
    for (int i = 0; i < 5; ++i) {
        const std::string m = "message " + std::to_string(i);
        ASSERT_EQ(a.write(to_b, m.data(), m.size()), Status::ok);
    }
    char buf[64];
    xm::ReadInfo info;
    for (int i = 0; i < 5; ++i) {
        ASSERT_EQ(b.read(buf, sizeof buf, &info), Status::ok);
        EXPECT_EQ(std::string(buf, info.length), "message " + std::to_string(i));
        EXPECT_EQ(info.from_bid, 1u);
    }
    EXPECT_EQ(b.read(buf, sizeof buf, &info), Status::would_block);
}

TEST(Mailbox, RingWrapsWithoutCorruption) {
    const std::string sys = test_sys("wrap");
    Mailbox a(sys, "a", 0, small(128)), b(sys, "b", 1, small(128));
    auto& to_b = a.peer("b");
    std::vector<unsigned char> msg(100), got(128);
    for (int round = 0; round < 500; ++round) {
        const std::size_t len = 1 + static_cast<std::size_t>(round * 37 % 100);
        for (std::size_t i = 0; i < len; ++i) msg[i] = static_cast<unsigned char>(round + i);
        ASSERT_EQ(a.write(to_b, msg.data(), len, 0), Status::ok) << round;
        xm::ReadInfo info;
        ASSERT_EQ(b.read(got.data(), got.size(), &info), Status::ok);
        ASSERT_EQ(info.length, len);
        ASSERT_EQ(std::memcmp(got.data(), msg.data(), len), 0) << "round " << round;
    }
}

TEST(Mailbox, FullBufferFailsAfterBoundInsteadOfHanging) {
    const std::string sys = test_sys("full");
    Mailbox a(sys, "a", 0, small(128)), b(sys, "b", 1, small(128));
    auto& to_b = a.peer("b");
    const char m[40] = "x";
    int sent = 0;
    while (a.write(to_b, m, sizeof m, 0) == Status::ok) ++sent;
    EXPECT_EQ(sent, 128 / 48);  // 8-byte record header + 40 bytes each
    const auto t0 = ipc::now_ns();
    EXPECT_EQ(a.write(to_b, m, sizeof m, 30'000'000), Status::full);
    EXPECT_GE(ipc::now_ns() - t0, 30'000'000);
    // A reader that frees space lets a blocked writer through.
    std::thread reader([&] {
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
        char buf[64];
        EXPECT_EQ(b.read(buf, sizeof buf), Status::ok);
    });
    EXPECT_EQ(a.write(to_b, m, sizeof m, 2'000'000'000), Status::ok);
    reader.join();
}

TEST(Mailbox, TooBigAndTooSmallBuffers) {
    const std::string sys = test_sys("big");
    Mailbox a(sys, "a", 0, small(128)), b(sys, "b", 1, small(128));
    auto& to_b = a.peer("b");
    char big[200] = {};
    EXPECT_EQ(a.write(to_b, big, 121), Status::too_big);
    EXPECT_EQ(a.write(to_b, big, 120), Status::ok);
    char small_buf[10];
    xm::ReadInfo info;
    EXPECT_EQ(b.read(small_buf, sizeof small_buf, &info), Status::too_big);
    EXPECT_EQ(info.length, 120u);
    char buf[128];
    EXPECT_EQ(b.read(buf, sizeof buf, &info), Status::ok);  // still there
}

TEST(Mailbox, ReadIsRoundRobinAcrossSenders) {
    const std::string sys = test_sys("rr");
    Mailbox r(sys, "r", 0, small()), s1(sys, "s1", 1, small()), s2(sys, "s2", 2, small());
    for (int i = 0; i < 3; ++i) {
        ASSERT_EQ(s1.write(s1.peer("r"), "1", 1), Status::ok);
        ASSERT_EQ(s2.write(s2.peer("r"), "2", 1), Status::ok);
    }
    std::string order;
    char c;
    while (r.read(&c, 1) == Status::ok) order += c;
    EXPECT_EQ(order, "121212");
}

TEST(Mailbox, InterruptsAreMultiplexedWithValues) {
    const std::string sys = test_sys("mbox");
    Mailbox a(sys, "a", 0, small()), b(sys, "b", 1, small());
    auto& to_b = a.peer("b");
    EXPECT_EQ(b.wait_interrupts(5'000'000), 0u);  // nothing pending: times out
    EXPECT_EQ(a.mbox_send(to_b, 5, 77), Status::ok);
    EXPECT_EQ(a.mbox_send(to_b, 8, 1), Status::bad_argument);
    EXPECT_EQ(a.mbox_send(to_b, 5, 0), Status::bad_argument);
    EXPECT_EQ(a.write(to_b, "m", 1), Status::ok);
    const std::uint32_t p = b.wait_interrupts(1'000'000'000);
    EXPECT_EQ(p, (1u << 5) | (1u << xm::kMboxSigBuf));
    EXPECT_EQ(b.mbox_value(5), 77u);
    EXPECT_EQ(b.take_interrupts(), 0u);
    // A sleeping owner is woken by a sender in another thread.
    std::thread t([&] {
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
        EXPECT_EQ(a.mbox_send(to_b, 6, 9), Status::ok);
    });
    EXPECT_EQ(b.wait_interrupts(2'000'000'000), 1u << 6);
    t.join();
}

TEST(Mailbox, WakeupBeforeBlockIsKeptAndBlockTimesOut) {
    const std::string sys = test_sys("wake");
    Mailbox a(sys, "a", 0, small()), b(sys, "b", 1, small());
    auto& to_b = a.peer("b");
    const std::uint32_t task = b.claim_task();
    EXPECT_EQ(b.block(task, 5'000'000), Status::timed_out);
    EXPECT_EQ(a.wakeup(to_b, task), Status::ok);
    EXPECT_EQ(a.wakeup(to_b, task), Status::ok);  // not counted: one wakeup kept
    EXPECT_EQ(b.block(task, 0), Status::ok);
    EXPECT_EQ(b.block(task, 5'000'000), Status::timed_out);
    EXPECT_EQ(a.wakeup(to_b, 99), Status::bad_argument);
    std::thread t([&] {
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
        EXPECT_EQ(a.wakeup(to_b, task), Status::ok);
    });
    EXPECT_EQ(b.block(task, 2'000'000'000), Status::ok);
    t.join();
    b.release_task(task);
}

TEST(Mailbox, BadConfigurationsAreRefused) {
    const std::string sys = test_sys("cfg");
    EXPECT_THROW(Mailbox(sys, "a", 4, small()), xm::Error);  // bid >= nrtpu
    EXPECT_THROW(Mailbox(sys, "a:b", 0, small()), xm::Error);
    Mailbox a(sys, "a", 0, small());
    try {
        Mailbox again(sys, "a", 1, small());
        FAIL() << "a second live owner was accepted";
    } catch (const xm::Error& e) {
        EXPECT_NE(std::string(e.what()).find("already running"), std::string::npos) << e.what();
    }
    try {
        a.peer("nobody");
        FAIL();
    } catch (const xm::Error& e) {
        EXPECT_NE(std::string(e.what()).find("no such RTPU"), std::string::npos) << e.what();
    }
}

TEST(Mailbox, DeadRtpuIsNotAliveAndItsMailboxIsTakenOver) {
    CHIMERA_NOT_UNDER_TSAN("a forked RTPU killed");
    const std::string sys = test_sys("dead");
    Mailbox a(sys, "a", 0, small());
    int ready[2];
    ASSERT_EQ(pipe(ready), 0);
    const pid_t child = fork();
    if (child == 0) {
        Mailbox c(sys, "c", 1, small());
        char x = 1;
        (void)!write(ready[1], &x, 1);
        pause();
        _exit(0);
    }
    char x;
    ASSERT_EQ(read(ready[0], &x, 1), 1);
    auto& to_c = a.peer("c");
    EXPECT_TRUE(a.alive(to_c));
    EXPECT_EQ(a.write(to_c, "hi", 2), Status::ok);
    kill(child, SIGKILL);
    waitpid(child, nullptr, 0);
    // Its alive word still says 1: the owner pid tells.
    EXPECT_EQ(to_c.header().alive.load(), 1u);
    EXPECT_FALSE(a.alive(to_c));
    a.set_probe_period(0);
    EXPECT_EQ(a.write(to_c, "hi", 2), Status::not_alive);
    EXPECT_EQ(a.wakeup(to_c, 0), Status::not_alive);
    EXPECT_EQ(a.mbox_send(to_c, 4, 1), Status::not_alive);
    // A new process may take the name over.
    Mailbox c2(sys, "c", 1, small());
    auto& again = a.peer("c");
    EXPECT_TRUE(a.alive(again));
    EXPECT_EQ(a.write(again, "hi", 2), Status::ok);
    close(ready[0]);
    close(ready[1]);
}

TEST(Mailbox, TwoLiveRtpusWithTheSameBidAreRefused) {
    CHIMERA_NOT_UNDER_TSAN("a forked RTPU");
    const std::string sys = test_sys("dupbid");
    const chimera::test::SegmentGuard cleanup("chimera." + sys + ".");  // the killed claimant's mailbox too
    Mailbox r(sys, "r", 0, small());
    int ready[2];
    ASSERT_EQ(pipe(ready), 0);
    const pid_t child = fork();
    if (child == 0) {
        Mailbox c(sys, "c", 1, small());
        c.peer("r");  // claims ring 1 in r
        char x = 1;
        (void)!write(ready[1], &x, 1);
        pause();
        _exit(0);
    }
    char x;
    ASSERT_EQ(read(ready[0], &x, 1), 1);
    {
        Mailbox d(sys, "d", 1, small());
        EXPECT_THROW(d.peer("r"), xm::Error);
    }
    kill(child, SIGKILL);
    waitpid(child, nullptr, 0);
    Mailbox d(sys, "d", 1, small());
    EXPECT_NO_THROW(d.peer("r"));  // the dead claimant's ring is taken over
    close(ready[0]);
    close(ready[1]);
}

TEST(Mailbox, ResetDropsUnreadMessages) {
    const std::string sys = test_sys("reset");
    Mailbox a(sys, "a", 0, small()), b(sys, "b", 1, small());
    auto& to_b = a.peer("b");
    ASSERT_EQ(a.write(to_b, "1", 1), Status::ok);
    ASSERT_EQ(a.write(to_b, "2", 1), Status::ok);
    b.reset_buffers();
    char c;
    EXPECT_EQ(b.read(&c, 1), Status::would_block);
    ASSERT_EQ(a.write(to_b, "3", 1), Status::ok);
    EXPECT_EQ(b.read(&c, 1), Status::ok);
    EXPECT_EQ(c, '3');
}

// The tasks of one RTPU share its Peer of a receiver (one ring, a local lock):
// writes and wake-ups from several threads at once, each re-checking that the
// receiver lives, all arrive, in each task's order. Under ThreadSanitizer
// (scripts/test.sh's tsan stage) this is the test of the Peer's liveness cache,
// which write() and wakeup() update outside the ring's lock.
TEST(Mailbox, TasksOfOneRtpuShareAPeer) {
    const std::string sys = test_sys("share");
    Mailbox a(sys, "a", 0, small(1024)), b(sys, "b", 1, small(1024));
    a.set_probe_period(0);  // every call re-checks the receiver
    auto& to_b = a.peer("b");
    constexpr std::uint32_t kTasks = 3, kEach = 500;
    std::vector<std::thread> tasks;
    for (std::uint32_t t = 0; t < kTasks; ++t)
        tasks.emplace_back([&, t] {
            for (std::uint32_t i = 0; i < kEach; ++i) {
                const std::uint32_t m = t << 16 | i;
                ASSERT_EQ(a.write(to_b, &m, sizeof m, 5'000'000'000), Status::ok) << t << ":" << i;
                ASSERT_EQ(a.wakeup(to_b, t), Status::ok);
            }
        });
    std::vector<std::uint32_t> next(kTasks, 0);
    std::uint32_t got = 0;
    const std::int64_t deadline = ipc::now_ns() + 30'000'000'000;
    while (got < kTasks * kEach && ipc::now_ns() < deadline) {
        std::uint32_t m = 0;
        xm::ReadInfo info;
        const Status s = b.read(&m, sizeof m, &info);
        if (s == Status::would_block) {
            std::this_thread::yield();
            continue;
        }
        ASSERT_EQ(s, Status::ok);
        const std::uint32_t t = m >> 16;
        ASSERT_LT(t, kTasks);
        ASSERT_EQ(m & 0xffff, next[t]) << "task " << t;
        ++next[t];
        ++got;
    }
    for (auto& t : tasks) t.join();
    EXPECT_EQ(got, kTasks * kEach);
    EXPECT_EQ(to_b.undelivered(), 0u);
}

// --- lost with a dead receiver: reported, not silent (issue #15.2) ----------------

namespace {

// A child RTPU "c" that reads nothing and waits to be killed.
pid_t idle_rtpu(const std::string& sys, const std::string& name, std::uint32_t bid) {
    int ready[2];
    if (pipe(ready) != 0) return -1;
    const pid_t child = fork();
    if (child == 0) {
        Mailbox c(sys, name, bid, small());
        char x = 1;
        (void)!write(ready[1], &x, 1);
        for (;;) pause();
    }
    char x;
    (void)!read(ready[0], &x, 1);
    close(ready[0]);
    close(ready[1]);
    return child;
}

}  // namespace

TEST(Mailbox, MessagesADeadReceiverLeftUnreadAreCountedByTheSender) {
    CHIMERA_NOT_UNDER_TSAN("a forked receiver killed");
    const std::string sys = test_sys("undeliv");
    const chimera::test::SegmentGuard cleanup("chimera." + sys + ".");
    Mailbox a(sys, "a", 0, small());
    const pid_t child = idle_rtpu(sys, "c", 1);
    auto& to_c = a.peer("c");
    for (int i = 0; i < 5; ++i) ASSERT_EQ(a.write(to_c, "msg", 3), Status::ok);
    kill(child, SIGKILL);
    waitpid(child, nullptr, 0);
    EXPECT_EQ(to_c.undelivered(), 0u);  // not known yet
    a.set_probe_period(0);
    EXPECT_EQ(a.write(to_c, "late", 4), Status::not_alive);
    EXPECT_EQ(to_c.undelivered(), 5u) << "the five written and never read";
    EXPECT_EQ(a.undelivered(), 5u);
    EXPECT_EQ(a.header().undelivered.load(), 5u) << "visible in the sender's mailbox header";
    EXPECT_EQ(a.write(to_c, "late", 4), Status::not_alive);
    EXPECT_EQ(a.undelivered(), 5u) << "counted once per dead receiver";
}

TEST(Mailbox, CheckPeersCountsTheLossWithoutAnotherWrite) {
    CHIMERA_NOT_UNDER_TSAN("a forked receiver killed");
    const std::string sys = test_sys("undeliv2");
    const chimera::test::SegmentGuard cleanup("chimera." + sys + ".");
    Mailbox a(sys, "a", 0, small());
    const pid_t child = idle_rtpu(sys, "c", 1);
    auto& to_c = a.peer("c");
    ASSERT_EQ(a.write(to_c, "one", 3), Status::ok);
    ASSERT_EQ(a.write(to_c, "two", 3), Status::ok);
    kill(child, SIGKILL);
    siginfo_t info{};
    ASSERT_EQ(waitid(P_PID, static_cast<id_t>(child), &info, WEXITED | WNOWAIT), 0);  // a zombie
    a.check_peers();
    EXPECT_EQ(a.undelivered(), 2u);
    waitpid(child, nullptr, 0);
}

// A receiver found dead stays dead for its Peer, even if a later probe says
// its owner lives: its pid reused, or (the kill loop's case) owner_alive()
// reading /proc/PID/task/TID/stat of a process reaped between its tgkill and
// its read, which failed with ESRCH and was taken for "alive". The loss had
// been counted once; a message write() then accepted went into no count.
TEST(Mailbox, APeerFoundDeadTakesNoMessageWhenItLooksAliveAgain) {
    CHIMERA_NOT_UNDER_TSAN("a forked receiver killed");
    const std::string sys = test_sys("undeliv4");
    const chimera::test::SegmentGuard cleanup("chimera." + sys + ".");
    Mailbox a(sys, "a", 0, small());
    a.set_probe_period(0);
    const pid_t child = idle_rtpu(sys, "c", 1);
    auto& to_c = a.peer("c");
    ASSERT_EQ(a.write(to_c, "one", 3), Status::ok);
    ASSERT_EQ(a.write(to_c, "two", 3), Status::ok);
    kill(child, SIGKILL);
    waitpid(child, nullptr, 0);
    a.check_peers();
    ASSERT_EQ(a.undelivered(), 2u);
    // The dead owner looks alive again: its pid now names a live process (ours).
    auto& header = const_cast<xm::layout::MailboxHeader&>(to_c.header());
    header.owner_pid.store(getpid());
    ASSERT_TRUE(a.alive(to_c));
    EXPECT_EQ(a.write(to_c, "three", 5), Status::not_alive) << "accepted, and counted nowhere";
    EXPECT_EQ(a.undelivered(), 2u);
    EXPECT_NE(&a.peer("c"), &to_c) << "the Peer found dead was handed out again";
}

TEST(Mailbox, AnRtpuServerCountsLossesOfItsTasksWithin100ms) {
    CHIMERA_NOT_UNDER_TSAN("a forked receiver killed");
    const std::string sys = test_sys("undeliv3");
    const chimera::test::SegmentGuard cleanup("chimera." + sys + ".");
    xm::Rtpu a(sys, "a", 0, small());
    const pid_t child = idle_rtpu(sys, "c", 1);
    auto& to_c = a.mailbox().peer("c");
    for (int i = 0; i < 3; ++i) ASSERT_EQ(a.mailbox().write(to_c, "x", 1), Status::ok);
    kill(child, SIGKILL);
    waitpid(child, nullptr, 0);
    const auto until = ipc::now_ns() + 2'000'000'000;
    while (a.mailbox().undelivered() == 0 && ipc::now_ns() < until)
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
    EXPECT_EQ(a.mailbox().undelivered(), 3u);
}

// --- memory another process writes is bounded before use (issue #15.3) ------------

TEST(Mailbox, ARingPositionOrRecordLengthOutsideTheRingIsRefused) {
    const std::string sys = test_sys("badring");
    Mailbox a(sys, "a", 1, small(256)), b(sys, "b", 2, small(256)), c(sys, "c", 3, small(256));
    auto& a_to_b = a.peer("b");
    auto& c_to_b = c.peer("b");
    const std::string seg = Mailbox::segment_name(sys, "b");
    // The sender's ring in b's segment, as any process mapping it can write it.
    ipc::Segment raw = ipc::Segment::attach(seg, {ipc::ObjectType::xmail_mailbox, xm::layout::kMailboxVersion});
    const auto& h = *static_cast<xm::layout::MailboxHeader*>(raw.base());
    auto* ring1 = reinterpret_cast<xm::layout::RingHeader*>(static_cast<std::byte*>(raw.base()) +
                                                            h.off_rings + h.ring_stride * 1);
    auto* rec1 = reinterpret_cast<xm::layout::RecordHeader*>(ring1 + 1);
    char buf[512];
    xm::ReadInfo info;

    // A record length larger than the ring.
    ASSERT_EQ(a.write(a_to_b, "hello", 5), Status::ok);
    ASSERT_EQ(c.write(c_to_b, "from c", 6), Status::ok);
    rec1->length = 100000;
    EXPECT_EQ(b.read(buf, sizeof buf, &info), Status::corrupt);
    EXPECT_NE(b.fault_message().find("segment " + seg + ": ring record length [1] is 100000"),
              std::string::npos)
        << b.fault_message();
    // The bad ring's bytes are dropped (counted); the other sender goes on.
    ASSERT_EQ(b.read(buf, sizeof buf, &info), Status::ok);
    EXPECT_EQ(std::string(buf, info.length), "from c");
    EXPECT_EQ(ring1->discarded.load(), 16u);
    // And the first one too, after the refusal.
    ASSERT_EQ(a.write(a_to_b, "again", 5), Status::ok);
    ASSERT_EQ(b.read(buf, sizeof buf, &info), Status::ok);
    EXPECT_EQ(std::string(buf, info.length), "again");

    // A write position beyond what the ring holds.
    ring1->in.store(ring1->in.load() + 4096);
    EXPECT_EQ(b.read(buf, sizeof buf, &info), Status::corrupt);
    EXPECT_NE(b.fault_message().find("ring fill (written - read) [1] is 4096 (must be at most 256)"),
              std::string::npos)
        << b.fault_message();
    // A read position the sender cannot trust: its write is refused, nothing copied.
    ring1->out.store(ring1->out.load() - 1000);
    EXPECT_EQ(a.write(a_to_b, "x", 1), Status::corrupt);
    EXPECT_NE(a_to_b.fault_message().find("segment " + seg + ": ring fill"), std::string::npos)
        << a_to_b.fault_message();
}

TEST(Mailbox, ACorruptMailboxHeaderIsRefusedOnAttachNamingTheSegment) {
    const std::string sys = test_sys("badhdr");
    Mailbox b(sys, "b", 1, small(256));
    const std::string seg = Mailbox::segment_name(sys, "b");
    auto& h = b.header();
    const struct {
        std::uint64_t xm::layout::MailboxHeader::*field;
        std::uint64_t bad;
        const char* named;
    } offsets[] = {
        {&xm::layout::MailboxHeader::off_rings, 1 << 30, "ring offset"},
        {&xm::layout::MailboxHeader::ring_stride, 64, "ring stride"},
        {&xm::layout::MailboxHeader::off_wakeup, 8, "wakeup offset"},
        {&xm::layout::MailboxHeader::off_mbox, 1 << 20, "mailbox interrupt offset"},
    };
    for (const auto& o : offsets) {
        const std::uint64_t good = h.*o.field;
        h.*o.field = o.bad;
        Mailbox a(sys, "a", 0, small(256));
        try {
            a.peer("b");
            ADD_FAILURE() << o.named << ": attached";
        } catch (const xm::Error& e) {
            EXPECT_NE(std::string(e.what()).find("segment " + seg + ": " + o.named), std::string::npos)
                << e.what();
        }
        h.*o.field = good;
    }
    for (std::uint32_t bad : {0u, 1u << 31}) {
        const std::uint32_t good = h.bufsize;
        h.bufsize = bad;
        Mailbox a(sys, "a", 0, small(256));
        EXPECT_THROW(a.peer("b"), xm::Error);
        h.bufsize = good;
    }
    // The owner keeps the sizes it created the mailbox with.
    h.bufsize = 1u << 30;
    Mailbox a(sys, "a", 0, small(256));
    h.bufsize = 256;
    auto& to_b = a.peer("b");
    h.bufsize = 1u << 30;
    h.nrtpu = 64;
    ASSERT_EQ(a.write(to_b, "ok", 2), Status::ok);
    char buf[8];
    EXPECT_EQ(b.read(buf, sizeof buf), Status::ok);
    EXPECT_TRUE(xm::validate_mailbox(&b.header(), xm::layout::mailbox_size(small(256))));
    h.bufsize = 256;
    h.nrtpu = 4;
    EXPECT_FALSE(xm::validate_mailbox(&b.header(), xm::layout::mailbox_size(small(256))));
}

// Squatted names (issue #29.5): nobody makes an RTPU's mailbox first, its
// alive word set and its owner pid 1 (root's init, alive): before, root's RTPU
// took it for a running one ("RTPU already running (pid 1)"). The segment's
// creator, the squatter, is dead and the file is not root's: root removes it,
// saying whose it was, and its RTPUs then talk through new mailboxes.
TEST(Mailbox, NobodysFakeMailboxDoesNotStopRootsRtpu) {
    CHIMERA_NOT_UNDER_TSAN("forked users");
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    const std::string sys = test_sys("squat");
    const chimera::test::SegmentGuard cleanup("chimera." + sys + ".");
    const pid_t squatter = fork();
    if (squatter == 0) {
        if (!chimera::test::become_nobody({})) _exit(10);
        Mailbox fake(sys, "a", 0, small());
        fake.header().owner_pid.store(1);
        _exit(0);  // no destructor: the mailbox stays, alive, naming pid 1
    }
    int status = -1;
    ASSERT_EQ(waitpid(squatter, &status, 0), squatter);
    ASSERT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << status;
    const passwd* nobody = getpwnam("nobody");
    ASSERT_NE(nobody, nullptr);
    testing::internal::CaptureStderr();
    Mailbox a(sys, "a", 0, small());
    EXPECT_EQ(testing::internal::GetCapturedStderr(),
              "chimera: segment " + Mailbox::segment_name(sys, "a") + ", nobody's (uid " +
                  std::to_string(nobody->pw_uid) +
                  ", mode 0600): squatted: it is another user's, and the creator its header names, pid " +
                  std::to_string(squatter) + ", is not running: removed, to be created anew\n");
    EXPECT_EQ(a.header().owner_pid.load(), getpid());
    Mailbox b(sys, "b", 1, small());
    ASSERT_EQ(b.write(b.peer("a"), "hi", 2), Status::ok);
    char buf[8];
    xm::ReadInfo info;
    ASSERT_EQ(a.read(buf, sizeof buf, &info), Status::ok);
    EXPECT_EQ(std::string(buf, info.length), "hi");
    EXPECT_EQ(info.from_bid, 1u);
}
