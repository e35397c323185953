// chimera/sampler.hpp — the real-time-side sampler: chosen elements of chosen
// state variables, read at a task's rate, into a shared-memory ring that any
// number of non-real-time readers follow (the scope of the web console, the
// `record` command, Python's chimera.record()).
//
// Two parts:
//
//  - Ring: one shared-memory segment (`/chimera.<subsystem>.<object>`), one
//    writer, any number of readers. Each entry holds a time-stamp
//    (CLOCK_MONOTONIC ns), the sampling task's cycle counter and one double
//    per channel. The writer never waits for, and never learns about, a
//    reader: readers only load from the segment, so a reader that is slow,
//    stopped or killed costs the writer nothing. Each RingReader keeps its own
//    position; it receives every sample exactly once while it keeps up, and
//    when the writer laps it, it counts exactly the samples it lost.
//
//  - Sampler: the writer side bound to the state-variable table. sample()
//    copies the sampled variables global → local as ONE set under one table
//    lock (the thesis's multi-variable transfer, §5.5: the channels of one
//    sample are consistent with each other), then converts the chosen elements
//    to double and publishes them. No allocation, no system call (while the
//    table lock is free), no stdio: it is called from a task's cycle.
//
// Who calls sample(): a task like any other — the `sampler` module
// (modules/sampler), spawned by the master on an RTPU at a chosen frequency.
// It reads the table as every task does, so it is scheduled, profiled and
// budgeted by its RTPU's scheduler like any task, and nothing in the other
// tasks' loop changes when a scope is opened or closed. It does not declare
// the sampled variables as INVARs: an observer is not a consumer, and opening
// a scope must neither make a configuration illegal (§3.3.1: an input with no
// producer) nor be refused by it — halscope watches any signal.
//
// Ring protocol (per entry; sample n lives in entry n mod capacity):
//   writer: seq := 2n+1 (odd: being written); fence; stamps and values
//           (relaxed atomics); seq := 2n+2 (release); head := n+1 (release).
//   reader: for n in [position, head): s := seq (acquire); s == 2n+2 → copy,
//           fence, re-read seq; unchanged → delivered. Anything else means the
//           writer has overwritten sample n (lapped the reader): lost.
// A writer killed mid-entry leaves seq odd and head unchanged, so no reader
// takes the half-written entry; the next writer (a Sampler attached to the
// same ring) goes on at head, with no gap and no duplicate in the numbers.
// Memory written by another process is untrusted (issue #15.3): the geometry
// is checked once on attach (validate_ring()) and kept in the handle.
#pragma once

#include "chimera/export.hpp"

#include <atomic>
#include <bit>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "chimera/ipc/fault.hpp"
#include "chimera/ipc/segment.hpp"
#include "chimera/svar.hpp"

