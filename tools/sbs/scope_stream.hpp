// tools/sbs/scope_stream.hpp — the web console's scope (issue 17.5), server
// side: one page's sampler ring (include/chimera/sampler.hpp) followed on a
// thread of its own (not real-time: SCHED_OTHER) and sent to the page as
// batches of consecutive samples.
//
// Flow control is the page's: each batch carries a number, the page
// acknowledges the batches it has drawn (`scope ack N`), and at most
// `window` batches, and max_unacked_bytes plus one batch, are
// unacknowledged. A page that falls behind (a busy browser buffers WebSocket
// messages without limit, so TCP would never say so) stops the reading; the
// ring laps this reader and the samples it overwrote are counted
// (RingReader's exact count) and reported in the next batch. Every sample
// reaches the page once, in order, or is counted lost.
#pragma once

#include <chimera/sampler.hpp>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

namespace chimera::cli {

struct ScopeSettings {
    std::chrono::milliseconds period{40};  ///< how often the ring is read (25 batches/s at most per window slot)
    std::uint64_t window = 8;              ///< batches sent and not yet acknowledged
    std::size_t max_batch = 4096;          ///< samples per batch
    std::size_t max_values = 65536;        ///< samples x channels per batch (about 1.5 MB of JSON)
    /// A batch is sent only while fewer bytes than this are unacknowledged,
    /// so a page holds at most this plus one batch (issue #29.2).
    std::size_t max_unacked_bytes = std::size_t{4} << 20;
};

/// Follows one ring and sends its samples as {"stream":"scope","data":{...}}
/// messages through `send`: {"rmod","batch","n":[each sample's number in
/// the ring],"t":[ns from the stream's first sample],"cycle":[the task's
/// cycle],"values":[[channel 0...],...],"lost","lost_total","closed"}. The
/// numbers run on from batch to batch without a gap or a repeat, except by
/// exactly the `lost` samples the ring overwrote first. `closed`: the sampler
/// task has finished and this is the last batch.
class ScopeStream {
public:
    using Send = std::function<void(const std::string&)>;

    /// Attaches to `ring` (throws sampler::Error) from its oldest sample.
    ScopeStream(std::string rmod, const std::string& ring, Send send, ScopeSettings settings = {});
    ~ScopeStream();
    ScopeStream(const ScopeStream&) = delete;
    ScopeStream& operator=(const ScopeStream&) = delete;

    const std::string& rmod() const noexcept { return rmod_; }
    const std::vector<std::string>& channels() const noexcept { return reader_.channel_names(); }
    double rate_hz() const noexcept { return reader_.rate_hz(); }

    /// Starts sending (idempotent; not after stop()).
    void start();
    /// The page has drawn batches up to `batch`.
    void ack(std::uint64_t batch);
    /// Ends the thread (idempotent); nothing is sent after it returns.
    void stop();

private:
    static ScopeSettings bounded(ScopeSettings s, std::size_t channels);
    void run();
    struct Taken {
        std::size_t samples = 0;
        std::uint64_t lost = 0;
    };
    Taken take();
    bool send_batch();  // false when there was nothing to send
    std::string batch_text(const Taken& got, bool closing);

    std::string rmod_;
    sampler::RingReader reader_;
    Send send_;
    ScopeSettings settings_;
    std::vector<std::uint64_t> numbers_;  // each sample's number in the ring
    std::vector<std::int64_t> time_ns_;
    std::vector<std::uint64_t> cycles_;
    std::vector<double> values_;
    std::int64_t origin_ns_ = 0;
    bool have_origin_ = false;
    bool closed_sent_ = false;
    std::uint64_t sent_ = 0;  // batches sent; batch numbers start at 1

    std::mutex mu_;
    std::condition_variable wake_;
    std::uint64_t acked_ = 0;
    std::deque<std::size_t> unacked_sizes_;  // batches acked_+1 .. sent_, in bytes
    std::size_t unacked_bytes_ = 0;
    bool stopping_ = false;
    std::thread thread_;
};

}  // namespace chimera::cli
