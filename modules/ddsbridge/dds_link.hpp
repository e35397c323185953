// dds_link.hpp — the non-real-time side of ddsbridge: one thread of its own
// that creates the DDS participant, topics, writers and readers (so Cyclone's
// threads, which inherit their creator's scheduling, are SCHED_OTHER too), and
// one triple buffer (TBUF, §5.6) per bridged variable between it and the task:
//
//   pub:  task cycle --tbuf write--> [TBUF] --look (or wake)--> bridge thread --dds_write--> network
//   sub:  network --> Cyclone receive thread (listener) --tbuf write--> [TBUF] --read--> task cycle
//
// The task never waits for the bridge and, with NOTIFY poll (the default) or
// spin, never makes a system call for it: the bridge thread learns of a new
// value by looking at the TBUF. It predicts when the task's next write is due
// from the task's release grid (WriteSchedule: the period and the earliest
// and typical phases of the recent writes) and
//   - poll: sleeps until just before the typical time (less its own usual
//     wake-up lateness, WakeLateness), then keeps looking for at most
//     kPollWindow (a short busy wait: the write's jitter around its typical
//     time), then looks every kPollStep while the write is late: a typical
//     write leaves within a few µs, for a few µs of CPU time per period;
//   - spin: sleeps until kSpinLead before the earliest due time and then keeps
//     looking (a busy wait, for at most kSpinLimit past the due time, on a CPU
//     other than the task's) until the write appears: the value leaves a few
//     µs after the write, for the CPU time of the lead plus the write's jitter
//     each period.
// With NOTIFY wake the task wakes the thread after writing (one futex(2) call
// per cycle): the lag is one thread wake-up. bench/results/dds.md measures
// the three.
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
#include "joint_map.hpp"

namespace ddsbridge {

/// What a subscription's TBUF item starts with; the variable's doubles follow.
struct ReceivedHeader {
    std::int64_t source_ns;  ///< the sender's stamp: header.stamp, CLOCK_REALTIME ns
    std::uint64_t counter;   ///< StateVar: the sender's counter-stamp; JointState: samples received - 1
};
static_assert(sizeof(ReceivedHeader) == 16);

inline constexpr std::int64_t kPollMargin = 2'000;   ///< poll: ns before the typical write time it aims to wake
inline constexpr std::int64_t kPollWindow = 20'000;  ///< poll: ns past the typical time it keeps looking (at most period/20)
inline constexpr std::int64_t kPollStep = 20'000;    ///< poll: ns between looks while it is late
inline constexpr std::int64_t kSpinLead = 20'000;    ///< spin: ns before the write is due (the thread's own wake-up lateness)
inline constexpr std::int64_t kSpinLimit = 200'000;  ///< spin: ns past the due time before it sleeps in poll steps

/// When the task's next write is due. The task is released on a grid (one
/// period apart) and writes some jitter after each release; the earliest
/// phase of its writes on that grid, relaxed by kRelax per write so that one
/// unusually early write is forgotten, is when the next one can come first;
/// the typical phase (a moving average over about kAverage writes) is when it
/// usually comes.
/// Starts afresh when the period changes or writes stop for over 3 periods
/// (the task turned OFF and ON: a new grid). Pure arithmetic: tested exactly.
class WriteSchedule {
public:
    static constexpr std::int64_t kRelax = 100;  ///< ns per write
    static constexpr std::int64_t kAverage = 8;  ///< writes

    /// The task wrote at `write_ns` (its TBUF stamp); its period is `period_ns`.
    void seen(std::int64_t write_ns, std::int64_t period_ns) noexcept;
    /// The earliest time the write after `write_ns` is due; 0 before any write.
    std::int64_t next_due(std::int64_t write_ns) const noexcept;
    /// The typical time of the write after `write_ns`: next_due() or later; 0 before any write.
    std::int64_t next_typical(std::int64_t write_ns) const noexcept;
    /// The earliest phase on the grid (ns after the first write of this grid; <= 0).
    std::int64_t earliest() const noexcept { return earliest_; }
    /// The typical phase on the grid (ns after the first write of this grid).
    std::int64_t typical() const noexcept { return typical_; }

private:
    std::int64_t origin_ = 0;    // the first write of this grid
    std::int64_t earliest_ = 0;  // the earliest phase seen, relative to origin_, in (-period/2, 0]
    std::int64_t typical_ = 0;   // the moving average of the phases
    std::int64_t last_ = 0;      // the newest write
    std::int64_t period_ = 0;
};

/// How late the bridge thread's timed sleeps end: a moving average over
/// about kAverage sleeps of (when it ran - when it asked), each counted at
/// most kMax (one stall is not its usual lateness). NOTIFY poll asks to be
/// woken this much before it wants to look.
class WakeLateness {
public:
    static constexpr std::int64_t kStart = 10'000;  ///< ns, before any sleep is seen
    static constexpr std::int64_t kMax = 100'000;   ///< ns
    static constexpr std::int64_t kAverage = 8;     ///< sleeps

    void seen(std::int64_t late_ns) noexcept {
        const std::int64_t late = late_ns < 0 ? 0 : late_ns > kMax ? kMax : late_ns;
        average_ += (late - average_) / kAverage;
    }
    std::int64_t average() const noexcept { return average_; }

private:
    std::int64_t average_ = kStart;
};

