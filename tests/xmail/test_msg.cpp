// Message queues over a plain memory block: Figure 5.2 structure, policies,
// multi-block messages, blocking variants, waiter ordering, journal repair.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/mman.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstring>
#include <deque>
#include <mutex>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "chimera/ipc/clock.hpp"
#include "chimera/ipc/lock.hpp"
#include "chimera/msg.hpp"
#include "detail.hpp"
#include "sanitizer.hpp"

using namespace chimera;
using msg::Policy;
using msg::Queue;
using xm::Status;

namespace {

struct Mem {
    explicit Mem(const msg::Params& p) : bytes(Queue::memory_size(p) / 8 + 1) {}
    void* data() { return bytes.data(); }
    std::size_t size() { return bytes.size() * 8; }
    std::vector<std::uint64_t> bytes;
};

msg::Params params(std::uint32_t blknum, std::uint32_t blksize, Policy policy) {
    msg::Params p;
    p.blknum = blknum;
    p.blksize = blksize;
    p.policy = policy;
    return p;
}

Status send_str(Queue& q, const std::string& s, std::int32_t prio = 0, std::int64_t timeout = 0) {
    return q.send(s.data(), s.size(), 0, prio, timeout);
}

std::string recv_str(Queue& q, std::int64_t timeout = 0, Status* st = nullptr, std::int32_t tp = 0) {
    char buf[4096];
    msg::Info info;
    const Status s = q.receive(buf, sizeof buf, &info, timeout, tp);
    if (st) *st = s;
    return s == Status::ok ? std::string(buf, info.size) : "<" + std::string(xm::to_string(s)) + ">";
}

// Pretends the lock holder died: a forked child that exits leaves a pid/tid
// that no longer exists.
std::uint64_t dead_owner() {
    const pid_t child = fork();
    if (child == 0) _exit(0);
    waitpid(child, nullptr, 0);
    return static_cast<std::uint64_t>(child) << 32 | static_cast<std::uint32_t>(child);
}

// A child process blocked in a receive without a time limit on the queue in
// shared memory `mem`, returned once it waits.
pid_t child_receiving(void* mem, std::size_t size, Queue& q, std::int32_t priority = 0) {
    const std::uint32_t before = q.stats().receive_waiters;
    const pid_t child = fork();
    if (child == 0) {
        Queue c = Queue::bind(mem, size);
        recv_str(c, -1, nullptr, priority);
        _exit(0);
    }
    while (q.stats().receive_waiters <= before) std::this_thread::yield();
    return child;
}

// A queue in shared memory with one receiver thread blocked in a receive
// without a time limit, alone on the list: it sleeps without a timer
// (detail::sleep_untimed()), so only a wake-up aimed at it gets it going.
class LoneReceiver {
public:
    explicit LoneReceiver(std::int32_t priority = 0)
        : p_(params(8, 16, Policy::fifo)), size_(Queue::memory_size(p_)),
          mem_(mmap(nullptr, size_, PROT_READ | PROT_WRITE, MAP_SHARED | MAP_ANONYMOUS, -1, 0)),
          q_(Queue::over(mem_, size_, p_)) {
        receiver_ = std::thread([this, priority] {
            got_ = recv_str(q_, -1, nullptr, priority);
            got_it_ = true;
        });
        while (q_.stats().receive_waiters == 0) std::this_thread::yield();
        std::this_thread::sleep_for(std::chrono::milliseconds(50));  // asleep, alone, untimed
    }
    ~LoneReceiver() {
        if (receiver_.joinable()) {
            (void)send_str(q_, "released by the test");
            receiver_.join();
        }
        munmap(mem_, size_);
    }
    LoneReceiver(const LoneReceiver&) = delete;
    LoneReceiver& operator=(const LoneReceiver&) = delete;
    Queue& queue() { return q_; }
    void* memory() { return mem_; }
    std::size_t size() const { return size_; }
    /// True when the receiver got a message within 2 s; either way it is
    /// joined (sent one of the test's if it still slept).
    bool got_it_in_time() {
        const std::int64_t deadline = ipc::now_ns() + 2'000'000'000;
        while (!got_it_ && ipc::now_ns() < deadline) std::this_thread::sleep_for(std::chrono::milliseconds(5));
        const bool in_time = got_it_;
        if (!in_time) (void)send_str(q_, "released by the test");
        receiver_.join();
        return in_time;
    }
    const std::string& got() const { return got_; }

private:
    msg::Params p_;
    std::size_t size_;
    void* mem_;
    Queue q_;
    std::atomic<bool> got_it_{false};
    std::string got_;
    std::thread receiver_;
};

}  // namespace

