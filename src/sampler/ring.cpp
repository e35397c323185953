// The sampler ring's set-up paths, its validator and the reader (the writer's
// publish is inline in sampler.hpp).
#include "chimera/sampler.hpp"

#include <unistd.h>

#include <algorithm>
#include <cstring>
#include <utility>

namespace chimera::sampler {

using detail::ChannelDesc;
using detail::Entry;
using detail::RingHeader;

namespace {

constexpr ipc::SegmentKind kKind{ipc::ObjectType::sampler_ring, kLayoutVersion};

std::size_t stride_for(std::size_t channels) noexcept {
    return ipc::align_up(detail::kEntryValuesOffset + 8 * channels, 64);
}
std::size_t entries_offset_for(std::size_t channels) noexcept {
    return ipc::align_up(sizeof(RingHeader) + channels * sizeof(ChannelDesc), 64);
}

}  // namespace

std::size_t required_size(std::size_t channels, std::size_t capacity) noexcept {
    return entries_offset_for(channels) + capacity * stride_for(channels);
}

std::size_t capacity_for(double rate_hz, double seconds) noexcept {
    const double want = rate_hz * seconds;
    std::size_t c = 1024;
    while (c < kMaxCapacity && static_cast<double>(c) < want) c *= 2;
    return c;
}

ipc::Fault validate_ring(const void* image, std::size_t size) noexcept {
    if (ipc::Fault f = ipc::header_fault(image, size, kKind)) return f;
    if (size < sizeof(RingHeader)) return {"size", -1, size, sizeof(RingHeader), "at least"};
    const auto& h = *static_cast<const RingHeader*>(image);
    using ipc::fault_if;
    if (ipc::Fault f = fault_if(h.channels == 0 || h.channels > kMaxChannels, "channel count", h.channels,
                                kMaxChannels, "1 to"))
        return f;
    if (ipc::Fault f = fault_if(h.capacity < 2 || h.capacity > kMaxCapacity || (h.capacity & (h.capacity - 1)) != 0,
                                "capacity (a power of two)", h.capacity, kMaxCapacity, "2 to"))
        return f;
    if (ipc::Fault f = fault_if(h.entry_stride != stride_for(h.channels), "entry stride", h.entry_stride,
                                stride_for(h.channels), "equal to"))
        return f;
    if (ipc::Fault f = fault_if(h.channels_offset != sizeof(RingHeader), "channels offset", h.channels_offset,
                                sizeof(RingHeader), "equal to"))
        return f;
    if (ipc::Fault f = fault_if(h.entries_offset != entries_offset_for(h.channels), "entries offset",
                                h.entries_offset, entries_offset_for(h.channels), "equal to"))
        return f;
    if (ipc::Fault f = fault_if(required_size(h.channels, h.capacity) > size, "ring size for its geometry",
                                required_size(h.channels, h.capacity), size))
        return f;
    const auto* ch = reinterpret_cast<const ChannelDesc*>(static_cast<const std::byte*>(image) + h.channels_offset);
    for (std::size_t i = 0; i < h.channels; ++i) {
        const std::size_t len = strnlen(ch[i].name, sizeof ch[i].name);
        if (ipc::Fault f = fault_if(len == sizeof ch[i].name, "channel name length", len, kMaxChannelName, "at most",
                                    static_cast<std::int64_t>(i)))
            return f;
    }
    return {};
}

namespace {

void check(const ipc::Segment& seg) {
    if (const ipc::Fault f = validate_ring(seg.base(), seg.size()))
        throw Error("corrupt sampler ring: " + ipc::describe(seg.name(), f));
}

}  // namespace

// --- writer -------------------------------------------------------------------

RingWriter::RingWriter(ipc::Segment seg) : seg_(std::move(seg)) {
    h_ = static_cast<RingHeader*>(seg_.base());
    entries_ = seg_.at_bytes(h_->entries_offset);
    stride_ = h_->entry_stride;
    mask_ = h_->capacity - 1;
    channels_ = h_->channels;
    next_ = h_->head.load(std::memory_order_acquire);
    h_->writer_pid.store(static_cast<std::int32_t>(getpid()), std::memory_order_relaxed);
    h_->closed.store(0, std::memory_order_release);
}

RingWriter::RingWriter(RingWriter&& o) noexcept { *this = std::move(o); }

RingWriter& RingWriter::operator=(RingWriter&& o) noexcept {
    if (this != &o) {
        destroy();
        seg_ = std::move(o.seg_);
        h_ = std::exchange(o.h_, nullptr);
        entries_ = std::exchange(o.entries_, nullptr);
        stride_ = o.stride_;
        mask_ = o.mask_;
        channels_ = o.channels_;
        next_ = o.next_;
    }
    return *this;
}

RingWriter::~RingWriter() { destroy(); }

RingWriter RingWriter::create(const std::string& name, std::span<const Channel> channels,
                              std::span<const std::uint32_t> var_indices, std::size_t capacity, double rate_hz,
                              const ipc::CreateOptions& options) {
    if (channels.empty() || channels.size() > kMaxChannels)
        throw Error("sampler ring " + name + ": " + std::to_string(channels.size()) + " channels (1 to " +
                    std::to_string(kMaxChannels) + ")");
    if (var_indices.size() != channels.size())
        throw Error("sampler ring " + name + ": one variable index per channel is needed");
    if (capacity < 2 || capacity > kMaxCapacity || (capacity & (capacity - 1)) != 0)
        throw Error("sampler ring " + name + ": capacity " + std::to_string(capacity) +
                    " is not a power of two from 2 to " + std::to_string(kMaxCapacity));
    for (const Channel& c : channels)
        if (c.name.empty() || c.name.size() > kMaxChannelName)
            throw Error("sampler ring " + name + ": channel name '" + c.name + "' must be 1 to " +
                        std::to_string(kMaxChannelName) + " characters");
    const std::size_t size = required_size(channels.size(), capacity);
    ipc::Segment seg = ipc::Segment::create(name, size, kKind, options);
    auto& h = *static_cast<RingHeader*>(seg.base());
    h.capacity = capacity;
    h.channels = channels.size();
    h.entry_stride = stride_for(channels.size());
    h.channels_offset = sizeof(RingHeader);
    h.entries_offset = entries_offset_for(channels.size());
    h.rate_hz = rate_hz;
    auto* desc = seg.at_bytes<ChannelDesc>(h.channels_offset);
    for (std::size_t i = 0; i < channels.size(); ++i) {
        std::memcpy(desc[i].name, channels[i].name.data(), channels[i].name.size());
        desc[i].var_index = var_indices[i];
        desc[i].element = static_cast<std::uint32_t>(channels[i].element);
    }
    seg.publish();
    return RingWriter(std::move(seg));
}

RingWriter RingWriter::attach(const std::string& name) {
    ipc::Segment seg = ipc::Segment::attach(name, kKind);
    check(seg);
    return RingWriter(std::move(seg));
}

bool RingWriter::destroy() noexcept {
    if (!h_) return false;
    h_->closed.store(1, std::memory_order_release);
    h_ = nullptr;
    // Readers map the ring as watchers: they keep their mapping, the name goes.
    const bool removed = seg_.detach_destroy_if_last();
    return removed;
}

void RingWriter::detach() noexcept {
    h_ = nullptr;
    seg_.detach();
}

// --- reader -------------------------------------------------------------------

RingReader::RingReader(ipc::Segment seg) : seg_(std::move(seg)) {
    h_ = static_cast<const RingHeader*>(seg_.base());
    entries_ = seg_.at_bytes(h_->entries_offset);
    stride_ = h_->entry_stride;
    mask_ = h_->capacity - 1;
    rate_hz_ = h_->rate_hz;
    const auto* desc = seg_.at_bytes<const ChannelDesc>(h_->channels_offset);
    for (std::size_t i = 0; i < h_->channels; ++i) {
        channels_.emplace_back(desc[i].name, strnlen(desc[i].name, sizeof desc[i].name));
        var_indices_.push_back(desc[i].var_index);
    }
    pos_ = head();
}

RingReader::RingReader(RingReader&& o) noexcept { *this = std::move(o); }

RingReader& RingReader::operator=(RingReader&& o) noexcept {
    if (this != &o) {
        seg_ = std::move(o.seg_);
        h_ = std::exchange(o.h_, nullptr);
        entries_ = std::exchange(o.entries_, nullptr);
        stride_ = o.stride_;
        mask_ = o.mask_;
        rate_hz_ = o.rate_hz_;
        channels_ = std::move(o.channels_);
        var_indices_ = std::move(o.var_indices_);
        pos_ = o.pos_;
        lost_total_ = o.lost_total_;
    }
    return *this;
}

RingReader::~RingReader() = default;

RingReader RingReader::attach(const std::string& name) {
    ipc::Segment seg = ipc::Segment::watch(name, kKind);
    check(seg);
    return RingReader(std::move(seg));
}

void RingReader::rewind() noexcept {
    const std::uint64_t h = head();
    // The oldest entry may be the one being overwritten: read() finds out.
    pos_ = h > capacity() ? h - capacity() : 0;
}

ReadCount RingReader::read(std::int64_t* time_ns, std::uint64_t* cycles, double* values,
                           std::size_t max_samples) noexcept {
    ReadCount r;
    const std::size_t width = channels_.size();
    std::uint64_t h = head();
    while (r.samples < max_samples && pos_ < h) {
        if (h - pos_ > capacity()) {  // lapped: the oldest entries are gone
            const std::uint64_t skip = h - capacity() - pos_;
            r.lost += skip;
            pos_ += skip;
        }
        const std::uint64_t n = pos_;
        const Entry& e = entry(n);
        const std::uint64_t want = 2 * n + 2;
        bool taken = false;
        if (e.seq.load(std::memory_order_acquire) == want) {
            const std::size_t k = r.samples;
            time_ns[k] = e.time_ns.load(std::memory_order_relaxed);
            cycles[k] = e.cycle.load(std::memory_order_relaxed);
            for (std::size_t i = 0; i < width; ++i)
                values[k * width + i] = std::bit_cast<double>(e.values[i].load(std::memory_order_relaxed));
            std::atomic_thread_fence(std::memory_order_acquire);
            taken = e.seq.load(std::memory_order_relaxed) == want;
        }
        // Below head, an entry not holding sample n has been overwritten since.
        if (taken)
            ++r.samples;
        else
            ++r.lost;
        ++pos_;
        if (!taken) h = head();
    }
    lost_total_ += r.lost;
    return r;
}

}  // namespace chimera::sampler
