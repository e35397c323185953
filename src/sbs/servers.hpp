// Guaranteed soft real-time tasks and the MUF aperiodic servers (thesis §6.4,
// §6.5.2; Listings 2, 3 and 4), as components of the task runtime.
//
// They are written with the public task API of chimera/muf/rt.hpp only —
// set_dfhandler, set_criticality, set_deadline, execstart/execend/execleft —
// exactly as the thesis writes them: the scheduler knows nothing about them.
// A server is an ordinary task of its RTPU's scheduler whose failure handler
// moves it between criticalities: DEADLINE is its replenishment time and
// MAXEXEC says its capacity is used up (§6.5.2). A user asks for one from the
// .rmod (TASKTYPE deferrable / sporadic / background, with PERIOD and WCET as
// the server's period and capacity) and the task runtime serves each event
// with one cycle under it.
//
// They live in src/sbs rather than modules/ because the task runtime
// instantiates them from the TASKTYPE line and src/ never depends on
// modules/ (docs/architecture.md §3); they are not port-based objects
// themselves.
//
// Everything a handler touches is plain data and the task API: the handlers
// run in the task's thread from a signal handler, async-signal-safe, with no
// allocation (the sporadic server's replenishment list is a fixed array).
#pragma once

#include "chimera/muf/rt.hpp"

#include <array>
#include <cstdint>

namespace chimera::sbs::detail {

/// Listing 2: a periodic task whose analysis reserves E (the scheduler's
/// MAXEXEC budget is E). Past E the task drops to `lowered` and goes on in
/// left-over time; at its deadline (or its next release) it gets its
/// criticality back and finishes the cycle with the next period's time.
class SoftTask {
public:
    explicit SoftTask(int lowered) noexcept : lowered_(lowered) {}
    /// At each release (the thesis's set_criticality(5) before pause()).
    void on_release() noexcept;
    /// From the task's failure handler.
    void on_failure(muf::Failure kind) noexcept;

private:
    int lowered_;
    volatile int saved_ = 0;  // criticality before lowering; 0: not lowered
};

/// An aperiodic server: begin() once the task has joined its RTPU's scheduler,
/// event_begin()/event_end() around each event's service, end() to leave.
class AperiodicServer {
public:
    virtual ~AperiodicServer() = default;
    virtual void begin() noexcept = 0;
    virtual void event_begin() noexcept {}
    virtual void event_end() noexcept {}
    void end() noexcept { muf::set_dfhandler(nullptr, 0, nullptr); }
};

/// Listing 3, the MUF deferrable server (MDS): capacity C per period T at
/// criticality `high` (6 under MUF); when C is used up (MAXEXEC) it drops to
/// `low` (4: below the critical set, above the other periodic tasks); at each
/// replenishment time (its DEADLINE) it gets C back and `high` again.
class DeferrableServer final : public AperiodicServer {
public:
    DeferrableServer(std::int64_t capacity_ns, std::int64_t period_ns, int high, int low) noexcept
        : capacity_(capacity_ns), period_(period_ns), high_(high), low_(low) {}
    void begin() noexcept override;
    static muf::FailureAction handler(muf::Failure kind, void* self) noexcept;

private:
    std::int64_t capacity_, period_;
    int high_, low_;
    std::int64_t next_start_ = 0;
};

/// Listing 4, the MUF sporadic server (MSS): capacity C at `high`; the CPU
/// time an event uses at `high` comes back one period T after the event began
/// (a list of replenishments). With nothing left it runs at `low` until the
/// next replenishment. Unlike the listing, the deadline is also set to the next
/// replenishment while capacity is left, so time comes back when it is due.
class SporadicServer final : public AperiodicServer {
public:
    SporadicServer(std::int64_t capacity_ns, std::int64_t period_ns, int high, int low) noexcept
        : capacity_(capacity_ns), period_(period_ns), high_(high), low_(low) {}
    void begin() noexcept override;
    void event_begin() noexcept override;
    void event_end() noexcept override;
    static muf::FailureAction handler(muf::Failure kind, void* self) noexcept;

    static constexpr std::size_t kQueue = 64;

private:
    struct Replenishment {
        std::int64_t at = 0;      // CLOCK_MONOTONIC ns
        std::int64_t amount = 0;  // CPU ns
    };
    void refill() noexcept;  // the handler: replenishments due, then the new budget and level
    void push(std::int64_t at, std::int64_t amount) noexcept;

    std::int64_t capacity_, period_;
    int high_, low_;
    std::array<Replenishment, kQueue> queue_{};
    volatile std::size_t head_ = 0, size_ = 0;
    std::int64_t event_start_ = 0;
    std::int64_t left_at_start_ = 0;
};

/// The background server: events run at `level` (2 under MUF: above
/// non-real-time work only), with neither budget nor deadline.
class BackgroundServer final : public AperiodicServer {
public:
    explicit BackgroundServer(int level) noexcept : level_(level) {}
    void begin() noexcept override;

private:
    int level_;
};

}  // namespace chimera::sbs::detail
