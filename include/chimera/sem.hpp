// chimera/sem.hpp — remote semaphores (thesis §5.4.2).
//
// A small shared object created by the XM server of the RTPU named in
// "rtpu:name" (semCreate) or laid over memory the caller supplies: a value
// guarded by the object's xmLock, and a waitlist. P takes a unit or blocks on
// the waiter's own futex word (no spinning); V hands its unit straight to the
// highest-priority waiter (FIFO among equals) and wakes it, from any process.
// Binary semaphores hold 0 or 1 (a V on 1 stays 1); counting ones any value
// >= 0.
//
// Robustness (issue #15.2): no unit stays with a waiter that died. V hands
// its unit over and wakes the waiter; when the wake-up reaches nobody and the
// thread is gone (killed, reaped or not), V takes the unit back and passes it
// on before returning. A waiter killed after its wake-up reached it is found
// by the waiters still blocked, which look every kWaitSlice (20 ms) and pass
// its unit on, and by any P that finds no unit; a holder of the lock that
// died is repaired by the next user. (The only waiter, without a time limit,
// sleeps without a timer; the next waiter to join wakes it into the looks. A
// V killed between handing its unit over and its wake-up leaves the waiter
// woken by the kernel: the hand-off is marked in V's robust-futex list while
// it lasts.)
#pragma once

#include "chimera/export.hpp"

#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include "chimera/ipc/lock.hpp"
#include "chimera/ipc/segment.hpp"
#include "chimera/xmail.hpp"

namespace chimera::sem {

using xm::Status;

enum class Kind : std::uint32_t { binary = 0, counting = 1 };

namespace layout {

inline constexpr std::uint32_t kSemVersion = 1;
inline constexpr std::uint32_t kMaxWaiters = 32;

struct SemHeader {
    ipc::SegmentHeader segment;
    ipc::LockWord mutex;        ///< xmLock
    char name[64];
    std::int32_t value;         ///< units available (>= 0)
    std::uint32_t kind;         ///< Kind
    std::uint32_t next_ticket;
    std::uint32_t recoveries;   ///< dead lock holders repaired after
    std::uint32_t reclaimed_waiters;
    std::uint32_t reserved[11];
    xm::layout::Waiter waiters[kMaxWaiters];
};
static_assert(sizeof(SemHeader) == 256 + 32 * kMaxWaiters);

}  // namespace layout

/// Checks a semaphore's image of `size` bytes (segment header, kind, value
/// in range for the kind, waiter states, the name ending in its field): the
/// first bound broken, or none. A pure function over the bytes. (Nothing in
/// a semaphore is an offset; attach and bind check all but the value and
/// the waiters, which P and V keep in range themselves.)
CHIMERA_API ipc::Fault validate(const void* image, std::size_t size) noexcept;

class CHIMERA_API Semaphore {
public:
    Semaphore() = default;
    Semaphore(Semaphore&&) noexcept;
    Semaphore& operator=(Semaphore&&) noexcept;
    ~Semaphore();

    /// semCreate: binary (initial 0 or 1) or counting (initial >= 0).
    static Semaphore create(xm::Rtpu& self, std::string_view full_name, Kind kind,
                            std::int32_t initial);
    /// semAttach.
    static Semaphore attach(xm::Rtpu& self, std::string_view full_name);

    static constexpr std::size_t memory_size() noexcept { return sizeof(layout::SemHeader); }
    /// A semaphore in caller-supplied memory (memory_size() bytes, 64-aligned).
    static Semaphore over(void* memory, Kind kind, std::int32_t initial,
                          std::string_view label = "local");
    static Semaphore bind(void* memory);

    /// semP. timeout: negative blocks, 0 never blocks (would_block), > 0 timed
    /// from the moment the call first has to wait.
    /// `priority`: waiters with a higher one get the next V first.
    Status p(std::int64_t timeout_ns = -1, std::int32_t priority = 0) noexcept;
    Status try_p() noexcept { return p(0); }
    /// semV.
    Status v() noexcept;

    /// Units available now.
    std::int32_t value() noexcept;
    /// Tasks blocked in P now.
    std::uint32_t waiting() noexcept;
    std::uint32_t recoveries() const noexcept { return h_ ? h_->recoveries : 0; }

    /// semDetach: the last user of a named semaphore frees it.
    void detach() noexcept;
    /// semDestroy: remove the name through the owner's XM server.
    void destroy(xm::Rtpu& self);

    bool valid() const noexcept { return h_ != nullptr; }
    Kind kind() const noexcept { return static_cast<Kind>(h_->kind); }
    const std::string& name() const noexcept { return name_; }

private:
    static Semaphore map(const xm::ObjectRef& ref, std::string_view full_name);
    Status lock() noexcept;
    void repair() noexcept;
    /// V's body, lock held; returns the waiter to wake after unlocking.
    xm::layout::Waiter* release_unit() noexcept;
    bool reclaim_granted() noexcept;
    void pass_on_dead_grants(const xm::layout::Waiter* self) noexcept;
    layout::SemHeader* h_ = nullptr;
    ipc::Segment segment_;
    std::string name_;
};

}  // namespace chimera::sem
