// The sampler ring and the table-bound sampler: every sample delivered exactly
// once while a reader keeps up, loss counted exactly when it does not, readers
// independent of each other, a killed writer or reader leaving nothing broken,
// and the sampling path free of allocation and system calls.
#include <gtest/gtest.h>

#include <signal.h>

#include <atomic>
#include <cstdlib>
#include <thread>
#include <vector>

#include "alloc_counter.hpp"
#include "chimera/ipc/clock.hpp"
#include "chimera/sampler.hpp"
#include "process.hpp"
#include "sanitizer.hpp"
#include "segment_guard.hpp"
#include "syscall_counter.hpp"

using namespace chimera;
using namespace chimera::sampler;
using chimera::test::fork_child;
using chimera::test::wait_child;
using chimera::test::wait_for;

namespace {

std::string prefix() { return "chimera.samptest" + std::to_string(getpid()) + "."; }
std::string unique_name(const std::string& what) { return "/" + prefix() + what; }

std::vector<Channel> channels(std::size_t n) {
    std::vector<Channel> c;
    for (std::size_t i = 0; i < n; ++i) c.push_back(Channel{"V", i, "V[" + std::to_string(i) + "]"});
    return c;
}
std::vector<std::uint32_t> zeros(std::size_t n) { return std::vector<std::uint32_t>(n, 0); }

// Sample n: channel i holds n * 10 + i, time n * 1000, cycle n + 7: a torn or
// misplaced sample shows.
void publish_n(RingWriter& w, std::uint64_t n) {
    double row[kMaxChannels];
    for (std::size_t i = 0; i < w.channels(); ++i) row[i] = static_cast<double>(n * 10 + i);
    w.publish_row(static_cast<std::int64_t>(n * 1000), n + 7, row);
}

// Checks the rows read; returns the sample numbers in order (from the time stamps).
struct Rows {
    std::vector<std::int64_t> t;
    std::vector<std::uint64_t> cycle;
    std::vector<double> v;
    explicit Rows(std::size_t rows, std::size_t width) : t(rows), cycle(rows), v(rows * width) {}
};

::testing::AssertionResult whole(const Rows& r, std::size_t k, std::size_t width) {
    const std::uint64_t n = static_cast<std::uint64_t>(r.t[k] / 1000);
    if (r.cycle[k] != n + 7) return ::testing::AssertionFailure() << "row " << k << ": cycle " << r.cycle[k];
    for (std::size_t i = 0; i < width; ++i)
        if (r.v[k * width + i] != static_cast<double>(n * 10 + i))
            return ::testing::AssertionFailure() << "row " << k << " (sample " << n << ") channel " << i
                                                 << " holds " << r.v[k * width + i];
    return ::testing::AssertionSuccess();
}

}  // namespace

TEST(SamplerRing, GeometryAndNames) {
    const test::SegmentGuard cleanup(prefix());
    const std::string name = unique_name("geo");
    RingWriter w = RingWriter::create(name, channels(3), zeros(3), 1024, 500.0);
    RingReader r = RingReader::attach(name);
    EXPECT_EQ(r.channels(), 3u);
    EXPECT_EQ(r.capacity(), 1024u);
    EXPECT_EQ(r.rate_hz(), 500.0);
    EXPECT_EQ(r.channel_names(), (std::vector<std::string>{"V[0]", "V[1]", "V[2]"}));
    EXPECT_EQ(r.writer_pid(), getpid());
    EXPECT_EQ(required_size(3, 1024), 192u + 192u + 1024u * 64u);
    EXPECT_EQ(capacity_for(1000, 2.0), 2048u);
    EXPECT_EQ(capacity_for(10, 1.0), 1024u);
    EXPECT_EQ(capacity_for(1e9, 1e9), kMaxCapacity);
    EXPECT_THROW(RingWriter::create(unique_name("bad"), channels(3), zeros(3), 1000, 1.0), Error);
    EXPECT_THROW(RingWriter::create(unique_name("bad"), {}, {}, 1024, 1.0), Error);
}