namespace chimera::sampler {

inline constexpr std::uint32_t kLayoutVersion = 1;
/// At most this many channels (elements) per ring.
inline constexpr std::size_t kMaxChannels = 256;
/// At most this many entries per ring (a power of two).
inline constexpr std::size_t kMaxCapacity = std::size_t{1} << 22;
/// Channel names ("Q_REF[2]") are at most this long.
inline constexpr std::size_t kMaxChannelName = 31;

/// One sampled element: variable `var`, element `element` (0-based).
struct Channel {
    std::string var;
    std::size_t element = 0;
    /// "Q_REF[2]"; a scalar variable's one element is just "TIME".
    std::string name;
};

/// Channels from words as the command line writes them: `Q_REF` (every
/// element), `Q_REF[2]` (one), `Q_REF[1:3]` (elements 1 to 3). Throws
/// svar::Error naming the word: unknown variable, element out of range, a
/// struct variable (no numbers), more than kMaxChannels.
CHIMERA_API std::vector<Channel> parse_channels(const svar::Table& table, std::span<const std::string> words);

namespace detail {

struct ChannelDesc {
    char name[kMaxChannelName + 1];
    std::uint32_t var_index;  // in the table the sampler reads
    std::uint32_t element;
    std::uint8_t reserved[8];
};
static_assert(sizeof(ChannelDesc) == 48);

struct alignas(64) RingHeader {
    ipc::SegmentHeader segment;  // offset 0
    // offset 64: fixed at creation
    std::uint64_t capacity;        // entries, a power of two
    std::uint64_t channels;        // doubles per entry
    std::uint64_t entry_stride;    // bytes
    std::uint64_t channels_offset; // ChannelDesc[channels], from the segment start
    std::uint64_t entries_offset;  // from the segment start
    double rate_hz;                // the sampling task's frequency (informative)
    std::uint8_t reserved0[16];
    // offset 128: the only word readers poll; written by the writer alone
    std::atomic<std::uint64_t> head;  // samples published
    std::atomic<std::int32_t> writer_pid;
    std::atomic<std::uint32_t> closed;  // 1 once the writer has finished for good
    std::uint8_t reserved1[48];
};
static_assert(sizeof(RingHeader) == 192);
static_assert(offsetof(RingHeader, head) == 128);

struct Entry {
    std::atomic<std::uint64_t> seq;  // 2n+1 while sample n is written, 2n+2 once it is complete
    std::atomic<std::int64_t> time_ns;
    std::atomic<std::uint64_t> cycle;
    std::uint64_t reserved;
    std::atomic<std::uint64_t> values[1];  // `channels` doubles, as bits
};
inline constexpr std::size_t kEntryValuesOffset = offsetof(Entry, values);
static_assert(kEntryValuesOffset == 32);
static_assert(std::atomic<std::uint64_t>::is_always_lock_free);

}  // namespace detail

/// Bytes of a ring of `capacity` entries of `channels` values.
CHIMERA_API std::size_t required_size(std::size_t channels, std::size_t capacity) noexcept;
/// The smallest power of two holding `seconds` of samples at `rate_hz`, at
/// least 1024 and at most kMaxCapacity.
CHIMERA_API std::size_t capacity_for(double rate_hz, double seconds) noexcept;

/// Checks a ring's image of `size` bytes as attaching does (header, geometry,
/// channel names): the first bound broken, or none. Pure, for fuzzers.
CHIMERA_API ipc::Fault validate_ring(const void* image, std::size_t size) noexcept;

/// An error creating or attaching a ring; what() names the segment.
class CHIMERA_API Error : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

/// The writing end of a ring (one at a time). Move-only.
class CHIMERA_API RingWriter {
public:
    RingWriter() noexcept = default;
    RingWriter(RingWriter&&) noexcept;
    RingWriter& operator=(RingWriter&&) noexcept;
    ~RingWriter();

    /// A new ring segment `name`. `channels` name the columns (var_index is
    /// the variable's index in the table). The writer's destructor is destroy().
    static RingWriter create(const std::string& name, std::span<const Channel> channels,
                             std::span<const std::uint32_t> var_indices, std::size_t capacity, double rate_hz,
                             const ipc::CreateOptions& options = {});
    /// Takes the writer's role of an existing ring over (its writer died or
    /// detached): numbering goes on from the ring's head.
    static RingWriter attach(const std::string& name);

    bool valid() const noexcept { return h_ != nullptr; }
    const std::string& name() const noexcept { return seg_.name(); }
    std::size_t channels() const noexcept { return channels_; }
    std::size_t capacity() const noexcept { return mask_ + 1; }
    /// Number of the next sample (samples published so far).
    std::uint64_t next() const noexcept { return next_; }

    /// Publishes one sample: `fill(double* out)` writes channels() values.
    /// Never waits, never allocates, no system call.
    template <typename Fill>
    void publish(std::int64_t time_ns, std::uint64_t cycle, Fill&& fill) noexcept {
        double row[kMaxChannels];
        fill(row);
        publish_row(time_ns, cycle, row);
    }
    void publish_row(std::int64_t time_ns, std::uint64_t cycle, const double* values) noexcept {
        const std::uint64_t n = next_;
        detail::Entry& e = entry(n);
        e.seq.store(2 * n + 1, std::memory_order_relaxed);
        std::atomic_thread_fence(std::memory_order_release);
        e.time_ns.store(time_ns, std::memory_order_relaxed);
        e.cycle.store(cycle, std::memory_order_relaxed);
        for (std::size_t i = 0; i < channels_; ++i)
            e.values[i].store(std::bit_cast<std::uint64_t>(values[i]), std::memory_order_relaxed);
        e.seq.store(2 * n + 2, std::memory_order_release);
        h_->head.store(n + 1, std::memory_order_release);
        next_ = n + 1;
    }

    /// Marks the ring finished (readers see closed()), unmaps and removes
    /// the name; readers that map it keep reading what it holds.
    bool destroy() noexcept;
    /// Unmaps and leaves the ring for another writer.
    void detach() noexcept;

private:
    explicit RingWriter(ipc::Segment seg);
    detail::Entry& entry(std::uint64_t n) noexcept {
        return *reinterpret_cast<detail::Entry*>(entries_ + (n & mask_) * stride_);
    }
    ipc::Segment seg_;
    detail::RingHeader* h_ = nullptr;
    std::byte* entries_ = nullptr;
    std::size_t stride_ = 0;
    std::uint64_t mask_ = 0;
    std::size_t channels_ = 0;
    std::uint64_t next_ = 0;
};

/// What one RingReader::read() delivered.
struct [[nodiscard]] ReadCount {
    std::size_t samples = 0;  ///< rows written to the caller's arrays
    std::uint64_t lost = 0;   ///< samples overwritten before this reader took them
};

/// One reader of a ring (any number, in any processes). Move-only. A reader
/// only loads from the segment: it never delays, and is never waited for by,
/// the writer.
class CHIMERA_API RingReader {
public:
    RingReader() noexcept = default;
    RingReader(RingReader&&) noexcept;
    RingReader& operator=(RingReader&&) noexcept;
    ~RingReader();

