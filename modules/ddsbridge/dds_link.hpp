// dds_link.hpp — the non-real-time side of ddsbridge: one thread of its own
// that creates the DDS participant, topics, writers and readers (so Cyclone's
// threads, which inherit their creator's scheduling, are SCHED_OTHER too), and
// one triple buffer (TBUF, §5.6) per bridged variable between it and the task:
//
//   pub:  task cycle --tbuf write--> [TBUF] --poll--> bridge thread --dds_write--> network
//   sub:  network --> Cyclone receive thread (listener) --tbuf write--> [TBUF] --read--> task cycle
//
// The task never waits for the bridge and, with NOTIFY poll (the default),
// never makes a system call for it:
// the bridge thread learns of a new value by looking at the TBUF, woken just
// after the task's next write is due (the newest write's stamp + one period +
// kPollLag), and again every kPollStep while the write is late. So a value
// leaves at most about kPollLag plus the thread's wake-up latency after the
// task wrote it (bench/results/dds.md measures it). With NOTIFY wake the task
// wakes the thread after writing (one futex(2) call per cycle): the lag is then
// one thread wake-up.
#pragma once

#include <chimera/ipc/futex.hpp>
#include <chimera/tbuf.hpp>

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include <pthread.h>

#include "bridge_config.hpp"

namespace ddsbridge {

/// What a subscription's TBUF item starts with; the variable's doubles follow.
struct ReceivedHeader {
    std::int64_t source_ns;  ///< the sender's stamp: header.stamp, CLOCK_REALTIME ns
    std::uint64_t counter;   ///< StateVar: the sender's counter-stamp; JointState: samples received - 1
};
static_assert(sizeof(ReceivedHeader) == 16);

inline constexpr std::int64_t kPollLag = 20'000;   ///< ns after the task's write is due
inline constexpr std::int64_t kPollStep = 50'000;  ///< ns between looks while it is late

/// One bridged variable.
struct Port {
    TopicSpec spec;
    std::string global_name;  ///< its SVAR name (StateVar frame_id)
    std::size_t nelem = 0;    ///< doubles
};

/// Counts a subscription's listener keeps (read by `get STATUS`).
struct SubCounts {
    std::atomic<std::uint64_t> received{0};  ///< samples written to the TBUF
    std::atomic<std::uint64_t> rejected{0};  ///< samples of the wrong length, dropped
};

class Link {
public:
    /// Starts the bridge thread and waits until it has created every DDS
    /// entity; throws std::runtime_error with the thread's reason (naming the
    /// topic or the configuration) when it could not, with nothing left running.
    Link(const BridgeConfig& config, std::vector<Port> ports);
    ~Link();
    Link(const Link&) = delete;
    Link& operator=(const Link&) = delete;

    /// The TBUF of port i: the task writes (pub) or reads (sub) it.
    chimera::tbuf::Tbuf& buffer(std::size_t i) noexcept;
    const Port& port(std::size_t i) const noexcept { return ports_[i]; }
    std::size_t size() const noexcept { return ports_.size(); }
    const SubCounts& counts(std::size_t i) const noexcept;
    /// The task's period while it is ON, 0 while OFF: paces the bridge thread's looks.
    void set_period_ns(std::int64_t ns) noexcept { period_ns_.store(ns, std::memory_order_relaxed); }
    /// NOTIFY wake: called by the task after writing its pub TBUFs; one
    /// futex(2) wake when the bridge thread sleeps (it nearly always does).
    void notify() noexcept {
        wakeups_.fetch_add(1);
        if (sleeping_.load()) chimera::ipc::futex_wake(wakeups_);
    }
    /// Linux thread id of the bridge thread (tests check its policy).
    long thread_id() const noexcept { return tid_.load(); }
    /// Samples published since start.
    std::uint64_t published() const noexcept { return published_.load(std::memory_order_relaxed); }

    struct Slot;  // a port's TBUF, its memory and its DDS entities (dds_link.cpp)

private:
    static void* thread_main(void* self) noexcept;
    void run() noexcept;
    void open();         // DDS entities; throws
    void publish_loop() noexcept;
    void close() noexcept;

    BridgeConfig config_;
    std::vector<Port> ports_;
    std::vector<std::unique_ptr<Slot>> slots_;
    pthread_t thread_{};
    std::atomic<long> tid_{0};
    std::atomic<bool> stop_{false};
    std::atomic<std::int64_t> period_ns_{0};
    std::atomic<std::uint32_t> wakeups_{0};  // NOTIFY wake: bumped by the task
    std::atomic<bool> sleeping_{false};       // the bridge thread is (about to be) in futex_wait
    std::atomic<std::uint64_t> published_{0};
    std::int32_t participant_ = 0;
    std::mutex mu_;
    std::condition_variable cv_;
    bool opened_ = false;
    std::string open_error_;
};

}  // namespace ddsbridge