TEST(SamplerRing, ReaderStartsAtTheNewestAndRewinds) {
    const test::SegmentGuard cleanup(prefix());
    const std::string name = unique_name("start");
    RingWriter w = RingWriter::create(name, channels(2), zeros(2), 16, 1.0);
    for (std::uint64_t n = 0; n < 5; ++n) publish_n(w, n);
    RingReader r = RingReader::attach(name);
    Rows rows(32, 2);
    ReadCount c = r.read(rows.t.data(), rows.cycle.data(), rows.v.data(), 32);
    EXPECT_EQ(c.samples, 0u);
    publish_n(w, 5);
    c = r.read(rows.t.data(), rows.cycle.data(), rows.v.data(), 32);
    ASSERT_EQ(c.samples, 1u);
    EXPECT_EQ(rows.t[0], 5000);
    EXPECT_TRUE(whole(rows, 0, 2));
    r.rewind();
    c = r.read(rows.t.data(), rows.cycle.data(), rows.v.data(), 32);
    ASSERT_EQ(c.samples, 6u);
    EXPECT_EQ(c.lost, 0u);
    for (std::size_t k = 0; k < 6; ++k) {
        EXPECT_EQ(rows.t[k], static_cast<std::int64_t>(k * 1000));
        EXPECT_TRUE(whole(rows, k, 2));
    }
}

TEST(SamplerRing, LossIsCountedExactlyWhenTheReaderFallsBehind) {
    const test::SegmentGuard cleanup(prefix());
    const std::string name = unique_name("loss");
    constexpr std::size_t kCap = 64;
    RingWriter w = RingWriter::create(name, channels(4), zeros(4), kCap, 1.0);
    RingReader r = RingReader::attach(name);
    Rows rows(1000, 4);
    // 3 laps and 5: the reader gets the newest 64, and knows it lost the rest.
    for (std::uint64_t n = 0; n < 3 * kCap + 5; ++n) publish_n(w, n);
    ReadCount c = r.read(rows.t.data(), rows.cycle.data(), rows.v.data(), 1000);
    EXPECT_EQ(c.samples, kCap);
    EXPECT_EQ(c.lost, 2 * kCap + 5);
    EXPECT_EQ(rows.t[0], static_cast<std::int64_t>((2 * kCap + 5) * 1000));
    for (std::size_t k = 0; k < c.samples; ++k) ASSERT_TRUE(whole(rows, k, 4));
    // Caught up; then 7 more than fit while it reads 10 of them.
    for (std::uint64_t n = 3 * kCap + 5; n < 3 * kCap + 15; ++n) publish_n(w, n);
    c = r.read(rows.t.data(), rows.cycle.data(), rows.v.data(), 10);
    EXPECT_EQ(c.samples, 10u);
    EXPECT_EQ(c.lost, 0u);
    for (std::uint64_t n = 3 * kCap + 15; n < 4 * kCap + 22; ++n) publish_n(w, n);
    c = r.read(rows.t.data(), rows.cycle.data(), rows.v.data(), 1000);
    EXPECT_EQ(c.lost, 7u);
    EXPECT_EQ(c.samples, kCap);
    EXPECT_EQ(r.lost_total(), 2 * kCap + 5 + 7);
    EXPECT_EQ(r.position(), 4 * kCap + 22);
    // A chunk smaller than what is there: the rest waits for the next read.
    for (std::uint64_t n = 4 * kCap + 22; n < 4 * kCap + 30; ++n) publish_n(w, n);
    c = r.read(rows.t.data(), rows.cycle.data(), rows.v.data(), 3);
    EXPECT_EQ(c.samples, 3u);
    c = r.read(rows.t.data(), rows.cycle.data(), rows.v.data(), 1000);
    EXPECT_EQ(c.samples, 5u);
    EXPECT_EQ(c.lost, 0u);
}

