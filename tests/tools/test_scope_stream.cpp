// The web console's scope stream (tools/sbs/scope_stream.hpp, issue 17.5)
// against a ring written here: every sample sent once, in order, with its
// number; at most `window` batches, and the byte bound, unacknowledged; the
// samples the ring overwrote while the page did not acknowledge counted
// exactly, and the numbers jumping by exactly that count; the writer's end sent once, last.
// No timing is asserted: the tests wait for what must come.
#include <gtest/gtest.h>

#include <nlohmann/json.hpp>

#include <algorithm>
#include <chrono>
#include <mutex>
#include <thread>
#include <vector>

#include "scope_stream.hpp"
#include "segment_guard.hpp"

using namespace chimera;
using chimera::cli::ScopeSettings;
using chimera::cli::ScopeStream;

namespace {

std::string prefix() { return "chimera.scopetest" + std::to_string(getpid()) + "."; }
std::string unique_name(const std::string& what) { return "/" + prefix() + what; }

sampler::RingWriter make_ring(const std::string& name, std::size_t capacity) {
    const std::vector<sampler::Channel> channels = {{"V", 0, "V[0]"}, {"V", 1, "V[1]"}};
    const std::vector<std::uint32_t> vars = {0, 0};
    return sampler::RingWriter::create(name, channels, vars, capacity, 500.0);
}

// Sample n: V[0] = n + 0.5, V[1] = -n, time 1000 + 2e6 n ns, cycle n + 3.
void publish(sampler::RingWriter& w, std::uint64_t from, std::uint64_t to) {
    for (std::uint64_t n = from; n < to; ++n) {
        const double row[2] = {static_cast<double>(n) + 0.5, -static_cast<double>(n)};
        w.publish_row(static_cast<std::int64_t>(1000 + 2'000'000 * n), n + 3, row);
    }
}

// What the page receives.
struct Page {
    std::mutex mu;
    std::vector<nlohmann::json> batches;

    ScopeStream::Send sender() {
        return [this](const std::string& text) {
            const nlohmann::json m = nlohmann::json::parse(text);
            EXPECT_EQ(m["stream"], "scope");
            std::lock_guard lock(mu);
            batches.push_back(m["data"]);
        };
    }
    std::vector<nlohmann::json> taken() {
        std::lock_guard lock(mu);
        return batches;
    }
    std::size_t samples() {
        std::size_t k = 0;
        for (const auto& b : taken()) k += b["n"].size();
        return k;
    }
    // Waits (up to 20 s: a loaded machine) until `done` holds.
    template <typename Done>
    bool wait(Done done) {
        for (int i = 0; i < 4000; ++i) {
            if (done()) return true;
            std::this_thread::sleep_for(std::chrono::milliseconds(5));
        }
        return done();
    }
};

ScopeSettings fast(std::uint64_t window, std::size_t max_batch) {
    ScopeSettings s;
    s.period = std::chrono::milliseconds(2);
    s.window = window;
    s.max_batch = max_batch;
    return s;
}

}  // namespace

TEST(ScopeStream, EverySampleOnceInOrderWithItsNumberTimeAndValues) {
    const test::SegmentGuard cleanup(prefix());
    const std::string name = unique_name("order");
    sampler::RingWriter w = make_ring(name, 1024);
    publish(w, 0, 100);
    Page page;
    ScopeStream s("sample.1", name, page.sender(), fast(1000, 30));
    EXPECT_EQ(s.channels(), (std::vector<std::string>{"V[0]", "V[1]"}));
    s.start();
    ASSERT_TRUE(page.wait([&] { return page.samples() == 100; }));
    publish(w, 100, 250);
    ASSERT_TRUE(page.wait([&] { return page.samples() == 250; }));
    s.stop();
    std::uint64_t expect = 0, batch = 0;
    for (const auto& b : page.taken()) {
        EXPECT_EQ(b["batch"], ++batch);
        EXPECT_EQ(b["rmod"], "sample.1");
        EXPECT_EQ(b["lost"], 0u);
        EXPECT_FALSE(b["closed"]);
        EXPECT_LE(b["n"].size(), 30u);
        for (std::size_t k = 0; k < b["n"].size(); ++k, ++expect) {
            ASSERT_EQ(b["n"][k], expect);
            EXPECT_EQ(b["t"][k], static_cast<std::int64_t>(2'000'000 * expect));  // from the first sample
            EXPECT_EQ(b["cycle"][k], expect + 3);
            EXPECT_EQ(b["values"][0][k], static_cast<double>(expect) + 0.5);
            EXPECT_EQ(b["values"][1][k], -static_cast<double>(expect));
        }
    }
    EXPECT_EQ(expect, 250u);
}

TEST(ScopeStream, AtMostTheWindowUnacknowledgedThenMoreOnAck) {
    const test::SegmentGuard cleanup(prefix());
    const std::string name = unique_name("window");
    sampler::RingWriter w = make_ring(name, 1024);
    publish(w, 0, 100);
    Page page;
    ScopeStream s("sample.2", name, page.sender(), fast(3, 10));
    s.start();
    ASSERT_TRUE(page.wait([&] { return page.taken().size() == 3; }));
    std::this_thread::sleep_for(std::chrono::milliseconds(50));  // 25 periods: nothing more may come
    EXPECT_EQ(page.taken().size(), 3u);
    s.ack(2);
    ASSERT_TRUE(page.wait([&] { return page.taken().size() == 5; }));
    s.ack(99);  // a batch not sent yet is no acknowledgement
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    EXPECT_EQ(page.taken().size(), 5u);
    s.stop();
}