/// One bridged variable.
struct Port {
    TopicSpec spec;
    std::string global_name;  ///< its SVAR name (StateVar frame_id)
    std::size_t nelem = 0;    ///< doubles
    /// JointState ports: the joints' names, published (pub) or matched on
    /// receipt (sub): JOINT_NAMES, or joint1 .. jointN.
    std::vector<std::string> joint_names;
};

/// What a subscription's listener saw of one stored value: the legs of its
/// transfer, for benchmarks and diagnostics (Link::set_receive_probe).
struct ReceiveProbe {
    const double* values = nullptr;  ///< the value stored (nelem doubles)
    std::size_t nelem = 0;
    std::int64_t header_stamp_ns = 0;  ///< header.stamp: the sender task's TBUF write, CLOCK_REALTIME
    std::int64_t written_ns = 0;       ///< the sender's dds_write call (DDS source timestamp), CLOCK_REALTIME
    std::int64_t entered_ns = 0;       ///< the listener's entry here, CLOCK_MONOTONIC
    std::int64_t stored_ns = 0;        ///< the TBUF write here (its stamp), CLOCK_MONOTONIC
};
/// Called on Cyclone's receive thread after each TBUF write; must not block.
using ReceiveProbeFn = void (*)(void* context, const ReceiveProbe& seen);

/// Counts a subscription's listener keeps (read by `get STATUS`).
struct SubCounts {
    std::atomic<std::uint64_t> received{0};  ///< samples written to the TBUF
    std::atomic<std::uint64_t> rejected{0};  ///< samples refused, whatever the reason (dropped whole)
    std::atomic<std::uint64_t> refused[kRefusals]{};  ///< ... by reason (index: Refusal)
    /// JointState samples taken but not yet passed on: they name some joints
    /// only, and a joint has had no value yet (the port gets its first value
    /// once every joint has one).
    std::atomic<std::uint64_t> held{0};
};

/// A refusal told to the task, which turns it into a warning: the listener
/// writes the text while the notice is not pending, the task reads it while it
/// is (a hand-over of one writer and one reader: no lock). One per reason, and
/// at most one every kNoticeInterval: a flood of bad samples is counted, not
/// told sample by sample.
struct Notice {
    static constexpr std::int64_t kNoticeInterval = 5'000'000'000;  ///< ns
    std::atomic<bool> pending{false};
    std::int64_t last_ns = 0;  // the listener's: when it last wrote one
    char text[320] = {};
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
    /// The refusal of subscription i for `reason` waiting to be told, or
    /// nullptr; after telling it, the task calls notice_told(i, reason).
    const char* pending_notice(std::size_t i, Refusal reason) const noexcept;
    void notice_told(std::size_t i, Refusal reason) noexcept;
    /// The task's period while it is ON, 0 while OFF: paces the bridge thread's looks.
    void set_period_ns(std::int64_t ns) noexcept { period_ns_.store(ns, std::memory_order_relaxed); }
    /// The CPUs the task may run on (bit n: CPU n; 0: unknown). NOTIFY spin:
    /// the bridge thread keeps off them while others are left, so that the
    /// task never preempts its looks (it would see the write only once the
    /// task's cycle has ended). Poll and wake leave the scheduler free to wake
    /// the thread on whichever CPU is idle, the task's included (measured:
    /// keeping them off it doubled their hand-off on two CPUs).
    void set_task_cpus(std::uint64_t mask) noexcept { task_cpus_.store(mask, std::memory_order_relaxed); }
    /// NOTIFY wake: called by the task after writing its pub TBUFs; one
    /// futex(2) wake when the bridge thread sleeps (it nearly always does).
    void notify() noexcept {
        wakeups_.fetch_add(1);
        if (sleeping_.load()) chimera::ipc::futex_wake(wakeups_);
    }
    /// Sets (or, with nullptr, removes) the probe of subscription i.
    void set_receive_probe(std::size_t i, ReceiveProbeFn fn, void* context) noexcept;
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
    std::int64_t publish_fresh() noexcept;  // the stamp of the newest write published, 0 if none
    void wait_for_write(const WriteSchedule& schedule, std::int64_t newest) noexcept;
    // Looks at the published TBUFs until one holds a fresh item (true) or
    // `until` passes or the link stops (false).
    bool look_until(std::int64_t until) noexcept;
    void keep_off_task_cpus() noexcept;
    void close() noexcept;

    BridgeConfig config_;
    std::vector<Port> ports_;
    std::vector<std::unique_ptr<Slot>> slots_;
    pthread_t thread_{};
    std::atomic<long> tid_{0};
    std::atomic<bool> stop_{false};
    std::atomic<std::int64_t> period_ns_{0};
    std::atomic<std::uint64_t> task_cpus_{0};
    WakeLateness lateness_;           // the bridge thread's (NOTIFY poll)
    std::uint64_t avoided_cpus_ = 0;  // the bridge thread's: task_cpus_ when it last set its affinity
    std::atomic<std::uint32_t> wakeups_{0};  // NOTIFY wake: bumped by the task
    std::atomic<bool> sleeping_{false};       // the bridge thread is (about to be) in futex_wait
    std::atomic<std::uint64_t> published_{0};
    std::int32_t participant_ = 0;
    // The publishing thread's reusable messages (publish_fresh).
    struct Messages;
    std::unique_ptr<Messages> messages_;
    std::mutex mu_;
    std::condition_variable cv_;
    bool opened_ = false;
    std::string open_error_;
};

}  // namespace ddsbridge