TEST(SamplerRing, ReadersAreIndependent) {
    const test::SegmentGuard cleanup(prefix());
    const std::string name = unique_name("two");
    RingWriter w = RingWriter::create(name, channels(1), zeros(1), 32, 1.0);
    RingReader fast = RingReader::attach(name);
    RingReader slow = RingReader::attach(name);
    Rows rows(64, 1);
    std::uint64_t fast_got = 0;
    for (std::uint64_t n = 0; n < 100; ++n) {
        publish_n(w, n);
        const ReadCount c = fast.read(rows.t.data(), rows.cycle.data(), rows.v.data(), 64);
        ASSERT_EQ(c.samples, 1u);
        ASSERT_EQ(rows.t[0], static_cast<std::int64_t>(n * 1000));
        fast_got += c.samples;
    }
    const ReadCount c = slow.read(rows.t.data(), rows.cycle.data(), rows.v.data(), 64);
    EXPECT_EQ(fast_got, 100u);
    EXPECT_EQ(fast.lost_total(), 0u);
    EXPECT_EQ(c.samples, 32u);
    EXPECT_EQ(c.lost, 68u);
}

// Writer and reader on two threads at full speed: a reader that keeps up (the
// writer waits for it, as a fast enough reader would be) gets every sample
// exactly once, in order; a reader that sleeps loses samples, and what it
// got plus what it counted lost is exactly what was written, with no sample
// twice and none torn.
TEST(SamplerRing, ExactlyOnceWhileTheReaderKeepsUpAndExactLossWhenNot) {
    const test::SegmentGuard cleanup(prefix());
    for (const bool keeps_up : {true, false}) {
        const std::string name = unique_name(keeps_up ? "race1" : "race2");
        constexpr std::size_t kCap = 256, kWidth = 8;
        constexpr std::uint64_t kSamples = 50000;
        RingWriter w = RingWriter::create(name, channels(kWidth), zeros(kWidth), kCap, 1.0);
        RingReader r = RingReader::attach(name);
        std::atomic<std::uint64_t> reader_pos{0};
        std::atomic<bool> done{false};
        std::thread writer([&] {
            for (std::uint64_t n = 0; n < kSamples; ++n) {
                while (keeps_up && n - reader_pos.load(std::memory_order_acquire) >= kCap / 2)
                    std::this_thread::yield();
                publish_n(w, n);
            }
            done.store(true, std::memory_order_release);
        });
        Rows rows(64, kWidth);
        std::uint64_t got = 0, lost = 0, next_expected = 0, reads = 0;
        bool ok = true;
        for (;;) {
            const bool finished = done.load(std::memory_order_acquire);
            const ReadCount c = r.read(rows.t.data(), rows.cycle.data(), rows.v.data(), 64);
            lost += c.lost;
            for (std::size_t k = 0; k < c.samples && ok; ++k) {
                const std::uint64_t n = static_cast<std::uint64_t>(rows.t[k] / 1000);
                if (!whole(rows, k, kWidth) || n < next_expected) ok = false;  // torn, duplicated or reordered
                if (keeps_up && n != next_expected) ok = false;              // a gap
                next_expected = n + 1;
            }
            got += c.samples;
            reader_pos.store(r.position(), std::memory_order_release);
            if (!keeps_up && ++reads % 8 == 0) std::this_thread::sleep_for(std::chrono::microseconds(200));
            if (finished && r.position() == kSamples) break;
        }
        writer.join();
        EXPECT_TRUE(ok) << (keeps_up ? "keeping up" : "falling behind");
        EXPECT_EQ(got + lost, kSamples);
        EXPECT_EQ(lost, r.lost_total());
        if (keeps_up) {
            EXPECT_EQ(got, kSamples);
            EXPECT_EQ(lost, 0u);
        } else {
            EXPECT_GT(lost, 0u) << "the sleeping reader should have been lapped";
        }
    }
}