TEST(Msg, InitialStructureIsFigure52) {
    Mem m(params(4, 16, Policy::fifo));
    Queue q = Queue::over(m.data(), m.size(), params(4, 16, Policy::fifo), "test:q");
    auto* h = q.header();
    EXPECT_STREQ(h->segname, "test:q");
    EXPECT_EQ(h->blknum, 4u);
    EXPECT_EQ(h->blksize, 16u);
    EXPECT_EQ(h->headused, 0u);
    EXPECT_EQ(h->tailused, 0u);
    EXPECT_NE(h->headfree, 0u);
    EXPECT_NE(h->blkfree, 0u);
    // Links are offsets from the queue's base, not pointers.
    EXPECT_LT(h->headfree, m.size());
    EXPECT_LT(h->blkfree, m.size());
    EXPECT_EQ(q.check(), "");
    auto s = q.stats();
    EXPECT_EQ(s.free_headers, 4u);
    EXPECT_EQ(s.free_blocks, 4u);
    EXPECT_EQ(s.messages, 0u);
}

TEST(Msg, FifoLifoHpfOrder) {
    for (Policy pol : {Policy::fifo, Policy::lifo, Policy::hpf}) {
        Mem m(params(8, 16, pol));
        Queue q = Queue::over(m.data(), m.size(), params(8, 16, pol));
        const std::vector<std::pair<std::string, int>> in = {
            {"a", 1}, {"b", 5}, {"c", 3}, {"d", 5}, {"e", 2}};
        for (auto& [s, p] : in) ASSERT_EQ(send_str(q, s, p), Status::ok);
        EXPECT_EQ(q.check(), "");
        std::string out;
        for (std::size_t i = 0; i < in.size(); ++i) out += recv_str(q);
        const char* expected = pol == Policy::fifo   ? "abcde"
                               : pol == Policy::lifo ? "edcba"
                                                     : "bdcea";  // equal priorities stay FIFO
        EXPECT_EQ(out, expected);
        EXPECT_EQ(q.check(), "");
    }
}

TEST(Msg, HpfKeepsHighestAtHeadWhileInterleaving) {
    Mem m(params(16, 8, Policy::hpf));
    Queue q = Queue::over(m.data(), m.size(), params(16, 8, Policy::hpf));
    ASSERT_EQ(send_str(q, "p2", 2), Status::ok);
    ASSERT_EQ(send_str(q, "p9", 9), Status::ok);
    EXPECT_EQ(q.dump(), "9:0:2 2:0:2");
    EXPECT_EQ(recv_str(q), "p9");
    ASSERT_EQ(send_str(q, "p7", 7), Status::ok);
    ASSERT_EQ(send_str(q, "p2b", 2), Status::ok);
    ASSERT_EQ(send_str(q, "m1", -1), Status::ok);
    EXPECT_EQ(q.dump(), "7:0:2 2:0:2 2:0:3 -1:0:2");
    EXPECT_EQ(recv_str(q), "p7");
    EXPECT_EQ(recv_str(q), "p2");
    EXPECT_EQ(recv_str(q), "p2b");
    EXPECT_EQ(recv_str(q), "m1");
}

