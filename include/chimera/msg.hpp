// chimera/msg.hpp — prioritized message queues (thesis §5.4.3, Figure 5.2).
//
// A queue is one shared segment created by the XM server of the RTPU named
// in "rtpu:name" (or laid over memory the caller supplies). Its layout is
// Figure 5.2: `blknum` message headers (msgHead: type, priority, size, link
// to the first block) on the lists headfree / headused (+ tailused), and
// `blknum` data blocks of `blksize` bytes (each led by msgBHead with its own
// link) on blkfree. A message longer than blksize takes several linked
// blocks, up to blksize*blknum. Every link is an offset from the queue's base,
// so each process maps the queue at its own address. Nothing is allocated on
// send or receive.
//
// Insertion policy: FIFO (at tailused), LIFO (at the head) or HPF (insertion
// sort; equal priorities stay FIFO). Receivers waiting on an empty queue are
// served highest task priority first (FIFO among equals): a send hands its
// message straight to that waiter. Senders waiting on a full queue are woken
// highest message priority first.
//
// Timeouts everywhere: negative blocks, 0 never blocks (would_block), > 0
// waits at most that long (timed_out).
//
// Robustness: a process killed inside send/receive leaves the lock to be
// recovered by the next user, which then repairs the queue from per-header
// states, as a journal: a message is in the queue iff its header is QUEUED
// (the commit point of send), or HANDED to a live waiter; an interrupted
// receive (READING) is rolled back into the queue; an interrupted send
// (WRITING) is rolled back (its blocks freed); the lists are then rebuilt in
// policy order from each message's sequence number and priority. Waiters that
// died are dropped and a message handed to one goes back into the queue; a
// live waiter keeps a handed message only if the hand-off was complete (slot
// signalled and header HANDED), otherwise the message is queued again.
// A receiver that dies after a message was handed to it loses nothing: when
// the sender's wake-up reaches nobody and the thread is gone, the sender
// takes the message back and hands it on (or queues it) before send()
// returns; a receiver killed after its wake-up reached it is found by the
// receivers still blocked, which look every 20 ms, and by any receive that
// finds the queue empty. The same holds for the turn of a waiting sender.
// (A waiter without a time limit that is the only one of its list sleeps
// without a timer, as a blocking mq_receive does; the next waiter to join
// wakes it into the 20 ms looks, since only another waiter can die with what
// it was given. A sender killed between handing a message over and its
// wake-up leaves it woken by the kernel: the hand-off is marked in the
// sender's robust-futex list while it lasts.)
//
// Untrusted memory (issue #15.3): the geometry is checked on attach and kept
// in the handle; every link, index and size read from the segment is checked
// before it is followed or used (inside the headers or blocks, no list longer
// than blknum, a message no larger than its blocks or the caller's buffer).
// A bad one is refused with Status::corrupt before anything is changed, and
// fault_message() names the segment and the field. The queue is left as it
// is: a corrupt queue is not repaired behind its users' backs.
#pragma once

#include "chimera/export.hpp"

#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include "chimera/ipc/lock.hpp"
#include "chimera/ipc/segment.hpp"
#include "chimera/xmail.hpp"

namespace chimera::msg {

using xm::Status;

enum class Policy : std::uint32_t { fifo = 0, lifo = 1, hpf = 2 };

/// msgCreate's arguments.
struct Params {
    std::uint32_t blknum = 64;   ///< headers and blocks (maximum messages)
    std::uint32_t blksize = 64;  ///< bytes per block (rounded up to 8)
    Policy policy = Policy::fifo;
};

/// What receive() says about the message it returned.
struct Info {
    std::uint32_t type = 0;
    std::int32_t priority = 0;
    std::size_t size = 0;
};

namespace layout {

inline constexpr std::uint32_t kQueueVersion = 1;
inline constexpr std::uint32_t kMaxWaiters = 16;  ///< per direction

/// Header states: the journal that makes an interrupted operation repairable.
enum HeadState : std::uint32_t {
    kHeadFree = 0, kHeadWriting = 1, kHeadQueued = 2, kHeadHanded = 3, kHeadReading = 4,
};

/// msgHead: one message.
struct MsgHead {
    std::uint32_t link;       ///< next header on its list (offset), 0 = nil
    std::uint32_t state;      ///< HeadState
    std::uint32_t type;
    std::int32_t priority;
    std::uint32_t size;       ///< bytes
    std::uint32_t blk;        ///< first block (offset), 0 = nil
    std::uint32_t nblk;
    std::uint32_t seq;        ///< commit order, for FIFO/LIFO order and repair
    std::int32_t pid, tid;    ///< the thread in WRITING/READING
};
static_assert(sizeof(MsgHead) == 40);

/// msgBHead: leads each data block.
struct MsgBHead {
    std::uint32_t link;   ///< next block of the same message / of blkfree
    std::uint32_t owner;  ///< header index + 1 while the block holds a message
};
static_assert(sizeof(MsgBHead) == 8);

/// The msgQueue object of Figure 5.2.
struct QueueHeader {
    ipc::SegmentHeader segment;
    ipc::LockWord mutex;          ///< xmLock
    char segname[64];             ///< "rtpu:name" (or a caller's label)
    std::uint32_t blknum, blksize, flags, block_stride;
    std::uint32_t headfree, headused, tailused, blkfree;
    // nmsgs and nhanded are also read without the lock (an empty queue is
    // polled without it), so they are written with atomic stores.
    std::uint32_t nmsgs, nfree_heads, nfree_blks, next_seq;
    std::uint32_t nhanded, recoveries, next_ticket, reclaimed_waiters;
    std::uint32_t off_heads, off_blocks, sends, receives;
    std::uint32_t reserved[12];
    xm::layout::Waiter recv_waiters[kMaxWaiters];
    xm::layout::Waiter send_waiters[kMaxWaiters];
};
static_assert(sizeof(QueueHeader) == 320 + 2 * 32 * kMaxWaiters);

/// Where everything is in a queue, computed from its parameters (blknum,
/// blksize, policy), never read from the segment after it was checked.
struct Geometry {
    std::uint32_t blknum = 0, blksize = 0, policy = 0;
    std::uint32_t stride = 0;      ///< msgBHead + blksize
    std::uint32_t off_heads = 0, off_blocks = 0;
    std::uint64_t total = 0;       ///< bytes
};

}  // namespace layout

/// Checks the fixed part of a queue's image of `size` bytes (segment header,
/// parameters, the offsets they imply), as attach() and bind() do: the first
/// bound broken, or none. A pure function over the bytes.
CHIMERA_API ipc::Fault validate_geometry(const void* image, std::size_t size) noexcept;
/// validate_geometry() and the structure of a queue at rest (no operation in
/// progress): every list link and block chain inside the queue, no list
/// longer than blknum, each message's size within its blocks, every waiter's
/// handed message in range, the counts matching the lists. For fuzzers and
/// check(); the operations check each link as they follow it.
CHIMERA_API ipc::Fault validate(const void* image, std::size_t size) noexcept;

/// Counters of a queue.
struct Stats {
    std::uint32_t messages = 0;          ///< in headused
    std::uint32_t handed = 0;            ///< handed to a waiter, not yet taken
    std::uint32_t free_headers = 0, free_blocks = 0;
    std::uint32_t receive_waiters = 0, send_waiters = 0;
    std::uint32_t recoveries = 0;        ///< dead lock holders repaired after
    std::uint32_t reclaimed_waiters = 0; ///< waiters found dead
    std::uint32_t lock_recoveries = 0;   ///< the ipc lock's own count
};

/// A mapping of one queue (msgAttach's result). Move-only.
class CHIMERA_API Queue {
public:
    Queue() = default;
    Queue(Queue&&) noexcept;
    Queue& operator=(Queue&&) noexcept;
    ~Queue();