// A writer killed at any instant (SIGKILL, mid-sample or not): readers see
// no half-written sample, and a new writer goes on with the next number, so a
// reader gets a gapless, duplicate-free sequence across the hand-over.
TEST(SamplerRing, AKilledWriterLeavesNoTornSampleAndIsTakenOver) {
    CHIMERA_NOT_UNDER_TSAN("a writer process killed -9");
    const test::SegmentGuard cleanup(prefix());
    const std::string name = unique_name("kill");
    constexpr std::size_t kWidth = 16;
    std::unique_ptr<RingWriter> creator =
        std::make_unique<RingWriter>(RingWriter::create(name, channels(kWidth), zeros(kWidth), 1 << 16, 1.0));
    creator->detach();  // the ring stays for the child to write
    creator.reset();
    RingReader r = RingReader::attach(name);
    Rows rows(1 << 16, kWidth);
    for (int round = 0; round < 5; ++round) {
        const pid_t child = fork_child([&] {
            RingWriter w = RingWriter::attach(name);
            for (std::uint64_t n = w.next();; ++n) publish_n(w, n);
            return 0;
        });
        ASSERT_TRUE(wait_for([&] { return r.head() > r.position() + 1000; }));
        kill(child, SIGKILL);
        EXPECT_EQ(wait_child(child), 128 + SIGKILL);
    }
    // Take the role over here and write 10 more.
    RingWriter w = RingWriter::attach(name);
    const std::uint64_t first_new = w.next();
    for (std::uint64_t n = first_new; n < first_new + 10; ++n) publish_n(w, n);
    r.rewind();
    std::uint64_t expected = r.position();
    ReadCount c{};
    do {
        c = r.read(rows.t.data(), rows.cycle.data(), rows.v.data(), rows.t.size());
        for (std::size_t k = 0; k < c.samples; ++k) {
            ASSERT_TRUE(whole(rows, k, kWidth));
            ASSERT_EQ(static_cast<std::uint64_t>(rows.t[k] / 1000), expected) << "a gap or a duplicate";
            ++expected;
        }
    } while (c.samples > 0);
    EXPECT_EQ(expected, first_new + 10);
    EXPECT_EQ(r.lost_total(), 0u);
    EXPECT_TRUE(w.destroy());
    EXPECT_TRUE(cleanup.present().empty());
}

// A reader killed at any instant changes nothing the writer or another reader sees.
TEST(SamplerRing, AKilledReaderLeavesNothingBehind) {
    CHIMERA_NOT_UNDER_TSAN("a reader process killed -9");
    const test::SegmentGuard cleanup(prefix());
    const std::string name = unique_name("rkill");
    RingWriter w = RingWriter::create(name, channels(2), zeros(2), 1024, 1.0);
    RingReader other = RingReader::attach(name);
    const pid_t child = fork_child([&] {
        RingReader r = RingReader::attach(name);
        Rows rows(256, 2);
        for (;;) (void)r.read(rows.t.data(), rows.cycle.data(), rows.v.data(), 256);
        return 0;
    });
    Rows rows(1024, 2);
    for (std::uint64_t n = 0; n < 20000; ++n) {
        publish_n(w, n);
        if (n == 10000) kill(child, SIGKILL);
        if (n % 512 == 0) {
            const ReadCount c = other.read(rows.t.data(), rows.cycle.data(), rows.v.data(), 1024);
            ASSERT_EQ(c.lost, 0u);
        }
    }
    EXPECT_EQ(wait_child(child), 128 + SIGKILL);
    const ReadCount c = other.read(rows.t.data(), rows.cycle.data(), rows.v.data(), 1024);
    EXPECT_EQ(c.lost, 0u);
    EXPECT_EQ(other.position(), 20000u);
    EXPECT_TRUE(w.destroy());
    EXPECT_TRUE(other.closed());
    EXPECT_TRUE(cleanup.present().empty()) << "the writer's destroy removes the ring, readers or not";
}