TEST(Msg, MultiBlockMessagesUpToBlksizeTimesBlknum) {
    Mem m(params(6, 16, Policy::fifo));
    Queue q = Queue::over(m.data(), m.size(), params(6, 16, Policy::fifo));
    std::string big(100, '\0');
    for (std::size_t i = 0; i < big.size(); ++i) big[i] = static_cast<char>('A' + i % 26);
    EXPECT_EQ(send_str(q, big.substr(0, 40)), Status::ok);  // 3 blocks
    EXPECT_EQ(q.stats().free_blocks, 3u);
    EXPECT_EQ(q.check(), "");
    EXPECT_EQ(send_str(q, big.substr(0, 49)), Status::would_block);  // needs 4
    EXPECT_EQ(send_str(q, big.substr(0, 48)), Status::ok);            // exactly 3
    EXPECT_EQ(q.stats().free_blocks, 0u);
    EXPECT_EQ(recv_str(q), big.substr(0, 40));
    EXPECT_EQ(recv_str(q), big.substr(0, 48));
    EXPECT_EQ(q.check(), "");
    // The whole queue for one message: blksize * blknum bytes.
    std::string whole(96, 'z');
    whole[0] = 'a';
    whole[95] = 'q';
    EXPECT_EQ(send_str(q, whole), Status::ok);
    EXPECT_EQ(q.check(), "");
    EXPECT_EQ(recv_str(q), whole);
    EXPECT_EQ(send_str(q, std::string(97, 'x')), Status::too_big);
    // Zero-length messages take a header and no block.
    EXPECT_EQ(send_str(q, ""), Status::ok);
    EXPECT_EQ(q.stats().free_blocks, 6u);
    EXPECT_EQ(recv_str(q), "");
}

TEST(Msg, ReceiveBufferTooSmallLeavesTheMessage) {
    Mem m(params(4, 16, Policy::fifo));
    Queue q = Queue::over(m.data(), m.size(), params(4, 16, Policy::fifo));
    ASSERT_EQ(send_str(q, "0123456789"), Status::ok);
    char buf[4];
    msg::Info info;
    EXPECT_EQ(q.receive(buf, sizeof buf, &info, 0), Status::too_big);
    EXPECT_EQ(info.size, 10u);
    EXPECT_EQ(recv_str(q), "0123456789");
}

TEST(Msg, TypeAndPriorityTravelWithTheMessage) {
    Mem m(params(4, 16, Policy::hpf));
    Queue q = Queue::over(m.data(), m.size(), params(4, 16, Policy::hpf));
    ASSERT_EQ(q.send("x", 1, 42, 7, 0), Status::ok);
    char c;
    msg::Info info;
    ASSERT_EQ(q.receive(&c, 1, &info, 0), Status::ok);
    EXPECT_EQ(info.type, 42u);
    EXPECT_EQ(info.priority, 7);
    EXPECT_EQ(info.size, 1u);
}

TEST(Msg, NonBlockingTimedAndBlockingOnFullAndEmpty) {
    Mem m(params(2, 8, Policy::fifo));
    Queue q = Queue::over(m.data(), m.size(), params(2, 8, Policy::fifo));
    Status st;
    EXPECT_EQ(recv_str(q, 0, &st), "<would block>");
    auto t0 = ipc::now_ns();
    recv_str(q, 20'000'000, &st);
    EXPECT_EQ(st, Status::timed_out);
    EXPECT_GE(ipc::now_ns() - t0, 20'000'000);
    ASSERT_EQ(send_str(q, "1"), Status::ok);
    ASSERT_EQ(send_str(q, "2"), Status::ok);
    EXPECT_EQ(send_str(q, "3", 0, 0), Status::would_block);
    t0 = ipc::now_ns();
    EXPECT_EQ(send_str(q, "3", 0, 20'000'000), Status::timed_out);
    EXPECT_GE(ipc::now_ns() - t0, 20'000'000);
    // A blocked sender gets through when a receiver makes room.
    std::thread r([&] {
        std::this_thread::sleep_for(std::chrono::milliseconds(30));
        EXPECT_EQ(recv_str(q), "1");
    });
    EXPECT_EQ(send_str(q, "3", 0, -1), Status::ok);
    r.join();
    EXPECT_EQ(recv_str(q), "2");
    EXPECT_EQ(recv_str(q), "3");
    // A blocked receiver is woken by a send.
    std::thread s([&] {
        std::this_thread::sleep_for(std::chrono::milliseconds(30));
        EXPECT_EQ(send_str(q, "late"), Status::ok);
    });
    EXPECT_EQ(recv_str(q, -1), "late");
    s.join();
    EXPECT_EQ(q.check(), "");
}

