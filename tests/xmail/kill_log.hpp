// The shared log of the kill test (an SHM object "host:klog"): what every
// sender committed and every receiver took, written so that a process killed
// at any instruction leaves a log the checker can still interpret.
//
// Receivers: the queue copies a message into the receiver's landing buffer,
// which lives here in shared memory, before receive() commits its removal.
// So a receiver killed anywhere after the commit (still inside receive(),
// or before it logged the receipt) leaves the id in landing[r][0]; a message
// that existed only in a dying process's private memory could not be traced.
// Senders: attempt[s] is the sequence being sent, valid once started[s] is set
// (a fresh log has attempt 0 and sent 0 whether or not sequence 0 was tried).
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>

namespace kill_test {

inline constexpr int kSenders = 2;
inline constexpr int kReceivers = 3;
/// Receipts per receiver: far more than a few seconds of traffic, so a
/// receiver never runs out; if one ever does, it idles until told to stop.
inline constexpr std::uint32_t kCap = 1u << 20;
inline constexpr std::size_t kMaxWords = 5;  // payload of up to 40 bytes

struct Log {
    std::atomic<std::uint32_t> stop;
    std::atomic<std::uint32_t> corrupt;  // a receiver saw a damaged payload
    std::atomic<std::uint32_t> started[kSenders];  // attempt[s] is meaningful
    std::atomic<std::uint64_t> attempt[kSenders];  // sequence being sent now
    std::atomic<std::uint64_t> sent[kSenders];     // sequences below this returned ok
    std::atomic<std::uint64_t> count[kReceivers];  // receipts committed
    std::uint64_t landing[kReceivers][kMaxWords];  // receive buffer: word 0 is the id in flight
    std::uint64_t ids[kReceivers][kCap];           // receipts, in order
};

/// Message id: sender slot and sequence; the payload repeats a function of it.
inline std::uint64_t make_id(int slot, std::uint64_t seq) {
    return (static_cast<std::uint64_t>(slot + 1) << 40) | seq;
}
inline std::size_t payload_words(std::uint64_t id) { return 1 + id % kMaxWords; }  // 8..40 bytes
inline std::uint64_t word(std::uint64_t id, std::size_t i) {
    return i == 0 ? id : id * 0x9E3779B97F4A7C15ull + i;
}

/// Where a sender (re)starts: after anything a killed predecessor may have sent.
inline std::uint64_t resume_sequence(const Log& log, int slot) {
    if (!log.started[slot].load()) return 0;
    const std::uint64_t sent = log.sent[slot].load(), next = log.attempt[slot].load() + 1;
    return sent > next ? sent : next;
}

// The mailbox kill test's log (a plain segment both sides map). Receivers
// read straight into `landing`, in shared memory, so a receiver killed
// anywhere after taking a message leaves its id there. A sender records each
// loss its Peer reports (the last N written to a receiver that died) as a
// range of its sequences.
inline constexpr int kMailSenders = 2;
inline constexpr std::uint32_t kMailCap = 1u << 20;
inline constexpr std::uint32_t kRangeCap = 4096;

struct MailLog {
    std::atomic<std::uint32_t> stop;
    std::atomic<std::uint32_t> corrupt;             // a damaged payload, or a sender's unexpected status
    std::atomic<std::uint64_t> sent[kMailSenders];  // sequences below this were written ok
    std::atomic<std::uint32_t> ranges[kMailSenders];
    std::uint64_t undelivered[kMailSenders][kRangeCap][2];  // [first, end) reported lost
    std::atomic<std::uint64_t> count;               // receipts committed
    std::uint64_t landing[kMaxWords];               // the receiver's read buffer: word 0 is the id
    std::uint64_t ids[kMailCap];
};
/// The log's place in its segment: after the segment header.
inline constexpr std::size_t kMailLogOffset = 64;

}  // namespace kill_test