TEST(SamplerRing, ValidateRefusesABadImage) {
    const test::SegmentGuard cleanup(prefix());
    const std::string name = unique_name("val");
    RingWriter w = RingWriter::create(name, channels(3), zeros(3), 64, 1.0);
    std::vector<std::byte> image(required_size(3, 64));
    const ipc::Segment seg = ipc::Segment::watch(name, {ipc::ObjectType::sampler_ring, kLayoutVersion});
    std::memcpy(image.data(), seg.base(), image.size());
    EXPECT_FALSE(validate_ring(image.data(), image.size()));
    auto* h = reinterpret_cast<detail::RingHeader*>(image.data());
    h->capacity = 100;
    EXPECT_STREQ(validate_ring(image.data(), image.size()).field, "capacity (a power of two)");
    h->capacity = 64;
    h->channels = 300;
    EXPECT_STREQ(validate_ring(image.data(), image.size()).field, "channel count");
    h->channels = 3;
    h->capacity = 1 << 20;
    EXPECT_STREQ(validate_ring(image.data(), image.size()).field, "ring size for its geometry");
    h->capacity = 64;
    auto* desc = reinterpret_cast<detail::ChannelDesc*>(image.data() + h->channels_offset);
    std::memset(desc[1].name, 'x', sizeof desc[1].name);
    EXPECT_STREQ(validate_ring(image.data(), image.size()).field, "channel name length");
}

// --- the sampler bound to a table -----------------------------------------------

namespace {

const char* kSvar =
    "NAME Q_REF\nTYPE double\nDESC r\nUNITS rad\nNELEM 6\n"
    "NAME COUNT\nTYPE int\nDESC c\nUNITS 1\nNELEM 1\n"
    "NAME F\nTYPE float\nDESC f\nUNITS 1\nNELEM 3\n"
    "NAME BLOB\nTYPE struct[8]\nDESC b\nUNITS -\nNELEM 1\nEOF\n";

svar::Table make_table(const std::string& name) {
    return svar::Table::create(name, svar::parse_svar_string(kSvar, "t.svar"));
}

std::vector<std::string> words(std::initializer_list<const char*> w) { return {w.begin(), w.end()}; }

std::string parse_error(const svar::Table& t, std::initializer_list<const char*> w) {
    try {
        (void)parse_channels(t, words(w));
    } catch (const svar::Error& e) {
        return e.what();
    }
    return "no error";
}

}  // namespace

TEST(Sampler, ChannelsFromWords) {
    const test::SegmentGuard cleanup(prefix());
    svar::Table t = make_table(unique_name("svar1"));
    const auto c = parse_channels(t, words({"COUNT", "Q_REF[4]", "F[1:2]", "Q_REF"}));
    std::vector<std::string> names;
    for (const auto& ch : c) names.push_back(ch.name);
    EXPECT_EQ(names, words({"COUNT", "Q_REF[4]", "F[1]", "F[2]", "Q_REF[0]", "Q_REF[1]", "Q_REF[2]", "Q_REF[3]",
                            "Q_REF[4]", "Q_REF[5]"}));
    EXPECT_EQ(c[1].var, "Q_REF");
    EXPECT_EQ(c[1].element, 4u);
    const std::string table = unique_name("svar1");
    EXPECT_EQ(parse_error(t, {"NOPE"}), "sample NOPE: table " + table + " has no variable NOPE");
    EXPECT_EQ(parse_error(t, {"Q_REF[6]"}), "sample Q_REF[6]: element 6 is outside Q_REF (6 elements: 0 to 5)");
    EXPECT_EQ(parse_error(t, {"Q_REF[x]"}), "sample Q_REF[x]: write VAR, VAR[i] or VAR[i:j] with i <= j");
    EXPECT_EQ(parse_error(t, {"Q_REF[3:1]"}), "sample Q_REF[3:1]: write VAR, VAR[i] or VAR[i:j] with i <= j");
    EXPECT_EQ(parse_error(t, {"Q_REF[1"}), "sample Q_REF[1: write VAR, VAR[i] or VAR[i:j]");
    EXPECT_EQ(parse_error(t, {"BLOB"}), "sample BLOB: BLOB is a struct: it has no numbers to sample");
    EXPECT_EQ(parse_error(t, {}), "sample: no variable named");
}