    /// msgCreate: the XM server of the owning RTPU creates the queue.
    static Queue create(xm::Rtpu& self, std::string_view full_name, const Params& params);
    /// msgAttach.
    static Queue attach(xm::Rtpu& self, std::string_view full_name);

    /// Bytes a queue with these parameters needs.
    static std::size_t memory_size(const Params& params);
    /// Lays a new queue over caller-supplied memory (8-byte aligned, zeroed
    /// or not); throws xm::Error on bad parameters or too little memory.
    static Queue over(void* memory, std::size_t size, const Params& params,
                      std::string_view label = "local");
    /// Binds to a queue already laid over `memory` (validates the header).
    static Queue bind(void* memory, std::size_t size);

    /// msgSend: `size` bytes, up to blksize*blknum. Timeouts (here and in
    /// receive): negative blocks, 0 never blocks (would_block), > 0 is counted
    /// from the moment the call first has to wait (a call that need not wait
    /// reads no clock).
    Status send(const void* data, std::size_t size, std::uint32_t type = 0,
                std::int32_t priority = 0, std::int64_t timeout_ns = -1) noexcept;
    /// msgReceive into `buffer`; too_big (message left queued, its size in
    /// `info`) when it does not fit. `task_priority` orders waiting receivers.
    Status receive(void* buffer, std::size_t capacity, Info* info = nullptr,
                   std::int64_t timeout_ns = -1, std::int32_t task_priority = 0) noexcept;

    Stats stats() noexcept;
    /// Checks every structural invariant under the lock (after repairing a
    /// dead holder's work); "" when consistent, else what is wrong.
    std::string check();
    /// Sequence of (priority, type, size) in headused order, for tests.
    std::string dump();

    /// msgDetach: unmap; the last user of a named queue frees it.
    void detach() noexcept;
    /// msgDestroy: remove the name through the owner's XM server.
    void destroy(xm::Rtpu& self);

    bool valid() const noexcept { return q_ != nullptr; }
    const std::string& name() const noexcept { return name_; }
    std::uint32_t blknum() const noexcept { return g_.blknum; }
    std::uint32_t blksize() const noexcept { return g_.blksize; }
    Policy policy() const noexcept { return static_cast<Policy>(g_.policy); }
    layout::QueueHeader* header() const noexcept { return q_; }
    /// What the last operation refused (Status::corrupt) found, naming the
    /// segment; "" if none.
    std::string fault_message() const;

    struct Ops;  ///< internal (msg.cpp): the queue as this handle checked it

private:
    Status lock() noexcept;
    void repair() noexcept;
    static Queue bound(layout::QueueHeader* q, std::size_t size, std::string where);
    static Queue attach_ref(const xm::ObjectRef& ref, std::string_view full_name);
    Status refuse(const ipc::Fault& fault) noexcept;
    Status unlock_and_wake(xm::layout::Waiter* w) noexcept;
    void pass_on_dead(const xm::layout::Waiter* self) noexcept;
    void prefetch_hot_lines() const noexcept;

    layout::QueueHeader* q_ = nullptr;
    layout::Geometry g_;    // checked on attach: never re-read from the segment
    ipc::Segment segment_;  // invalid for a queue over caller memory
    std::string name_;
    std::string where_;     // the segment's name (or the caller memory's label), for faults
    ipc::Fault fault_;
    // The header and first block this handle last sent or received (0: none):
    // the free lists are LIFO, so the next operation on the queue most
    // likely uses them again (see prefetch_hot_lines in msg.cpp).
    std::uint32_t hint_head_ = 0, hint_block_ = 0;
};

}  // namespace chimera::msg
