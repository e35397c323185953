// The triple buffer: stamps, newest item, missed counts, caller memory, and
// a writer/reader stress test across processes and threads.
#include <gtest/gtest.h>

#include <cstdlib>
#include <thread>

#include "chimera/ipc/clock.hpp"
#include "chimera/tbuf.hpp"
#include "svar_test_util.hpp"

using namespace chimera;
using namespace chimera::tbuf;
using namespace svar_test;

namespace {

struct Item {
    std::uint64_t counter;  // the writer's own count, to compare with the stamp
    std::uint64_t words[30];
};

void make_item(Item& it, std::uint64_t n) {
    it.counter = n;
    for (std::uint64_t& w : it.words) w = n * 0x9E3779B97F4A7C15ull;
}

// 0 when the item is whole and matches the counter-stamp.
int check_item(const Item& it, const ReadResult& r) {
    if (it.counter != r.counter) return 1;
    for (std::uint64_t w : it.words)
        if (w != it.counter * 0x9E3779B97F4A7C15ull) return 2;
    return 0;
}

struct alignas(64) Block {
    std::byte bytes[4096];
};

// Reader loop shared by the process and thread stress tests; 0 on success.
int reader_loop(Tbuf& tb, std::int64_t end_ns, const std::atomic<int>& writer_done,
                std::uint64_t last_written_expected_min, long& fresh_reads) {
    Item it{};
    std::uint64_t prev = 0;
    std::int64_t prev_time = 0;
    bool any = false;
    std::uint64_t missed_sum = 0;
    for (;;) {
        const bool done = writer_done.load(std::memory_order_acquire) != 0;
        const ReadResult r = tb.read(&it);
        if (r.status == ReadStatus::empty) {
            if (any) return 10;  // empty after data
        } else {
            if (check_item(it, r) != 0) return 11;  // torn item
            if (r.status == ReadStatus::fresh) {
                if (any && r.counter <= prev) return 12;  // stale after new / non-monotonic
                if (r.missed != (any ? r.counter - prev - 1 : r.counter)) return 13;
                if (r.time_ns < prev_time) return 14;
                missed_sum += r.missed;
                prev = r.counter;
                prev_time = r.time_ns;
                any = true;
                ++fresh_reads;
            } else {
                if (!any || r.counter != prev) return 15;  // reused must be the same item
            }
        }
        if (done) {
            // Writer finished before this read began: we must hold its newest.
            if (!any || prev + 1 < last_written_expected_min) return 16;
            if (missed_sum + static_cast<std::uint64_t>(fresh_reads) != prev + 1) return 17;
            if (tb.missed_total() != missed_sum) return 18;
            return 0;
        }
        if (ipc::now_ns() > end_ns + 5'000'000'000) return 19;
    }
}

}  // namespace

TEST(Tbuf, StampsNewestReuseAndMissed) {
    const std::string name = unique_name("tb1");
    Tbuf w = Tbuf::create(name, sizeof(Item));
    Tbuf r = Tbuf::attach(name);
    EXPECT_EQ(r.item_size(), sizeof(Item));
    Item in{}, out{};
    ReadResult res = r.read(&out);
    EXPECT_EQ(res.status, ReadStatus::empty);

    make_item(in, 0);
    const std::int64_t t0 = ipc::now_ns();
    EXPECT_EQ(w.write(&in), 0u);  // the counter-stamp begins at zero
    res = r.read(&out);
    EXPECT_EQ(res.status, ReadStatus::fresh);
    EXPECT_EQ(res.counter, 0u);
    EXPECT_EQ(res.missed, 0u);
    EXPECT_GE(res.time_ns, t0);
    EXPECT_LE(res.time_ns, ipc::now_ns());
    EXPECT_EQ(check_item(out, res), 0);

    res = r.read(&out);  // nothing new: the same item, reused
    EXPECT_EQ(res.status, ReadStatus::reused);
    EXPECT_EQ(res.counter, 0u);

    for (std::uint64_t n = 1; n <= 5; ++n) {
        make_item(in, n);
        EXPECT_EQ(w.write(&in, 1000 + static_cast<std::int64_t>(n)), n);
    }
    res = r.read(&out);  // the newest, and 4 missed
    EXPECT_EQ(res.status, ReadStatus::fresh);
    EXPECT_EQ(res.counter, 5u);
    EXPECT_EQ(res.time_ns, 1005);
    EXPECT_EQ(res.missed, 4u);
    EXPECT_EQ(check_item(out, res), 0);
    EXPECT_EQ(r.missed_total(), 4u);

    // zero-copy writer and reader
    auto* slot = static_cast<Item*>(w.write_slot());
    make_item(*slot, 6);
    EXPECT_EQ(w.publish(2000), 6u);
    ReadResult v;
    const auto* view = static_cast<const Item*>(r.read_view(v));
    EXPECT_EQ(v.status, ReadStatus::fresh);
    EXPECT_EQ(check_item(*view, v), 0);
    r.detach();
    EXPECT_TRUE(w.destroy());
    EXPECT_FALSE(ipc::Segment::exists(name));
}

TEST(Tbuf, FirstReadAfterSeveralWritesCountsTheMissedOnes) {
    const std::string name = unique_name("tb2");
    Tbuf w = Tbuf::create(name, 8);
    std::uint64_t x = 1;
    for (int i = 0; i < 3; ++i) w.write(&x, 0);
    Tbuf r = Tbuf::attach(name);
    const ReadResult res = r.read(&x);
    EXPECT_EQ(res.counter, 2u);
    EXPECT_EQ(res.missed, 2u);  // items 0 and 1 were never read
    w.destroy();
    r.destroy();
}

TEST(Tbuf, CallerSuppliedMemory) {
    auto* block = shared_anon<Block>();
    EXPECT_EQ(required_size(sizeof(Item)), 320u + 3u * 320u);
    Tbuf w = Tbuf::create_in(block, sizeof(Block), sizeof(Item));
    Tbuf r = Tbuf::attach_in(block, sizeof(Block));
    Item in{}, out{};
    make_item(in, 0);
    w.write(&in, 5);
    const ReadResult res = r.read(&out);
    EXPECT_EQ(res.status, ReadStatus::fresh);
    EXPECT_EQ(check_item(out, res), 0);
    EXPECT_THROW(Tbuf::create_in(block->bytes + 8, 1024, 8), ipc::SegmentError);  // misaligned
    EXPECT_THROW(Tbuf::create_in(block, 500, sizeof(Item)), ipc::SegmentError);  // too small
}

TEST(Tbuf, OtherByteOrderIsRefusedOnAttach) {
    auto* block = shared_anon<Block>();
    Tbuf::create_in(block, sizeof(Block), 16);
    auto* hdr = reinterpret_cast<ipc::SegmentHeader*>(block);
    // What a machine of the other byte order would have written.
    hdr->magic = __builtin_bswap32(hdr->magic);
    hdr->byte_order = __builtin_bswap32(hdr->byte_order);
    try {
        Tbuf::attach_in(block, sizeof(Block));
        FAIL() << "attached";
    } catch (const ipc::SegmentError& e) {
        EXPECT_NE(std::string(e.what()).find("other byte order"), std::string::npos) << e.what();
    }
    auto* fresh = shared_anon<Block>();
    EXPECT_THROW(Tbuf::attach_in(fresh, sizeof(Block)), ipc::SegmentError);  // nothing created
}

TEST(Tbuf, AttachByNameRefusesATable) {
    const std::string name = unique_name("tb3");
    ipc::Segment s = ipc::Segment::create(name, 4096, {ipc::ObjectType::svar_table, 1});
    s.publish();
    EXPECT_THROW(Tbuf::attach(name), ipc::SegmentError);
    s.detach_destroy_if_last();
}

// Writer and reader in two processes at full speed: never a torn item, never
// an older item after a newer one, counters and missed counts add up, and the
// reader ends holding the writer's newest item.
TEST(Tbuf, StressAcrossProcesses) {
    const std::string name = unique_name("tbs");
    Tbuf owner = Tbuf::create(name, sizeof(Item));
    struct Board {
        std::atomic<int> go{0};
        std::atomic<int> writer_done{0};
        std::atomic<std::uint64_t> written{0};
        std::atomic<long> fresh{0};
    };
    auto* b = shared_anon<Board>();
    const std::int64_t run = 400'000'000;
    const pid_t writer = fork_child([&] {
        Tbuf w = Tbuf::attach(name);
        Item it{};
        while (!b->go) std::this_thread::yield();
        const std::int64_t end = ipc::now_ns() + run;
        std::uint64_t n = 0;
        while (ipc::now_ns() < end) {
            make_item(it, n);
            if (w.write(&it) != n) return 2;
            ++n;
            b->written.store(n);
        }
        b->writer_done.store(1, std::memory_order_release);
        return 0;
    });
    const pid_t reader = fork_child([&] {
        Tbuf r = Tbuf::attach(name);
        while (!b->go) std::this_thread::yield();
        long fresh = 0;
        const int rc = reader_loop(r, ipc::now_ns() + run, b->writer_done, 1, fresh);
        if (rc == 0 && b->written.load() == 0) return 20;
        b->fresh = fresh;
        return rc;
    });
    b->go = 1;
    EXPECT_EQ(wait_child(writer), 0);
    EXPECT_EQ(wait_child(reader), 0);
    EXPECT_GT(b->written.load(), 1000u);
    EXPECT_GT(b->fresh.load(), 10);
    owner.destroy();
}

TEST(Tbuf, StressAcrossThreadsOverCallerMemory) {
    void* mem = std::aligned_alloc(64, 4096);
    Tbuf w = Tbuf::create_in(mem, 4096, sizeof(Item));
    Tbuf r = Tbuf::attach_in(mem, 4096);
    std::atomic<int> done{0};
    const std::int64_t end = ipc::now_ns() + 300'000'000;
    std::thread writer([&] {
        Item it{};
        for (std::uint64_t n = 0; ipc::now_ns() < end; ++n) {
            make_item(it, n);
            w.write(&it, static_cast<std::int64_t>(n));
        }
        done.store(1, std::memory_order_release);
    });
    long fresh = 0;
    const int rc = reader_loop(r, end, done, 1, fresh);
    writer.join();
    EXPECT_EQ(rc, 0);
    EXPECT_GT(fresh, 10);
    std::free(mem);
}