TEST(Sampler, SamplesTheTableAsOneConsistentSet) {
    const test::SegmentGuard cleanup(prefix());
    svar::Table t = make_table(unique_name("svar2"));
    Sampler s(t, parse_channels(t, words({"Q_REF[1:2]", "COUNT", "F[2]"})), unique_name("ring2"), 1024, 250.0);
    RingReader r = RingReader::attach(s.ring_name());
    EXPECT_EQ(r.channel_names(), words({"Q_REF[1]", "Q_REF[2]", "COUNT", "F[2]"}));
    EXPECT_EQ(r.var_indices(), (std::vector<std::uint32_t>{0, 0, 1, 2}));
    EXPECT_EQ(r.rate_hz(), 250.0);
    for (int k = 0; k < 5; ++k) {
        const double q[6] = {0, 1.5 * k, -2.0 * k, 3, 4, 5};
        const std::int32_t count = 100 + k;
        const float f[3] = {0, 0, 0.25f * static_cast<float>(k)};
        ASSERT_EQ(t.write(0, q), svar::Status::ok);
        ASSERT_EQ(t.write(1, &count), svar::Status::ok);
        ASSERT_EQ(t.write(2, f), svar::Status::ok);
        ASSERT_EQ(s.sample(1000 + k, static_cast<std::uint64_t>(k)), svar::Status::ok);
    }
    Rows rows(8, 4);
    const ReadCount c = r.read(rows.t.data(), rows.cycle.data(), rows.v.data(), 8);
    ASSERT_EQ(c.samples, 5u);
    for (std::size_t k = 0; k < 5; ++k) {
        EXPECT_EQ(rows.t[k], static_cast<std::int64_t>(1000 + k));
        EXPECT_EQ(rows.cycle[k], k);
        EXPECT_EQ(rows.v[k * 4 + 0], 1.5 * static_cast<double>(k));
        EXPECT_EQ(rows.v[k * 4 + 1], -2.0 * static_cast<double>(k));
        EXPECT_EQ(rows.v[k * 4 + 2], 100.0 + static_cast<double>(k));
        EXPECT_EQ(rows.v[k * 4 + 3], 0.25 * static_cast<double>(k));
    }
}

// The sampling path is a task's cycle: no allocation, and no system call.
TEST(Sampler, SamplingAllocatesNothingAndMakesNoSystemCall) {
    const test::SegmentGuard cleanup(prefix());
    svar::Table t = make_table(unique_name("svar3"));
    Sampler s(t, parse_channels(t, words({"Q_REF", "COUNT", "F"})), unique_name("ring3"), 1024, 1000.0);
    ASSERT_EQ(s.sample(ipc::now_ns(), 0), svar::Status::ok);  // first touch of every page
    const long allocations = test::allocations_in([&] {
        for (std::uint64_t k = 1; k < 5000; ++k) (void)s.sample(ipc::now_ns(), k);
    });
    EXPECT_EQ(allocations, 0);

    const int fd = test::open_syscall_counter();
    if (fd < 0) {
        if (std::getenv("CHIMERA_REQUIRE_SYSCALL_COUNTER")) FAIL() << "raw_syscalls:sys_enter counter could not be opened";
        GTEST_SKIP() << "raw_syscalls:sys_enter not available (run the sampler_syscalls test)";
    }
    const std::uint64_t c0 = test::read_syscall_counter(fd);
    const std::uint64_t c1 = test::read_syscall_counter(fd);
    const std::uint64_t per_read = c1 - c0;
    const std::uint64_t a = test::read_syscall_counter(fd);
    for (std::uint64_t k = 0; k < 20000; ++k) (void)s.sample(ipc::now_ns(), k);
    const std::uint64_t b = test::read_syscall_counter(fd);
    EXPECT_EQ(b - a - per_read, 0u) << "system calls in 20000 samples";
    close(fd);
}
