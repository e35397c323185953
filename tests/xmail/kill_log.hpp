// The shared log of the kill test (an SHM object "host:klog"): what every
// sender committed and every receiver took, written so that a process killed
// at any instruction leaves a log the checker can still interpret.
#pragma once

#include <atomic>
#include <cstdint>

namespace kill_test {

inline constexpr int kSenders = 2;
inline constexpr int kReceivers = 3;
inline constexpr std::uint32_t kCap = 1u << 17;  // receipts per receiver

struct Log {
    std::atomic<std::uint32_t> stop;
    std::atomic<std::uint32_t> corrupt;  // a receiver saw a damaged payload
    std::atomic<std::uint64_t> attempt[kSenders];  // sequence being sent now
    std::atomic<std::uint64_t> sent[kSenders];     // sequences below this returned ok
    std::atomic<std::uint64_t> count[kReceivers];  // receipts committed
    std::uint64_t ids[kReceivers][kCap];           // ids[r][count[r]] is in flight
};

/// Message id: sender slot and sequence; the payload repeats a function of it.
inline std::uint64_t make_id(int slot, std::uint64_t seq) {
    return (static_cast<std::uint64_t>(slot + 1) << 40) | seq;
}
inline std::size_t payload_words(std::uint64_t id) { return 1 + id % 5; }  // 8..40 bytes
inline std::uint64_t word(std::uint64_t id, std::size_t i) {
    return i == 0 ? id : id * 0x9E3779B97F4A7C15ull + i;
}

}  // namespace kill_test
