// Express mail: mailboxes, rings, interrupts, wakeups, alive status (§5.3.1).
#include "segment_guard.hpp"
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

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
        a.mbox_send(to_b, 6, 9);
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
        a.wakeup(to_b, task);
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
