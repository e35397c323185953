// The triple buffer: stamps, newest item, missed counts, caller memory, and
// a writer/reader stress test across processes and threads.
#include <gtest/gtest.h>

#include <pwd.h>
#include <signal.h>
#include <sys/stat.h>

#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <string_view>
#include <thread>

#include "chimera/ipc/clock.hpp"
#include "as_user.hpp"
#include "chimera/tbuf.hpp"
#include "sanitizer.hpp"
#include "segment_guard.hpp"
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
                std::uint64_t last_written_expected_min, std::atomic<long>& fresh_reads) {
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
            if (missed_sum + static_cast<std::uint64_t>(fresh_reads.load()) != prev + 1) return 17;
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

// fresh_pending(): a reader's look for a new item (the DDS bridge's spin)
// that leaves the buffer as it was: true from a write until the next read.
TEST(Tbuf, FreshPendingFromAWriteUntilTheNextRead) {
    const std::string name = unique_name("tbp");
    Tbuf w = Tbuf::create(name, sizeof(Item));
    Tbuf r = Tbuf::attach(name);
    Item in{}, out{};
    EXPECT_FALSE(r.fresh_pending()) << "nothing written yet";
    make_item(in, 0);
    (void)w.write(&in);
    EXPECT_TRUE(r.fresh_pending());
    EXPECT_TRUE(r.fresh_pending()) << "looking does not take the item";
    EXPECT_EQ(r.read(&out).status, ReadStatus::fresh);
    EXPECT_FALSE(r.fresh_pending());
    EXPECT_EQ(r.read(&out).status, ReadStatus::reused);
    EXPECT_FALSE(r.fresh_pending());
    make_item(in, 1);
    (void)w.write(&in);
    make_item(in, 2);
    (void)w.write(&in);
    EXPECT_TRUE(r.fresh_pending());
    const ReadResult res = r.read(&out);
    EXPECT_EQ(res.status, ReadStatus::fresh);
    EXPECT_EQ(res.counter, 2u);
    EXPECT_FALSE(r.fresh_pending());
    r.detach();
    w.destroy();
}

TEST(Tbuf, FirstReadAfterSeveralWritesCountsTheMissedOnes) {
    const std::string name = unique_name("tb2");
    Tbuf w = Tbuf::create(name, 8);
    std::uint64_t x = 1;
    for (int i = 0; i < 3; ++i) ASSERT_NE(w.write(&x, 0), kCorrupt);
    Tbuf r = Tbuf::attach(name);
    const ReadResult res = r.read(&x);
    EXPECT_EQ(res.counter, 2u);
    EXPECT_EQ(res.missed, 2u);  // items 0 and 1 were never read
    w.destroy();
    r.destroy();
}

// Whatever number of publishes came between two reads (none, one, two,
// three...), a read takes the newest item once, counts the missed ones, and
// never takes an older item back (an even count leaves the middle slot as the
// reader's take left it, but for the fresh bit).
TEST(Tbuf, AnyNumberOfWritesBetweenReadsGivesTheNewestOnce) {
    const std::string name = unique_name("tb3");
    Tbuf w = Tbuf::create(name, sizeof(Item));
    Tbuf r = Tbuf::attach(name);
    Item in{}, out{};
    std::uint64_t next = 0;
    for (int writes : {1, 2, 0, 3, 4, 1, 1, 6, 0, 0, 5, 2}) {
        for (int i = 0; i < writes; ++i) {
            make_item(in, next);
            ASSERT_EQ(w.write(&in, static_cast<std::int64_t>(next) + 100), next);
            ++next;
        }
        const std::uint64_t before = r.missed_total();
        const ReadResult res = r.read(&out);
        EXPECT_EQ(res.status, writes > 0 ? ReadStatus::fresh : ReadStatus::reused) << writes << " writes";
        EXPECT_EQ(res.counter, next - 1) << writes << " writes";
        EXPECT_EQ(res.time_ns, static_cast<std::int64_t>(next) + 99);
        EXPECT_EQ(res.missed, writes > 1 ? static_cast<std::uint64_t>(writes - 1) : 0u);
        EXPECT_EQ(r.missed_total() - before, res.missed);
        EXPECT_EQ(check_item(out, res), 0);
        EXPECT_EQ(r.read(&out).status, ReadStatus::reused);  // taken once only
        EXPECT_EQ(check_item(out, res), 0);
    }
    r.detach();
    EXPECT_TRUE(w.destroy());
}

TEST(Tbuf, CallerSuppliedMemory) {
    auto* block = shared_anon<Block>();
    EXPECT_EQ(required_size(sizeof(Item)), 384u + 3u * 320u);  // 248-byte items: 256 + 16 stamps -> 320
    Tbuf w = Tbuf::create_in(block, sizeof(Block), sizeof(Item));
    Tbuf r = Tbuf::attach_in(block, sizeof(Block));
    Item in{}, out{};
    make_item(in, 0);
    ASSERT_NE(w.write(&in, 5), kCorrupt);
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
    CHIMERA_NOT_UNDER_TSAN("a forked writer and reader");
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
        // Past `run`, on until the reader has had 100 fresh items (at most 4 s more).
        while (ipc::now_ns() < end || (b->fresh.load() < 100 && ipc::now_ns() < end + 4'000'000'000)) {
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
        const int rc = reader_loop(r, ipc::now_ns() + run, b->writer_done, 1, b->fresh);
        if (rc == 0 && b->written.load() == 0) return 20;
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
    std::atomic<long> fresh{0};
    const std::int64_t end = ipc::now_ns() + 300'000'000;
    // Past 300 ms the writer goes on until the reader has had 100 fresh items
    // (at most 4 s more): on a loaded machine, or a sanitizer build, the reader
    // may get few turns in a fixed time.
    const auto more = [&] { return fresh.load(std::memory_order_relaxed) < 100 && ipc::now_ns() < end + 4'000'000'000; };
    std::thread writer([&] {
        Item it{};
        for (std::uint64_t n = 0; ipc::now_ns() < end || more(); ++n) {
            make_item(it, n);
            if (w.write(&it, static_cast<std::int64_t>(n)) == kCorrupt) break;  // the reader's checks then fail
        }
        done.store(1, std::memory_order_release);
    });
    const int rc = reader_loop(r, end, done, 1, fresh);
    writer.join();
    EXPECT_EQ(rc, 0);
    EXPECT_GT(fresh.load(), 10);
    std::free(mem);
}

// --- kill -9 at any instruction (issue #15.2) -------------------------------------

namespace {

struct alignas(64) KillBoard {
    std::atomic<int> stop{0};
    std::atomic<long> writes{0};      // items published, all writers
    std::atomic<long> fresh{0};       // fresh reads, all readers
    std::atomic<long> torn{0};        // an item whose contents do not match its stamp
    std::atomic<long> backwards{0};   // a fresh item not newer than the last one
    std::atomic<long> gaps{0};        // a writer whose first counter is not the newest + 1
    std::atomic<long> refused{0};     // kCorrupt / ReadStatus::corrupt: the state word damaged
    std::atomic<std::uint64_t> newest{0};  // the newest counter any reader saw + 1
};

// A writer process: attaches, writes item after item in place until killed.
int kill_writer(const std::string& name, KillBoard* b) {
    Tbuf w = Tbuf::attach(name);
    // A successor goes on from the newest published item: no gap, no repeat.
    const std::uint64_t first = w.next_counter();
    if (first == kCorrupt) return b->refused.fetch_add(1), 3;
    if (first < b->newest.load()) b->gaps.fetch_add(1);
    for (std::uint64_t n = first; !b->stop.load(std::memory_order_relaxed); ++n) {
        auto* slot = static_cast<Item*>(w.write_slot());
        if (slot == nullptr) return b->refused.fetch_add(1), 3;
        make_item(*slot, n);
        const std::uint64_t c = w.publish(static_cast<std::int64_t>(n));
        if (c == kCorrupt) return b->refused.fetch_add(1), 3;
        if (c != n) return b->gaps.fetch_add(1), 4;
        b->writes.fetch_add(1, std::memory_order_relaxed);
    }
    return 0;
}

// A reader process: attaches and checks every item until killed.
int kill_reader(const std::string& name, KillBoard* b) {
    Tbuf r = Tbuf::attach(name);
    Item it{};
    std::uint64_t last = 0;
    bool any = false;
    while (!b->stop.load(std::memory_order_relaxed)) {
        const ReadResult res = r.read(&it);
        if (res.status == ReadStatus::corrupt) return b->refused.fetch_add(1), 3;
        if (res.status == ReadStatus::empty) continue;
        if (check_item(it, res) != 0 || res.time_ns != static_cast<std::int64_t>(res.counter))
            b->torn.fetch_add(1);
        if (res.status != ReadStatus::fresh) continue;
        if (any && res.counter <= last) b->backwards.fetch_add(1);
        last = res.counter;
        any = true;
        b->fresh.fetch_add(1, std::memory_order_relaxed);
        std::uint64_t seen = b->newest.load();
        while (seen < res.counter + 1 && !b->newest.compare_exchange_weak(seen, res.counter + 1)) {
        }
    }
    return 0;
}

}  // namespace

// 400 rounds: each SIGKILLs the writer or the reader process (alternately) at
// a random instant, mostly inside write()/publish() or read(), and starts a
// successor. After every kill the middle word and the records are in range and
// the dead process is no longer counted as a user; no reader ever sees a torn
// item or an item older than one it had, and no writer resumes with a repeat
// in the counters (a gap of one is allowed: a writer killed between stamping
// and publishing an item). At the end the last live user frees the segment.
// (With the slot indices in two words, 300 writer kills gave 268 index
// collisions and 593 794 torn items.)
TEST(Tbuf, KillLoopWriterAndReaderStayConsistent) {
    CHIMERA_NOT_UNDER_TSAN("forked writers and readers killed");
    const std::string name = unique_name("tbkill");
    const chimera::test::SegmentGuard cleanup(name.substr(1));
    Tbuf owner = Tbuf::create(name, sizeof(Item));
    ipc::Segment image = ipc::Segment::attach(name, {ipc::ObjectType::tbuf, kLayoutVersion});
    auto* b = shared_anon<KillBoard>();
    pid_t writer = fork_child([&] { return kill_writer(name, b); });
    pid_t reader = fork_child([&] { return kill_reader(name, b); });
    std::srand(static_cast<unsigned>(getpid()));
    constexpr int kRounds = 400;
    int faults = 0, counted_dead = 0;
    for (int round = 0; round < kRounds; ++round) {
        std::this_thread::sleep_for(std::chrono::microseconds(200 + std::rand() % 800));
        pid_t& victim = round % 2 == 0 ? writer : reader;
        kill(victim, SIGKILL);
        EXPECT_EQ(wait_child(victim), 128 + SIGKILL) << "round " << round;
        if (const ipc::Fault f = validate(image.base(), image.size())) {
            ++faults;
            ADD_FAILURE() << "round " << round << ": " << ipc::describe(name, f);
        }
        // owner + image + at most the survivor (which may still be attaching).
        // The kernel drops a dead process's user lock as it dies, even while
        // a reader of its /proc/PID/stat (ps, top) holds its memory: the lock
        // is not on the description its mapping holds (ipc/segment.hpp).
        if (image.users() > 3) ++counted_dead;
        victim = round % 2 == 0 ? fork_child([&] { return kill_writer(name, b); })
                                : fork_child([&] { return kill_reader(name, b); });
    }
    b->stop.store(1);
    EXPECT_EQ(wait_child(writer), 0);
    EXPECT_EQ(wait_child(reader), 0);
    std::printf("tbuf kill loop: %d rounds (%d writers, %d readers killed), %ld items written, "
                "%ld fresh reads; torn %ld, backwards %ld, gaps %ld, refused %ld, bad state %d, "
                "dead users counted %d\n",
                kRounds, kRounds / 2, kRounds / 2, b->writes.load(), b->fresh.load(), b->torn.load(),
                b->backwards.load(), b->gaps.load(), b->refused.load(), faults, counted_dead);
    EXPECT_EQ(b->torn.load(), 0);
    EXPECT_EQ(b->backwards.load(), 0);
    EXPECT_EQ(b->gaps.load(), 0);
    EXPECT_EQ(b->refused.load(), 0);
    EXPECT_EQ(counted_dead, 0);
    EXPECT_GT(b->writes.load(), 1000);
    EXPECT_GT(b->fresh.load(), 100);
    image.detach();
    EXPECT_TRUE(owner.destroy()) << "killed users kept the segment";
    EXPECT_TRUE(cleanup.present().empty()) << "leaked segment " << name;
}

// --- memory another process writes is bounded before use (issue #15.3) ------------

// Each field of a live buffer that a process reads from shared memory,
// corrupted by "another process" (a second mapping): attach refuses a bad
// geometry naming the segment; a damaged state word makes read() and write()
// refuse with the segment named, and nothing is read or written outside.
// Found by fuzz/fuzz_tbuf: a writer that took over a buffer whose newest
// item's counter-stamp was 2^64 - 1 went on from it, so its item carried
// kCorrupt as its counter (a write that looked refused) and the stamp wrapped
// to 0, which the reader takes for a slot that never held an item.
TEST(Tbuf, AWriterRefusesToGoOnFromACounterStampNoWriteCouldMake) {
    auto* block = shared_anon<Block>();
    Tbuf first = Tbuf::create_in(block, sizeof(Block), sizeof(Item));
    Item item{};
    ASSERT_EQ(first.write(&item, 1), 0u);
    auto& h = *reinterpret_cast<detail::Header*>(block);
    const std::uint32_t middle = h.middle.load() & detail::kSlotMask;
    auto* newest = reinterpret_cast<detail::Stamp*>(reinterpret_cast<std::byte*>(block) + h.slots_offset +
                                                    middle * h.slot_stride + h.stamp_offset);
    for (std::uint64_t bad : {~std::uint64_t{0}, detail::kMaxSeq}) {
        newest->seq = bad;
        Tbuf writer = Tbuf::attach_in(block, sizeof(Block));
        EXPECT_EQ(writer.write(&item, 2), kCorrupt);
        EXPECT_NE(writer.fault_message().find("counter-stamp"), std::string::npos) << writer.fault_message();
    }
    newest->seq = detail::kMaxSeq - 1;  // the highest a writer goes on from
    Tbuf writer = Tbuf::attach_in(block, sizeof(Block));
    EXPECT_EQ(writer.write(&item, 3), detail::kMaxSeq - 1);
    Tbuf reader = Tbuf::attach_in(block, sizeof(Block));
    const ReadResult r = reader.read(&item);
    EXPECT_EQ(r.status, ReadStatus::fresh);
    EXPECT_EQ(r.counter, detail::kMaxSeq - 1);
}

TEST(Tbuf, CorruptFieldsAreRefusedNamingTheSegment) {
    const std::string name = unique_name("tbbad");
    Tbuf w = Tbuf::create(name, 24);
    Tbuf r = Tbuf::attach(name);
    ipc::Segment raw = ipc::Segment::attach(name, {ipc::ObjectType::tbuf, kLayoutVersion});
    auto& h = *static_cast<detail::Header*>(raw.base());
    std::byte item[24] = {};
    ASSERT_EQ(w.write(item, 1), 0u);

    // Geometry: checked on attach (the live handles keep what they checked).
    const struct {
        std::uint64_t detail::Header::*field;
        std::uint64_t bad;
        const char* named;
    } geometry[] = {
        {&detail::Header::item_size, std::uint64_t{1} << 40, "item size"},
        {&detail::Header::item_size, 1000, "slot stride"},
        {&detail::Header::slot_stride, 1 << 20, "slot stride"},
        {&detail::Header::stamp_offset, 4000, "stamp offset"},
        {&detail::Header::slots_offset, 1 << 30, "slots offset"},
    };
    for (const auto& g : geometry) {
        const std::uint64_t good = h.*g.field;
        h.*g.field = g.bad;
        try {
            Tbuf::attach(name);
            ADD_FAILURE() << g.named << ": attached";
        } catch (const ipc::SegmentError& e) {
            const std::string what = e.what();
            EXPECT_NE(what.find("segment " + name), std::string::npos) << what;
            EXPECT_NE(what.find(g.named), std::string::npos) << what;
        }
        EXPECT_TRUE(validate(raw.base(), raw.size()));
        EXPECT_NE(w.write(item, 2), kCorrupt) << "a live writer keeps the geometry it checked";
        h.*g.field = good;
        ASSERT_FALSE(validate(raw.base(), raw.size()));
        ReadResult res = r.read(item);
        ASSERT_EQ(res.status, ReadStatus::fresh);
        ASSERT_NE(w.write(item, 3), kCorrupt);
        ASSERT_EQ(r.read(item).status, ReadStatus::fresh);
    }

    // The middle word: a slot number 3 or stray bits (both sides refuse), the
    // reader's own slot (the reader refuses), the writer's own slot (the
    // writer refuses). The reader refuses before its exchange; the writer
    // after its exchange, putting the damaged word back (nothing published).
    // Each side can only see a slot given twice when one of the two is its
    // own (a slot number in range is no read outside the buffer).
    enum Bad { slot_3, stray_bit, readers_own, writers_own };
    for (Bad bad_kind : {slot_3, stray_bit, readers_own, writers_own}) {
        // Both hold their roles (taken over again after the last refusal).
        ASSERT_NE(w.write(item, 6), kCorrupt);
        ASSERT_EQ(r.read(item).status, ReadStatus::fresh);
        const std::uint32_t good = h.middle.load();
        const std::uint32_t bad = bad_kind == slot_3       ? 3u | detail::kFresh
                                  : bad_kind == stray_bit  ? (good & detail::kSlotMask) | 1u << 9
                                  : bad_kind == readers_own ? static_cast<std::uint32_t>(h.reader.record.load()) | detail::kFresh
                                                            : detail::record_slot(h.writer.record.load()) | detail::kFresh;
        const bool reader_sees = bad_kind != writers_own, writer_sees = bad_kind != readers_own;
        h.middle.store(bad);
        if (reader_sees) {
            ReadResult res = r.read(item);
            EXPECT_EQ(res.status, ReadStatus::corrupt);
            EXPECT_NE(r.fault_message().find("segment " + name + ": middle word"), std::string::npos)
                << r.fault_message();
            EXPECT_EQ(r.read_view(res), nullptr);
        }
        if (writer_sees) {
            EXPECT_EQ(w.write(item, 7), kCorrupt);
            EXPECT_NE(w.fault_message().find("segment " + name + ": middle word"), std::string::npos)
                << w.fault_message();
            EXPECT_EQ(h.middle.load(), bad) << "the writer put the damaged word back";
        }
        // attach checks the word's range too
        if (reader_sees && writer_sees) {
            EXPECT_THROW(Tbuf::attach(name), ipc::SegmentError);
        }
        h.middle.store(good);
    }
    const std::uint32_t good = h.middle.load();
    // After refusing, both take their roles over again from the mended word.
    ASSERT_NE(w.write(item, 8), kCorrupt);
    ASSERT_EQ(r.read(item).status, ReadStatus::fresh);
    // A writer whose first write meets a damaged word refuses and names it.
    {
        Tbuf fresh_writer = Tbuf::attach(name);
        h.middle.store(3);
        EXPECT_EQ(fresh_writer.write(item, 9), kCorrupt);
        EXPECT_EQ(fresh_writer.write_slot(), nullptr);
        EXPECT_NE(fresh_writer.fault_message().find("segment " + name), std::string::npos);
        h.middle.store(good);
    }
    // The records: a slot number out of range, or a stray bit in the
    // reader's, is refused on attach; the writer's also by a handle taking
    // the role over, and an exact record naming the middle slot there too.
    const std::uint64_t writers = h.writer.record.load(), readers = h.reader.record.load();
    const std::uint64_t published = detail::record_published(writers);
    for (std::uint64_t bad : {detail::make_record(3, published), detail::make_record(h.middle.load() & detail::kSlotMask, published)}) {
        Tbuf successor = Tbuf::attach(name);
        h.writer.record.store(bad);
        if (detail::record_slot(bad) == 3) {
            EXPECT_THROW(Tbuf::attach(name), ipc::SegmentError);
        }
        EXPECT_EQ(successor.write(item, 10), kCorrupt) << bad;
        EXPECT_NE(successor.fault_message().find("segment " + name + ": writer's slot record"), std::string::npos)
            << successor.fault_message();
        h.writer.record.store(writers);
    }
    for (std::uint64_t bad : {std::uint64_t{3}, readers | 1u << 5}) {
        h.reader.record.store(bad);
        try {
            Tbuf::attach(name);
            ADD_FAILURE() << "attached with a reader's record " << bad;
        } catch (const ipc::SegmentError& e) {
            EXPECT_NE(std::string(e.what()).find("reader's slot record"), std::string::npos) << e.what();
        }
        h.reader.record.store(readers);
    }
    raw.detach();
    r.detach();
    EXPECT_TRUE(w.destroy());
}

// A second handle writing while the first still holds the writer's slot:
// the first one's next publish is refused (its slot moved), not published
// into a slot the reader may hold.
TEST(Tbuf, AWriterWhoseSlotAnotherWriterMovedRefuses) {
    const std::string name = unique_name("tbtwo");
    Tbuf a = Tbuf::create(name, 8);
    Tbuf b = Tbuf::attach(name);
    std::uint64_t x = 1;
    EXPECT_EQ(a.write(&x, 1), 0u);
    EXPECT_EQ(b.write(&x, 2), 1u);  // b takes the role: it starts from the state word
    EXPECT_EQ(a.write(&x, 3), kCorrupt);
    EXPECT_NE(a.fault_message().find("another writer"), std::string::npos) << a.fault_message();
    EXPECT_EQ(a.write(&x, 4), 2u);  // after refusing it starts from the state word again
    b.detach();
    EXPECT_TRUE(a.destroy());
}

// --- taking a role over from a side killed inside its exchange ----------------------

namespace {

// The owner word of a process that has exited and been reaped.
std::uint64_t dead_owner() {
    const pid_t pid = fork_child([] { return 0; });
    EXPECT_EQ(wait_child(pid), 0);
    return static_cast<std::uint64_t>(static_cast<std::uint32_t>(pid)) << 32 | static_cast<std::uint32_t>(pid);
}

// Slot `i` of the buffer at `h`: its item and its stamps.
Item& item_at(detail::Header& h, std::uint32_t i) {
    return *reinterpret_cast<Item*>(reinterpret_cast<std::byte*>(&h) + h.slots_offset + i * h.slot_stride);
}
detail::Stamp& stamp_at(detail::Header& h, std::uint32_t i) {
    return *reinterpret_cast<detail::Stamp*>(reinterpret_cast<std::byte*>(&h) + h.slots_offset +
                                             i * h.slot_stride + h.stamp_offset);
}

// A buffer laid out in `block` after `steps` ('w': the writer writes the next
// item, 'r': the reader reads), both handles then detached (their records
// exact).
detail::Header& buffer_after(Block* block, std::string_view steps) {
    Tbuf w = Tbuf::create_in(block, sizeof(Block), sizeof(Item));
    Tbuf r = Tbuf::attach_in(block, sizeof(Block));
    Item it{};
    std::uint64_t next = 0;
    for (const char step : steps) {
        if (step == 'w') {
            make_item(it, next);
            EXPECT_EQ(w.write(&it, static_cast<std::int64_t>(next)), next);
            ++next;
        } else {
            EXPECT_EQ(r.read(&it).status, ReadStatus::fresh);
        }
    }
    return *reinterpret_cast<detail::Header*>(block);
}

// The writer's item `n`, complete and stamped in its slot, as a writer
// killed inside its publish leaves it (no record after); returns the slot.
std::uint32_t stamp_unrecorded(detail::Header& h, std::uint64_t n) {
    const std::uint64_t record = h.writer.record.load();
    const std::uint32_t slot = detail::record_slot(record);
    make_item(item_at(h, slot), n);
    stamp_at(h, slot) = detail::Stamp{static_cast<std::int64_t>(n), detail::record_published(record) + 1};
    return slot;
}

// A reader's exchange, marked, and no record after it (killed there).
void reader_exchange_unrecorded(detail::Header& h) {
    const auto given = static_cast<std::uint32_t>(h.reader.record.load());
    h.reader.record.store(given | detail::kExchanging);
    (void)h.middle.exchange(given);
}

// `r` reads item `n`, fresh and whole. Returns the read's result.
ReadResult read_fresh(Tbuf& r, std::uint64_t n) {
    Item out{};
    const ReadResult res = r.read(&out);
    EXPECT_EQ(res.status, ReadStatus::fresh) << "item " << n << ": " << r.fault_message();
    EXPECT_EQ(res.counter, n);
    EXPECT_EQ(check_item(out, res), 0);
    return res;
}

// Items flow again after a take-over: `w` writes item `n`, and `r` reads it
// fresh and whole. Returns the read's result.
ReadResult write_and_read_fresh(Tbuf& w, Tbuf& r, std::uint64_t n) {
    Item it{};
    make_item(it, n);
    EXPECT_EQ(w.write(&it, static_cast<std::int64_t>(n)), n);
    return read_fresh(r, n);
}

// The owner word of a live process (`pid`, single-threaded).
std::uint64_t owner_of(pid_t pid) {
    return static_cast<std::uint64_t>(static_cast<std::uint32_t>(pid)) << 32 | static_cast<std::uint32_t>(pid);
}

}  // namespace

// The write of an item half done when the writer is killed stays with the
// writer role, whatever the reader did: here the reader died between its
// exchange and its record first, then the writer went on publishing and died
// while writing. The writer's successor takes the slot of its record (exact:
// no newer stamp in it) and completes the next item there; the reader's
// successor never gets that slot (its "reused" reads would return a torn
// item).
TEST(Tbuf, AHalfWrittenItemStaysWithTheWriterRoleAfterBothSidesDied) {
    CHIMERA_NOT_UNDER_TSAN("a forked process as a dead owner");
    auto* block = shared_anon<Block>();
    auto& h = *reinterpret_cast<detail::Header*>(block);
    Tbuf w = Tbuf::create_in(block, sizeof(Block), sizeof(Item));
    Item it{};
    {
        Tbuf r = Tbuf::attach_in(block, sizeof(Block));
        make_item(it, 0);
        ASSERT_EQ(w.write(&it, 0), 0u);
        ASSERT_EQ(r.read(&it).status, ReadStatus::fresh);
        make_item(it, 1);
        ASSERT_EQ(w.write(&it, 1), 1u);
    }
    reader_exchange_unrecorded(h);  // it took item 1, then died
    h.reader.owner.store(dead_owner());
    make_item(it, 2);
    ASSERT_EQ(w.write(&it, 2), 2u);
    // Item 3 half written, then the writer is gone.
    auto* half = static_cast<Item*>(w.write_slot());
    ASSERT_NE(half, nullptr);
    half->counter = 3;
    const std::uint32_t writers = detail::record_slot(h.writer.record.load());
    w.detach();

    // The writer's successor first: the reader's record (of a dead reader,
    // stale) must not decide for it.
    Tbuf w2 = Tbuf::attach_in(block, sizeof(Block));
    EXPECT_EQ(w2.next_counter(), 3u);
    EXPECT_EQ(detail::record_slot(h.writer.record.load()), writers) << "the writer's successor takes its record's slot";
    Tbuf r2 = Tbuf::attach_in(block, sizeof(Block));
    (void)read_fresh(r2, 2);
    EXPECT_NE(h.reader.record.load(), writers) << "the reader got the half-written slot";
    Item out{};
    const ReadResult res = r2.read(&out);
    EXPECT_EQ(res.status, ReadStatus::reused);
    EXPECT_EQ(check_item(out, res), 0);

    (void)write_and_read_fresh(w2, r2, 3);
}

// A writer killed inside its publish (its slot's stamp newer than its
// record's) has its slot worked out from the reader's record. While the
// reader is itself inside its exchange (its record marked) and alive — here a
// stopped process — its successor waits, and refuses after the bound naming
// the exchange; once the reader is dead too it takes a slot (no repeat of a
// counter: the dead writer's stamped item 2 was never published, so 2 is
// skipped), and the reader's successor takes the remaining one.
TEST(Tbuf, AWriterTakingOverWaitsForALiveReaderInsideItsExchangeNotForADeadOne) {
    CHIMERA_NOT_UNDER_TSAN("forked processes as owners");
    auto* block = shared_anon<Block>();
    detail::Header& h = buffer_after(block, "wrw");
    (void)stamp_unrecorded(h, 2);    // the writer died before its exchange
    reader_exchange_unrecorded(h);  // the reader took item 1, and stopped there

    const pid_t live = fork_child([] { pause(); return 0; });
    h.reader.owner.store(owner_of(live));
    Tbuf w2 = Tbuf::attach_in(block, sizeof(Block));
    Item it{};
    make_item(it, 3);
    const std::int64_t t0 = ipc::now_ns();
    EXPECT_EQ(w2.write(&it, 3), kCorrupt);
    EXPECT_GE(ipc::now_ns() - t0, 90'000'000) << "waited for the live reader";
    EXPECT_NE(w2.fault_message().find("stopped inside an exchange"), std::string::npos) << w2.fault_message();
    kill(live, SIGKILL);
    EXPECT_EQ(wait_child(live), 128 + SIGKILL);

    EXPECT_EQ(w2.write(&it, 3), 3u) << w2.fault_message();
    Tbuf r2 = Tbuf::attach_in(block, sizeof(Block));
    Item out{};
    const ReadResult res = r2.read(&out);
    EXPECT_EQ(res.status, ReadStatus::fresh);
    EXPECT_EQ(res.counter, 3u);
    EXPECT_EQ(check_item(out, res), 0);
    const std::uint32_t w_slot = detail::record_slot(h.writer.record.load());
    const auto r_slot = static_cast<std::uint32_t>(h.reader.record.load());
    const std::uint32_t m_slot = h.middle.load() & detail::kSlotMask;
    EXPECT_TRUE(w_slot != r_slot && w_slot != m_slot && r_slot != m_slot) << w_slot << r_slot << m_slot;
}

// A writer killed after its exchange, before its record: the reader takes
// the item it published, and the writer's successor works out the slot the
// dead writer got back and goes on from the item (no repeat, no gap).
TEST(Tbuf, AReaderTakingOverAfterAWriterKilledInsideItsExchangeGetsItsItem) {
    CHIMERA_NOT_UNDER_TSAN("a forked process as a dead owner");
    auto* block = shared_anon<Block>();
    detail::Header& h = buffer_after(block, "ww");
    // The writer's item 2, stamped and exchanged, and no record.
    const std::uint32_t back = stamp_unrecorded(h, 2);
    const std::uint32_t got = h.middle.exchange(back | detail::kFresh) & detail::kSlotMask;
    h.writer.owner.store(dead_owner());

    Tbuf r = Tbuf::attach_in(block, sizeof(Block));
    (void)read_fresh(r, 2);

    Tbuf w2 = Tbuf::attach_in(block, sizeof(Block));
    EXPECT_EQ(w2.next_counter(), 3u);
    EXPECT_EQ(detail::record_slot(h.writer.record.load()), got) << "the slot the dead writer got back";
    EXPECT_EQ(write_and_read_fresh(w2, r, 3).missed, 0u);
}

// A writer stopped inside its publish (here a live, stopped process) after
// its exchange, whose slot a reader then took before it died: the writer's
// record still names the slot it gave, which is no longer the middle one, so
// only the stamp (newer than the record's) says the record is not the
// writer's slot. The reader's successor must wait for it — deriving its slot
// from that record would give it the writer's live slot — and refuse after
// the bound; once the writer is dead, the successors of both sides share the
// slots out and items flow again.
TEST(Tbuf, AReaderTakingOverWaitsForALiveWriterInsidePublishWhoseGivenSlotADeadReaderTook) {
    CHIMERA_NOT_UNDER_TSAN("forked processes as owners");
    auto* block = shared_anon<Block>();
    detail::Header& h = buffer_after(block, "wr");
    // The writer stamps item 1 and exchanges it in; no record yet.
    const std::uint32_t given = stamp_unrecorded(h, 1);
    (void)h.middle.exchange(given | detail::kFresh);
    const pid_t live = fork_child([] { pause(); return 0; });
    h.writer.owner.store(owner_of(live));
    // A reader takes item 1 (its whole exchange and record), then dies.
    const auto front = static_cast<std::uint32_t>(h.reader.record.load());
    ASSERT_EQ(h.middle.exchange(front) & detail::kSlotMask, given);
    h.reader.record.store(given);
    h.reader.owner.store(dead_owner());
    ASSERT_NE(detail::record_slot(h.writer.record.load()), h.middle.load() & detail::kSlotMask);

    Tbuf r2 = Tbuf::attach_in(block, sizeof(Block));
    Item out{};
    const std::int64_t t0 = ipc::now_ns();
    EXPECT_EQ(r2.read(&out).status, ReadStatus::corrupt);
    EXPECT_GE(ipc::now_ns() - t0, 90'000'000) << "waited for the live writer";
    EXPECT_NE(r2.fault_message().find("stopped inside an exchange"), std::string::npos) << r2.fault_message();
    kill(live, SIGKILL);
    EXPECT_EQ(wait_child(live), 128 + SIGKILL);

    // Both died inside their exchanges: every item is complete, and any slot
    // but the middle one may be the reader's now (the dead writer's too).
    ReadResult res = r2.read(&out);
    EXPECT_NE(res.status, ReadStatus::corrupt) << r2.fault_message();
    Tbuf w2 = Tbuf::attach_in(block, sizeof(Block));
    EXPECT_EQ(w2.next_counter(), 2u);
    (void)write_and_read_fresh(w2, r2, 2);
    const std::uint32_t w_slot = detail::record_slot(h.writer.record.load());
    const auto r_slot = static_cast<std::uint32_t>(h.reader.record.load());
    EXPECT_TRUE(w_slot != r_slot && w_slot != (h.middle.load() & detail::kSlotMask)) << w_slot << r_slot;
}


// Squatted names (issue #29.5): any user may make /dev/shm/chimera.X... first,
// a real triple buffer and all. A fake of nobody's whose creator is dead does
// not stop root's writer: its create removes it, saying whose it was, and
// root's buffer then works.
TEST(Tbuf, NobodysFakeUnderTheNameDoesNotStopRootsWriter) {
    CHIMERA_NOT_UNDER_TSAN("forked users");
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    const std::string name = unique_name("tbsquat");
    const chimera::test::SegmentGuard cleanup(name.substr(1));
    const pid_t squatter = fork_child([&] {
        if (!chimera::test::become_nobody({})) return 10;
        Tbuf fake = Tbuf::create(name, sizeof(Item));
        _exit(0);  // no destructor: the file stays, naming this dead child
        return 0;
    });
    ASSERT_EQ(wait_child(squatter), 0);
    const passwd* nobody = getpwnam("nobody");
    ASSERT_NE(nobody, nullptr);
    testing::internal::CaptureStderr();
    Tbuf w = Tbuf::create(name, sizeof(Item));
    EXPECT_EQ(testing::internal::GetCapturedStderr(),
              "chimera: segment " + name + ", nobody's (uid " + std::to_string(nobody->pw_uid) +
                  ", mode 0600): squatted: it is another user's, and the creator its header names, pid " +
                  std::to_string(squatter) + ", is not running: removed, to be created anew\n");
    struct stat st {};
    ASSERT_EQ(::stat(("/dev/shm" + name).c_str(), &st), 0);
    EXPECT_EQ(st.st_uid, ::geteuid());
    Tbuf r = Tbuf::attach(name);
    Item in{}, out{};
    make_item(in, 0);
    EXPECT_EQ(w.write(&in), 0u);
    const ReadResult res = r.read(&out);
    EXPECT_EQ(res.status, ReadStatus::fresh);
    EXPECT_EQ(check_item(out, res), 0);
    r.detach();
    EXPECT_TRUE(w.destroy());
}

// A writer that is not root meets another user's triple buffer it may not
// read (root's, its creator dead): refused, told whose it is and what to do.
TEST(Tbuf, ANonRootWriterMeetingAnotherUsersBufferIsToldWhoseItIs) {
    CHIMERA_NOT_UNDER_TSAN("forked users");
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    const std::string name = unique_name("tbroots");
    const chimera::test::SegmentGuard cleanup(name.substr(1));
    ASSERT_EQ(wait_child(fork_child([&] {
                  Tbuf fake = Tbuf::create(name, sizeof(Item));
                  _exit(0);
                  return 0;
              })),
              0);
    EXPECT_EQ(chimera::test::eperm_refusal_as_nobody<ipc::SegmentError>([&] { Tbuf::create(name, sizeof(Item)); }),
              "segment " + name + ": taken by another user's file, which this user may not read: it is root's (uid 0, "
              "mode 0600), and only root may remove it (sudo rm /dev/shm" + name + "), then start again");
    EXPECT_TRUE(ipc::Segment::exists(name));  // not removed: only root may
}