// Issue #29.2: bytes bound what a page holds unacknowledged, whatever the
// window: with a bound of 1 byte, one batch goes, then nothing until it is
// acknowledged (a window of 1000 batches would let all ten go at once).
TEST(ScopeStream, AtMostTheByteBoundUnacknowledgedThenMoreOnAck) {
    const test::SegmentGuard cleanup(prefix());
    const std::string name = unique_name("bytes");
    sampler::RingWriter w = make_ring(name, 1024);
    publish(w, 0, 100);
    Page page;
    ScopeSettings settings = fast(1000, 10);
    settings.max_unacked_bytes = 1;
    ScopeStream s("sample.8", name, page.sender(), settings);
    s.start();
    ASSERT_TRUE(page.wait([&] { return page.taken().size() == 1; }));
    std::this_thread::sleep_for(std::chrono::milliseconds(50));  // 25 periods: nothing more may come
    EXPECT_EQ(page.taken().size(), 1u);
    s.ack(1);
    ASSERT_TRUE(page.wait([&] { return page.taken().size() == 2; }));
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    EXPECT_EQ(page.taken().size(), 2u);
    s.stop();
}

TEST(ScopeStream, SamplesOverwrittenWhileThePageStalledAreCountedExactly) {
    const test::SegmentGuard cleanup(prefix());
    const std::string name = unique_name("loss");
    sampler::RingWriter w = make_ring(name, 16);
    publish(w, 0, 10);
    Page page;
    ScopeStream s("sample.3", name, page.sender(), fast(1, 10));
    s.start();
    ASSERT_TRUE(page.wait([&] { return page.taken().size() == 1; }));  // samples 0..9, unacknowledged
    publish(w, 10, 50);  // the ring holds 34..49: 10..33 are gone
    ASSERT_TRUE(page.wait([&] {
        s.ack(page.taken().size());  // the page keeps up again
        return page.samples() == 10 + 16;
    }));
    s.stop();
    const auto b = page.taken();
    EXPECT_EQ(b[1]["lost"], 24u);
    EXPECT_EQ(b[1]["n"][0], 34u);
    EXPECT_EQ(b.back()["n"].back(), 49u);
    EXPECT_EQ(b.back()["lost_total"], 24u);
}

TEST(ScopeStream, TheWritersEndIsSentOnceAfterItsLastSample) {
    const test::SegmentGuard cleanup(prefix());
    const std::string name = unique_name("closed");
    sampler::RingWriter w = make_ring(name, 64);
    publish(w, 0, 20);
    Page page;
    ScopeStream s("sample.4", name, page.sender(), fast(100, 8));
    s.start();
    ASSERT_TRUE(page.wait([&] { return page.samples() == 20; }));
    publish(w, 20, 25);
    w.destroy();
    ASSERT_TRUE(page.wait([&] { return !page.taken().empty() && page.taken().back()["closed"] == true; }));
    std::this_thread::sleep_for(std::chrono::milliseconds(30));
    const auto b = page.taken();
    EXPECT_EQ(page.samples(), 25u);
    EXPECT_TRUE(b.back()["n"].empty());
    EXPECT_EQ(std::count_if(b.begin(), b.end(), [](const auto& x) { return x["closed"] == true; }), 1);
    s.stop();
}

TEST(ScopeStream, NothingIsSentAfterStop) {
    const test::SegmentGuard cleanup(prefix());
    const std::string name = unique_name("stop");
    sampler::RingWriter w = make_ring(name, 64);
    Page page;
    ScopeStream s("sample.5", name, page.sender(), fast(100, 8));
    s.start();
    s.stop();
    s.stop();  // idempotent
    s.start();  // not after stop
    publish(w, 0, 10);
    std::this_thread::sleep_for(std::chrono::milliseconds(30));
    EXPECT_TRUE(page.taken().empty());
}

TEST(ScopeStream, ManyChannelsMakeSmallerBatches) {
    const test::SegmentGuard cleanup(prefix());
    const std::string name = unique_name("wide");
    sampler::RingWriter w = make_ring(name, 64);  // two channels
    publish(w, 0, 50);
    Page page;
    ScopeSettings settings = fast(100, 40);
    settings.max_values = 20;  // 10 samples of 2 channels
    ScopeStream s("sample.7", name, page.sender(), settings);
    s.start();
    ASSERT_TRUE(page.wait([&] { return page.samples() == 50; }));
    s.stop();
    for (const auto& b : page.taken()) EXPECT_LE(b["n"].size(), 10u);
}

TEST(ScopeStream, AMissingRingIsAnErrorNamingIt) {
    Page page;
    try {
        ScopeStream s("sample.6", unique_name("nosuch"), page.sender());
        FAIL() << "attached to a ring that does not exist";
    } catch (const std::exception& e) {
        EXPECT_NE(std::string(e.what()).find("nosuch"), std::string::npos) << e.what();
    }
}