TEST(Msg, WaitingReceiversAreServedHighestPriorityFirst) {
    Mem m(params(8, 16, Policy::fifo));
    Queue q = Queue::over(m.data(), m.size(), params(8, 16, Policy::fifo));
    std::mutex mu;
    std::vector<std::pair<int, std::string>> got;
    std::vector<std::thread> threads;
    for (int prio : {1, 5, 3, 5}) {
        threads.emplace_back([&, prio] {
            const std::string s = recv_str(q, 5'000'000'000, nullptr, prio);
            std::lock_guard lock(mu);
            got.emplace_back(prio, s);
        });
        // One at a time, so arrival order among the equal priorities is known.
        while (q.stats().receive_waiters < threads.size()) std::this_thread::yield();
    }
    for (const char* s : {"A", "B", "C", "D"}) ASSERT_EQ(send_str(q, s), Status::ok);
    for (auto& t : threads) t.join();
    std::sort(got.begin(), got.end(), [](auto& a, auto& b) { return a.second < b.second; });
    ASSERT_EQ(got.size(), 4u);
    EXPECT_EQ(got[0], std::make_pair(5, std::string("A")));
    EXPECT_EQ(got[1], std::make_pair(5, std::string("B")));
    EXPECT_EQ(got[2], std::make_pair(3, std::string("C")));
    EXPECT_EQ(got[3], std::make_pair(1, std::string("D")));
    EXPECT_EQ(q.check(), "");
}

// A receiver killed while it waits, and not reaped yet (a zombie: it passes
// the hand-off's cheap liveness check), may be handed a message; the next
// receive finds the queue empty, takes the message back and gets it.
TEST(Msg, AMessageHandedToAKilledUnreapedReceiverIsTakenBack) {
    CHIMERA_NOT_UNDER_TSAN("a forked receiver killed");
    const auto p = params(8, 16, Policy::fifo);
    const std::size_t size = Queue::memory_size(p);
    void* mem = mmap(nullptr, size, PROT_READ | PROT_WRITE, MAP_SHARED | MAP_ANONYMOUS, -1, 0);
    ASSERT_NE(mem, MAP_FAILED);
    Queue q = Queue::over(mem, size, p);
    const pid_t child = child_receiving(mem, size, q);
    kill(child, SIGKILL);
    siginfo_t info{};
    ASSERT_EQ(waitid(P_PID, static_cast<id_t>(child), &info, WEXITED | WNOWAIT), 0);  // a zombie now
    ASSERT_EQ(send_str(q, "lost?"), Status::ok);
    EXPECT_EQ(recv_str(q, 200'000'000), "lost?");
    EXPECT_EQ(q.check(), "");
    waitpid(child, nullptr, 0);
    munmap(mem, size);
}

// A receiver that waits without a time limit sleeps without a timer while it
// is the only one (detail::sleep_untimed()); a second receiver that joins
// kicks it into slices, so a message handed to the second and lost with it
// still reaches the first. Here the second (a child, higher priority) is
// stopped, handed the message (a stopped thread passes the liveness check),
// and killed: without the kick, the first would sleep on for good.
TEST(Msg, AMessageLostWithALaterReceiverReachesTheOneThatWaitedAlone) {
    CHIMERA_NOT_UNDER_TSAN("a forked receiver stopped and killed");
    LoneReceiver first(1);
    Queue& q = first.queue();
    const pid_t second = child_receiving(first.memory(), first.size(), q, 5);
    kill(second, SIGSTOP);
    siginfo_t info{};
    ASSERT_EQ(waitid(P_PID, static_cast<id_t>(second), &info, WSTOPPED | WNOWAIT), 0);
    ASSERT_EQ(send_str(q, "handed"), Status::ok);  // to the higher priority: the stopped child
    kill(second, SIGKILL);
    waitpid(second, nullptr, 0);
    EXPECT_TRUE(first.got_it_in_time()) << "the lone receiver slept on while the message stayed with the dead one";
    EXPECT_EQ(first.got(), "handed");
    EXPECT_EQ(q.check(), "");
}

// A sender killed after its commit point and before its hand-off (and so
// before its wake-up) holds the lock with the message committed; a lone
// receiver that sleeps without a timer would sleep on until some other
// process took the lock. The child does what send() does up to there, with
// the library's own arming of the receiver's word before the commit, then
// exits holding the lock: the kernel, finding the hand-off pending in the
// exiting thread's robust list, wakes the receiver, which takes the lock
// over, has the message queued by the repair, and receives it.
TEST(Msg, ALoneReceiverGetsAMessageWhoseSenderDiedBetweenCommitAndHandOff) {
    CHIMERA_NOT_UNDER_TSAN("a forked sender");
    LoneReceiver receiver;
    Queue& q = receiver.queue();
    auto* h = q.header();
    const pid_t sender = fork();
    if (sender == 0) {
        if (!ipc::holds(ipc::lock(h->mutex))) _exit(2);
        xm::layout::Waiter* w = xm::detail::waiter_pick(h->recv_waiters, msg::layout::kMaxWaiters);
        if (w == nullptr) _exit(3);
        // A header and a block off the free lists, filled, as send() does.
        const std::uint32_t hoff = h->headfree;
        auto* head = reinterpret_cast<msg::layout::MsgHead*>(reinterpret_cast<std::byte*>(h) + hoff);
        h->headfree = head->link;
        h->nfree_heads--;
        head->state = msg::layout::kHeadWriting;
        const std::uint32_t boff = h->blkfree;
        auto* blk = reinterpret_cast<msg::layout::MsgBHead*>(reinterpret_cast<std::byte*>(h) + boff);
        h->blkfree = blk->link;
        h->nfree_blks--;
        blk->owner = (hoff - h->off_heads) / sizeof(msg::layout::MsgHead) + 1;
        blk->link = 0;
        std::memcpy(blk + 1, "committed", 9);
        head->link = 0;
        head->type = 0;
        head->priority = 0;
        head->size = 9;
        head->nblk = 1;
        head->blk = boff;
        head->seq = h->next_seq++;
        xm::detail::waiter_arm(*w);  // as send() does, before its commit
        head->state = msg::layout::kHeadQueued;  // the commit
        _exit(0);  // gone before the hand-off, holding the lock, as if killed there
    }
    int status = 0;
    ASSERT_EQ(waitpid(sender, &status, 0), sender);
    ASSERT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << status;
    EXPECT_TRUE(receiver.got_it_in_time()) << "the lone receiver slept on while the committed message waited in the queue";
    EXPECT_EQ(receiver.got(), "committed");
    EXPECT_EQ(q.stats().recoveries, 1u);
    EXPECT_EQ(q.check(), "");
}

// Senders blocked on a full queue get the room in message-priority order
// (FIFO among equals), whatever order they arrived in.
TEST(Msg, BlockedSendersAreServedHighestMessagePriorityFirst) {
    Mem m(params(1, 16, Policy::fifo));
    Queue q = Queue::over(m.data(), m.size(), params(1, 16, Policy::fifo));
    ASSERT_EQ(send_str(q, "first"), Status::ok);  // the queue is full
    std::vector<std::thread> threads;
    std::vector<Status> results(4);
    const std::vector<std::pair<int, std::string>> senders{{1, "p1"}, {5, "p5a"}, {3, "p3"}, {5, "p5b"}};
    for (std::size_t i = 0; i < senders.size(); ++i) {
        threads.emplace_back([&, i] { results[i] = send_str(q, senders[i].second, senders[i].first, 5'000'000'000); });
        while (q.stats().send_waiters < threads.size()) std::this_thread::yield();
    }
    std::vector<std::string> got;
    for (int i = 0; i < 5; ++i) got.push_back(recv_str(q, 5'000'000'000));
    for (auto& t : threads) t.join();
    for (Status st : results) EXPECT_EQ(st, Status::ok);
    EXPECT_EQ(got, (std::vector<std::string>{"first", "p5a", "p5b", "p3", "p1"}));
    EXPECT_EQ(q.check(), "");
}

// A receiver polling (timeout 0: the empty queue is seen without the lock)
// while a sender of the same process sends: every message arrives once and in
// order. Under ThreadSanitizer (scripts/test.sh's tsan stage) this is the test
// of that lock-free look at the counters the sender changes under the lock.
TEST(Msg, PollingReceiverBesideASenderGetsEveryMessageInOrder) {
    const auto p = params(4, 8, Policy::fifo);
    Mem m(p);
    Queue q = Queue::over(m.data(), m.size(), p);
    constexpr int kMessages = 2000;
    std::thread sender([&] {
        for (int i = 0; i < kMessages; ++i)
            ASSERT_EQ(send_str(q, std::to_string(i), 0, 5'000'000'000), Status::ok) << i;
    });
    int next = 0;
    const std::int64_t deadline = ipc::now_ns() + 30'000'000'000;
    while (next < kMessages && ipc::now_ns() < deadline) {
        Status st;
        const std::string got = recv_str(q, 0, &st);
        if (st == Status::would_block) {
            std::this_thread::yield();
            continue;
        }
        ASSERT_EQ(st, Status::ok);
        ASSERT_EQ(got, std::to_string(next));
        ++next;
    }
    sender.join();
    EXPECT_EQ(next, kMessages);
    EXPECT_EQ(q.check(), "");
}

// Random operations against a reference model: exact contents and order.
TEST(Msg, RandomOperationsMatchAReferenceModel) {
    for (Policy pol : {Policy::fifo, Policy::lifo, Policy::hpf}) {
        const auto p = params(12, 8, pol);
        Mem m(p);
        Queue q = Queue::over(m.data(), m.size(), p);
        struct Ref { std::string data; int prio; unsigned seq; };
        std::vector<Ref> model;  // in delivery order
        unsigned seq = 0;
        int free_blocks = 12;
        std::mt19937 rng(1234 + static_cast<int>(pol));
        for (int step = 0; step < 3000; ++step) {
            if (rng() % 2) {
                const std::size_t len = rng() % 30;
                const int prio = static_cast<int>(rng() % 4);
                std::string s(len, '\0');
                for (auto& c : s) c = static_cast<char>('a' + rng() % 26);
                const int need = static_cast<int>((len + 7) / 8);
                const Status st = send_str(q, s, prio, 0);
                const bool fits = model.size() < 12 && need <= free_blocks;
                ASSERT_EQ(st, fits ? Status::ok : Status::would_block) << step;
                if (!fits) continue;
                free_blocks -= need;
                Ref r{s, prio, seq++};
                auto pos = model.end();
                if (pol == Policy::lifo) pos = model.begin();
                if (pol == Policy::hpf)
                    pos = std::find_if(model.begin(), model.end(), [&](const Ref& x) { return x.prio < prio; });
                model.insert(pos, r);
            } else {
                Status st;
                const std::string got = recv_str(q, 0, &st);
                if (model.empty()) {
                    ASSERT_EQ(st, Status::would_block);
                    continue;
                }
                ASSERT_EQ(got, model.front().data) << "step " << step;
                free_blocks += static_cast<int>((model.front().data.size() + 7) / 8);
                model.erase(model.begin());
            }
            if (step % 100 == 0) {
                ASSERT_EQ(q.check(), "") << step;
            }
        }
    }
}

// The journal: a holder killed mid-operation is rolled back by the next user.
TEST(Msg, RepairRollsBackAnInterruptedReceive) {
    CHIMERA_NOT_UNDER_TSAN("the lock held by a forked child that exited");
    const auto p = params(4, 8, Policy::hpf);
    Mem m(p);
    Queue q = Queue::over(m.data(), m.size(), p);
    ASSERT_EQ(send_str(q, "low", 1), Status::ok);
    ASSERT_EQ(send_str(q, "high", 9), Status::ok);
    auto* h = q.header();
    // A receiver popped the head and was copying it when it died.
    const std::uint32_t off = h->headused;
    auto* head = reinterpret_cast<msg::layout::MsgHead*>(reinterpret_cast<std::byte*>(h) + off);
    h->headused = head->link;
    h->nmsgs--;
    head->state = msg::layout::kHeadReading;
    h->mutex.owner.store(dead_owner());
    EXPECT_EQ(q.check(), "");  // takes the lock over, repairs, finds it consistent
    EXPECT_EQ(q.stats().recoveries, 1u);
    EXPECT_EQ(q.stats().lock_recoveries, 1u);
    EXPECT_EQ(recv_str(q), "high");
    EXPECT_EQ(recv_str(q), "low");
}

TEST(Msg, RepairRollsBackAnInterruptedSend) {
    CHIMERA_NOT_UNDER_TSAN("the lock held by a forked child that exited");
    const auto p = params(4, 8, Policy::fifo);
    Mem m(p);
    Queue q = Queue::over(m.data(), m.size(), p);
    ASSERT_EQ(send_str(q, "one"), Status::ok);
    auto* h = q.header();
    // A sender took a header and two blocks, then died before its commit.
    const std::uint32_t hoff = h->headfree;
    auto* head = reinterpret_cast<msg::layout::MsgHead*>(reinterpret_cast<std::byte*>(h) + hoff);
    h->headfree = head->link;
    h->nfree_heads--;
    head->state = msg::layout::kHeadWriting;
    const std::uint32_t b1 = h->blkfree;
    auto* blk = reinterpret_cast<msg::layout::MsgBHead*>(reinterpret_cast<std::byte*>(h) + b1);
    h->blkfree = blk->link;
    blk->owner = (hoff - h->off_heads) / sizeof(msg::layout::MsgHead) + 1;
    head->blk = b1;
    h->nfree_blks--;
    h->mutex.owner.store(dead_owner());
    EXPECT_EQ(q.check(), "");
    auto s = q.stats();
    EXPECT_EQ(s.messages, 1u);
    EXPECT_EQ(s.free_headers, 3u);
    EXPECT_EQ(s.free_blocks, 3u);
    EXPECT_EQ(recv_str(q), "one");
}

TEST(Msg, RepairKeepsACommittedSendHalfInserted) {
    CHIMERA_NOT_UNDER_TSAN("the lock held by a forked child that exited");
    const auto p = params(4, 8, Policy::fifo);
    Mem m(p);
    Queue q = Queue::over(m.data(), m.size(), p);
    ASSERT_EQ(send_str(q, "one"), Status::ok);
    ASSERT_EQ(send_str(q, "two"), Status::ok);
    auto* h = q.header();
    // "two" was committed (QUEUED) but the sender died before linking it.
    auto* first = reinterpret_cast<msg::layout::MsgHead*>(reinterpret_cast<std::byte*>(h) + h->headused);
    first->link = 0;
    h->tailused = h->headused;
    h->nmsgs = 1;
    h->mutex.owner.store(dead_owner());
    EXPECT_EQ(q.check(), "");
    EXPECT_EQ(recv_str(q), "one");
    EXPECT_EQ(recv_str(q), "two");
    // check() itself sees a broken list when nobody died.
    ASSERT_EQ(send_str(q, "x"), Status::ok);
    h->nmsgs = 5;
    EXPECT_NE(q.check(), "");
}

// A sender died in the middle of handing a message to a waiting receiver:
// it had named the header in the receiver's slot but not yet signalled it.
// The message must go back into the queue and the slot must not keep it, or
// the receiver, once woken, would take a header that is also queued.
TEST(Msg, RepairUndoesAHalfDoneHandOff) {
    CHIMERA_NOT_UNDER_TSAN("the lock held by a forked child that exited");
    const auto p = params(4, 8, Policy::fifo);
    Mem m(p);
    Queue q = Queue::over(m.data(), m.size(), p);
    ASSERT_EQ(send_str(q, "m"), Status::ok);
    auto* h = q.header();
    const std::uint32_t off = h->headused;
    auto* head = reinterpret_cast<msg::layout::MsgHead*>(reinterpret_cast<std::byte*>(h) + off);
    h->headused = head->link;
    h->tailused = 0;
    h->nmsgs--;
    head->state = msg::layout::kHeadHanded;
    // The receiver waiting in slot 0 is this (live) thread.
    xm::layout::Waiter& w = h->recv_waiters[0];
    const std::uint64_t me = ipc::self_owner_id();
    w.pid = ipc::owner_pid(me);
    w.tid = ipc::owner_tid(me);
    w.state = 1;  // waiting
    w.handed = (off - h->off_heads) / sizeof(msg::layout::MsgHead) + 1;
    h->mutex.owner.store(dead_owner());
    EXPECT_EQ(q.check(), "");
    EXPECT_EQ(q.stats().recoveries, 1u);
    EXPECT_EQ(w.handed, 0u);
    EXPECT_EQ(q.stats().messages, 1u);
    EXPECT_EQ(q.stats().handed, 0u);
    w.state = 0;  // the receiver would free its slot on waking
    EXPECT_EQ(recv_str(q), "m");
    Status st;
    recv_str(q, 0, &st);
    EXPECT_EQ(st, Status::would_block);
    // check() names a slot that holds a header not handed to it.
    ASSERT_EQ(send_str(q, "n"), Status::ok);
    w.state = 2;
    w.handed = (h->headused - h->off_heads) / sizeof(msg::layout::MsgHead) + 1;
    EXPECT_NE(q.check().find("not HANDED"), std::string::npos);
    w.state = 0;
    w.handed = 0;
}

TEST(Msg, BadParametersAndMemoryAreRefused) {
    std::vector<std::uint64_t> mem(64);
    EXPECT_THROW(Queue::over(mem.data(), 512, params(0, 8, Policy::fifo)), xm::Error);
    EXPECT_THROW(Queue::over(mem.data(), 512, params(4, 0, Policy::fifo)), xm::Error);
    EXPECT_THROW(Queue::over(mem.data(), 512, params(1000, 8, Policy::fifo)), xm::Error);
    EXPECT_THROW(Queue::over(mem.data(), 512, params(4, 8, static_cast<Policy>(7))), xm::Error);
    std::vector<std::uint64_t> junk(4096, 0x1234);
    EXPECT_THROW(Queue::bind(junk.data(), junk.size() * 8), xm::Error);
    // A layout version mismatch is named.
    const auto p = params(4, 8, Policy::fifo);
    Mem m(p);
    Queue::over(m.data(), m.size(), p);
    static_cast<msg::layout::QueueHeader*>(m.data())->segment.layout_version = 99;
    try {
        Queue::bind(m.data(), Queue::memory_size(p));
        FAIL();
    } catch (const xm::Error& e) {
        EXPECT_NE(std::string(e.what()).find("layout version 99"), std::string::npos) << e.what();
    }
}