    /// Maps the ring `name` read-only (a watcher: it never keeps the ring
    /// alive, and it cannot write into it); the reader starts at the newest
    /// sample (what the ring held before is not delivered; see rewind()).
    static RingReader attach(const std::string& name);

    bool valid() const noexcept { return h_ != nullptr; }
    const std::string& name() const noexcept { return seg_.name(); }
    std::size_t channels() const noexcept { return channels_.size(); }
    std::size_t capacity() const noexcept { return mask_ + 1; }
    double rate_hz() const noexcept { return rate_hz_; }
    /// The column names and their variables' table indices, from the ring's header.
    const std::vector<std::string>& channel_names() const noexcept { return channels_; }
    const std::vector<std::uint32_t>& var_indices() const noexcept { return var_indices_; }
    /// The writer's process id (0 when none has written).
    std::int32_t writer_pid() const noexcept { return h_->writer_pid.load(std::memory_order_relaxed); }

    /// Number of the next sample this reader will take.
    std::uint64_t position() const noexcept { return pos_; }
    /// Samples published so far.
    std::uint64_t head() const noexcept { return h_->head.load(std::memory_order_acquire); }
    /// True once the writer has finished (the sampling task was turned off or
    /// killed): no sample will follow those published.
    bool closed() const noexcept { return h_->closed.load(std::memory_order_acquire) != 0; }
    /// Samples this reader lost since it attached.
    std::uint64_t lost_total() const noexcept { return lost_total_; }
    /// Goes back to the oldest sample the ring still holds.
    void rewind() noexcept;

    /// Takes at most `max_samples` samples, oldest first: for row k,
    /// time_ns[k], cycles[k] and values[k * channels() + i]. Samples the
    /// writer overwrote before they could be taken are skipped and counted
    /// (`lost`, and lost_total()). Never waits.
    ReadCount read(std::int64_t* time_ns, std::uint64_t* cycles, double* values, std::size_t max_samples) noexcept;

private:
    explicit RingReader(ipc::Segment seg);
    const detail::Entry& entry(std::uint64_t n) const noexcept {
        return *reinterpret_cast<const detail::Entry*>(entries_ + (n & mask_) * stride_);
    }
    ipc::Segment seg_;
    const detail::RingHeader* h_ = nullptr;
    const std::byte* entries_ = nullptr;
    std::size_t stride_ = 0;
    std::uint64_t mask_ = 0;
    double rate_hz_ = 0;
    std::vector<std::string> channels_;
    std::vector<std::uint32_t> var_indices_;
    std::uint64_t pos_ = 0;
    std::uint64_t lost_total_ = 0;
};

/// The writer bound to a state-variable table: what a sampling task's cycle
/// calls. Built at set-up (allocates); sample() allocates nothing.
class CHIMERA_API Sampler {
public:
    /// Reads `channels` of `table` into the ring `ring_name` (created here,
    /// removed with the Sampler) of `capacity` entries. Throws svar::Error or
    /// sampler::Error naming what is wrong.
    Sampler(svar::Table& table, std::vector<Channel> channels, const std::string& ring_name, std::size_t capacity,
            double rate_hz, const ipc::CreateOptions& options = {});
    Sampler(Sampler&&) noexcept;
    ~Sampler();

    const std::vector<Channel>& channels() const noexcept { return channels_; }
    const std::string& ring_name() const noexcept { return ring_.name(); }
    RingWriter& ring() noexcept { return ring_; }

    /// One sample: the variables global → local under one table lock, the
    /// chosen elements into the ring with `time_ns` and `cycle`. When the
    /// table could not be read (lock timeout, ...) nothing is published and
    /// the status says why. No allocation, no system call while the lock is free.
    svar::Status sample(std::int64_t time_ns, std::uint64_t cycle) noexcept;

private:
    struct Source {
        const std::byte* at;  // the sampled element in the local table
        svar::Type type;
    };
    std::vector<Channel> channels_;
    std::unique_ptr<svar::LocalTable> local_;
    svar::VarSet set_;
    std::vector<Source> sources_;
    RingWriter ring_;
};

}  // namespace chimera::sampler
