// chimera/xmail.hpp — express mail (thesis §5.3): mailboxes between RTPU
// processes, mailbox interrupts, task wakeups, xmLock/xmLockFix, and the XM
// server that acts as the name server for SHM, SEM and MSG objects (§5.4).
//
// Linux mapping (docs/architecture.md §6). An RTPU is a process. Each RTPU owns
// one mailbox segment `/chimera.<sys>.xm.<rtpu>` laid out as Figure 5.1:
//   - an alive status, with the owner's pid, so a peer that died without
//     clearing it is still seen as dead;
//   - `ntasks` wakeup words (futex words) for xmBlock/xmWakeup;
//   - `nmbox` mailbox interrupt values, multiplexed in software on one
//     trigger word (the futex the XM server sleeps on) and a pending mask;
//   - `nrtpu` single-producer/single-consumer rings, ring[b] written only by
//     RTPU `b` (its bid), read only by the owner: sending never takes a lock
//     shared with another sender.
// Everything inside the segment is an offset; each process maps it anywhere.
//
// Hot paths (write, read, wakeup, block, mbox_send) are noexcept and return a
// Status; set-up (create, peer attach, name-server requests) throws Error with
// the object named.
//
// Untrusted memory (issue #15.3): every process that sends to a mailbox maps
// it writable, so nothing in it is taken on trust. The owner uses the sizes
// and offsets it created the mailbox with, and a sender those it checked
// when it attached (validate_mailbox()), kept in its Peer; the positions of a
// ring are bounded by the ring's size and every record length by the bytes
// the ring holds, before anything is copied. A bad value is refused with
// Status::corrupt and the mailbox's (or Peer's) fault_message() names the
// segment, the ring and the field; the owner drops that ring's unread bytes
// (counted in the ring's `discarded`) so that the other senders go on.
//
// Lost with a dead receiver (issue #15.2): messages a sender wrote that the
// receiving RTPU never read before it died are not lost silently. When the
// sender finds the receiver dead (a write, mbox_send or wakeup that returns
// not_alive, peer() re-attaching, check_peers(), which the XM server runs
// every 100 ms), it counts the records still in its ring there: in the
// Peer (undelivered(): they are the last ones written to it), in
// Mailbox::undelivered(), and in its own mailbox header (`undelivered`),
// which any process mapping the segment reads (no tool of this project shows
// it yet: sbs subsystems do not use express mail between RTPUs). And when an
// RTPU takes over the mailbox of a
// dead predecessor of its name, it counts what that one left unread in its
// own header (`predecessor_unread`): the loss is on record even when the
// senders died too.
#pragma once

#include "chimera/export.hpp"

#include <atomic>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include "chimera/ipc/pi_mutex.hpp"
#include "chimera/ipc/lock.hpp"
#include "chimera/ipc/segment.hpp"

namespace chimera::xm {

/// Result of a hot-path operation (express mail, SEM, MSG).
enum class [[nodiscard]] Status : int {
    ok = 0,
    would_block,     ///< non-blocking call: queue full/empty, semaphore taken, no message
    timed_out,       ///< the timeout passed
    not_alive,       ///< the destination RTPU is not running (or died)
    full,            ///< the destination buffer stayed full past the bound
    too_big,         ///< message larger than the buffer/queue/caller's space
    bad_argument,    ///< task or mailbox number out of range, ...
    lock_timeout,    ///< the object's lock could not be taken in time
    too_many_waiters,///< every waiter slot of the object is in use
    corrupt,         ///< a value read from the shared segment is out of bounds: refused,
                     ///< nothing copied (the object's fault_message() names the segment)
};
CHIMERA_API const char* to_string(Status s) noexcept;

/// A set-up error (create, attach, name server); what() names the object.
class CHIMERA_API Error : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

/// Mailbox interrupts reserved by express mail (§5.3.1); the rest are user-defined.
inline constexpr std::uint32_t kMboxReset = 0;   ///< XM_MBOX_RESET: reset the mailbox
inline constexpr std::uint32_t kMboxSigBuf = 1;  ///< XM_MBOX_SIGBUF: a message is in a buffer
inline constexpr std::uint32_t kMboxSigWkup = 2; ///< XM_MBOX_SIGWKUP: a task was woken
inline constexpr std::uint32_t kMboxUser = 3;    ///< first user-defined mailbox interrupt

/// Sizes of a mailbox (the thesis's ntasks, nrtpu, bufsize, nmbox).
struct MailboxConfig {
    std::uint32_t nrtpu = 8;      ///< RTPU ids (bids) 0..nrtpu-1 may send here
    std::uint32_t ntasks = 32;    ///< wakeup words
    std::uint32_t bufsize = 4096; ///< bytes per sender ring (rounded up to 8)
    std::uint32_t nmbox = 8;      ///< mailbox interrupts, 3..32
};

namespace layout {

inline constexpr std::uint32_t kMailboxVersion = 2;
inline constexpr std::size_t kNameMax = 31;  ///< RTPU and object names, characters

/// The mailbox segment header (after it: wakeup words, mbox values, rings).
struct MailboxHeader {
    ipc::SegmentHeader segment;
    char rtpu[32];                     ///< logical name, NUL-terminated
    std::uint32_t bid;                 ///< this RTPU's id
    std::uint32_t nrtpu, ntasks, nmbox, bufsize;
    std::uint32_t reserved0;
    std::uint64_t off_wakeup;          ///< atomic<u32>[ntasks]
    std::uint64_t off_mbox;            ///< atomic<u32>[nmbox]
    std::uint64_t off_rings;           ///< nrtpu x (RingHeader + bufsize)
    std::uint64_t ring_stride;
    alignas(64) std::atomic<std::uint32_t> alive;     ///< 1 while the owner runs
    std::atomic<std::int32_t> owner_pid;
    std::atomic<std::uint32_t> trigger;  ///< futex word: bumped by every interrupt
    std::atomic<std::uint32_t> sleeping; ///< the owner is (about to be) asleep on trigger
    std::atomic<std::uint32_t> pending;  ///< bit n: mailbox interrupt n pending
    std::atomic<std::uint32_t> resets;   ///< reset interrupts handled
    std::atomic<std::uint64_t> undelivered; ///< messages this RTPU sent that died unread with their receivers
    std::atomic<std::uint64_t> predecessor_unread; ///< messages a dead predecessor of this RTPU left unread (taken over)
    std::uint8_t reserved1[24];
};
static_assert(sizeof(MailboxHeader) == 256);

/// One sender's ring, owned by the sender with bid == index.
struct RingHeader {
    alignas(64) std::atomic<std::uint64_t> in;  ///< bytes ever written (producer)
    std::atomic<std::int32_t> producer_pid;     ///< the process that claimed this ring
    std::atomic<std::uint32_t> producer_waiting;///< the producer sleeps for space
    std::atomic<std::uint32_t> space_seq;       ///< futex word bumped by the consumer
    std::uint32_t reserved0;
    alignas(64) std::atomic<std::uint64_t> out; ///< bytes ever consumed (owner)
    std::atomic<std::uint64_t> discarded;       ///< bytes dropped by a reset
};
static_assert(sizeof(RingHeader) == 128);

/// Record header in a ring; the payload follows, padded to 8 bytes.
struct RecordHeader {
    std::uint32_t length;
    std::uint32_t reserved;
};
static_assert(sizeof(RecordHeader) == 8);

/// Total segment bytes for a config (the Linux form of the thesis's eq. 5).
CHIMERA_API std::size_t mailbox_size(const MailboxConfig& config) noexcept;

/// Where everything is in a mailbox, computed from its config (never read
/// from the segment after it was checked).
struct MailboxGeometry {
    std::uint32_t nrtpu = 0, ntasks = 0, nmbox = 0, bufsize = 0;
    std::uint64_t off_wakeup = 0, off_mbox = 0, off_rings = 0, ring_stride = 0, total = 0;
};

/// A task waiting on a SEM or MSG object (the thesis's waitlist entry). The
/// task sleeps on `word` (futex); the signaller sets it under the object's
/// lock, so a dead waiter or signaller is repaired from these fields.
struct Waiter {
    std::atomic<std::uint32_t> word;  ///< the futex it sleeps on: bit 0 signalled, 1 kicked, 2 asleep untimed; or the signaller's thread id with bit 31 (handed over)
    std::uint32_t state;              ///< 0 free, 1 waiting, 2 signalled (atomic stores: read without the lock)
    std::int32_t pid, tid;            ///< the waiting thread (atomic stores: read without the lock)
    std::int32_t priority;            ///< higher is served first
    std::uint32_t ticket;             ///< arrival order among equal priorities
    std::uint32_t handed;             ///< MSG: message header handed over (index + 1)
    std::uint32_t reserved;
};
static_assert(sizeof(Waiter) == 32);

}  // namespace layout

class Mailbox;

/// Checks a mailbox image of `size` bytes as a sender does on attach (segment
/// header, sizes, the offsets they imply, the RTPU name) and the contents of
/// every ring (positions within the ring, each record within the bytes
/// written): the first bound broken, or none. A pure function over the bytes.
CHIMERA_API ipc::Fault validate_mailbox(const void* image, std::size_t size) noexcept;

/// Another RTPU's mailbox as seen by this one (the thesis's xmheaders[bid]
/// pointers). Obtained from Mailbox::peer(); valid while the Mailbox lives.
class CHIMERA_API Peer {
public:
    const std::string& rtpu() const noexcept { return rtpu_; }
    std::uint32_t bid() const noexcept { return bid_; }
    /// The peer's mailbox header (alive word, owner pid, counters).
    const layout::MailboxHeader& header() const noexcept { return *header_; }
    /// Messages written here that its RTPU never read before it died: the
    /// last undelivered() ones written to it (0 while it lives).
    std::uint64_t undelivered() const noexcept { return undelivered_; }
    /// What the last refused operation (Status::corrupt) found, naming the segment.
    std::string fault_message() const;

private:
    friend class Mailbox;
    std::string rtpu_;
    ipc::Segment segment_;
    layout::MailboxHeader* header_ = nullptr;
    layout::MailboxGeometry geometry_;    // checked on attach
    std::uint32_t bid_ = 0;
    layout::RingHeader* ring_ = nullptr;  // our ring in the peer's mailbox
    std::byte* buffer_ = nullptr;
    std::uint64_t in_ = 0;                // our ring's write position (the truth; mirrored in ring_->in)
    // The last liveness check, shared by this RTPU's tasks: write() and
    // wakeup() update it outside write_mutex_, so atomic (relaxed: a cache).
    std::atomic<std::int64_t> last_probe_ns_{0};
    std::atomic<bool> probe_ok_{false};
    bool loss_counted_ = false;           // the receiver was found dead and its unread records counted
    std::uint64_t undelivered_ = 0;
    ipc::Fault fault_;
    ipc::PiMutex write_mutex_;  // tasks of this RTPU share our one ring (local lock; inherits priority)
};

/// What read() tells about the message it returned.
struct ReadInfo {
    std::uint32_t from_bid = 0;  ///< the sending RTPU
    std::size_t length = 0;      ///< message bytes
};

/// This RTPU's express mail: its own mailbox (xmInitLocal) plus handles to
/// the mailboxes of the other RTPUs (xmInit). One per process.
class CHIMERA_API Mailbox {
public:
    /// Creates `/chimera.<sys>.xm.<rtpu>` and marks it alive. A mailbox left by
    /// a dead process is taken over; one whose owner still runs is an error.
    Mailbox(std::string sys, std::string rtpu, std::uint32_t bid, MailboxConfig config = {});
    /// Marks the RTPU not alive and removes the segment.
    ~Mailbox();
    Mailbox(const Mailbox&) = delete;
    Mailbox& operator=(const Mailbox&) = delete;

    const std::string& sys() const noexcept { return sys_; }
    const std::string& rtpu() const noexcept { return rtpu_; }
    std::uint32_t bid() const noexcept { return bid_; }
    const MailboxConfig& config() const noexcept { return config_; }
    layout::MailboxHeader& header() noexcept { return *header_; }

    /// Attaches (once; cached) to the mailbox of RTPU `rtpu` and claims our
    /// ring in it. Throws Error when no such RTPU runs or another live process
    /// uses our bid there. A cached peer found dead is re-attached.
    Peer& peer(std::string_view rtpu);

    /// xmAlive: the peer's alive status AND its owner process exists (a
    /// system call; write() and wakeup() use a cached probe instead).
    bool alive(Peer& peer) noexcept;

    /// xmWrite: copies a message into our ring in the peer's mailbox and
    /// sends XM_MBOX_SIGBUF. Waits for space at most `timeout_ns`
    /// (0: never), then returns Status::full; Status::not_alive at once if
    /// the peer is not running.
    Status write(Peer& peer, const void* data, std::size_t length,
                 std::int64_t timeout_ns = 100'000'000) noexcept;

    /// xmRead: takes the next message from any ring (round-robin, so no
    /// sender starves) into `buffer`. would_block when every ring is empty;
    /// too_big (message left in place, length in `info`) when it does not fit.
    Status read(void* buffer, std::size_t capacity, ReadInfo* info = nullptr) noexcept;

    /// Sleeps until a mailbox interrupt arrives (or `timeout_ns` passes;
    /// negative: no limit) and returns the pending mask, cleared (0 on timeout).
    /// Values of user interrupts are in mbox_value().
    std::uint32_t wait_interrupts(std::int64_t timeout_ns) noexcept;
    /// The pending mask, cleared, without sleeping.
    std::uint32_t take_interrupts() noexcept;
    std::uint32_t mbox_value(std::uint32_t mbox) const noexcept;

    /// xmMboxSend: stores `value` (non-zero) in the peer's mailbox `mbox` and
    /// triggers it (one futex wake, only when the owner sleeps).
    Status mbox_send(Peer& peer, std::uint32_t mbox, std::uint32_t value) noexcept;

    /// xmWakeup: sets task `task`'s wakeup word on the peer and wakes it. A
    /// wakeup that arrives before the task blocks is kept (one, not counted),
    /// so a wakeup racing with xmBlock is never lost.
    Status wakeup(Peer& peer, std::uint32_t task) noexcept;
    /// xmBlock: blocks local task slot `task` until an xmWakeup (or timeout).
    Status block(std::uint32_t task, std::int64_t timeout_ns = -1) noexcept;

    /// Task slots for xmBlock, local to this process.
    std::uint32_t claim_task();
    void release_task(std::uint32_t task) noexcept;

    /// XM_MBOX_RESET handling (xmInitLocal again): drops every unread message.
    void reset_buffers() noexcept;

    /// Probes every peer this RTPU has written to; counts the messages left
    /// unread in the mailbox of each one found dead (see undelivered()).
    void check_peers() noexcept;
    /// Messages this RTPU wrote that their receivers died without reading.
    std::uint64_t undelivered() const noexcept {
        return header_->undelivered.load(std::memory_order_relaxed);
    }
    /// What the last refused read (Status::corrupt) found, naming the segment.
    std::string fault_message() const;

    /// How often write()/wakeup() re-check that a peer's process exists.
    void set_probe_period(std::int64_t ns) noexcept { probe_period_ns_ = ns; }

    /// The segment name of RTPU `rtpu`'s mailbox in system `sys`.
    static std::string segment_name(std::string_view sys, std::string_view rtpu);

private:
    bool probe(Peer& peer) noexcept;
    Status dead(Peer& peer) noexcept;
    Status dead_locked(Peer& peer) noexcept;
    void signal(layout::MailboxHeader& h, std::uint32_t mbox) noexcept;
    layout::RingHeader* own_ring(std::uint32_t b) noexcept;
    std::atomic<std::uint32_t>* own_wakeup() noexcept;

    std::string sys_, rtpu_;
    std::uint32_t bid_;
    MailboxConfig config_;
    layout::MailboxGeometry geometry_;  // of our own mailbox, as we made it
    ipc::Segment segment_;
    layout::MailboxHeader* header_ = nullptr;
    std::vector<std::uint64_t> out_;    // each ring's read position (the truth; mirrored in the ring)
    ipc::Fault fault_;
    std::uint32_t next_ring_ = 0;
    std::int64_t probe_period_ns_ = 1'000'000;
    ipc::PiMutex peers_mutex_;  // a task sending looks its peer up under it
    std::map<std::string, std::unique_ptr<Peer>, std::less<>> peers_;
    std::vector<std::unique_ptr<Peer>> retired_;  // dead peers other threads may still hold
    ipc::PiMutex tasks_mutex_;
    std::uint64_t tasks_used_[4] = {};
};

/// xmLock / xmUnlock: the ipc lock (owner TID, dead-holder recovery, timeout).
inline ipc::LockStatus lock(ipc::LockWord& word, std::int64_t timeout_ns) noexcept {
    ipc::LockOptions options;
    options.timeout_ns = timeout_ns;
    return ipc::lock(word, options);
}
[[nodiscard]] inline bool unlock(ipc::LockWord& word) noexcept { return ipc::unlock(word); }

/// xmLockFix (§5.3.2): the two-step lock for a peer that has no atomic
/// test-and-set. Step 1 picks one contender per side (RTPUs with TAS on
/// rtpumutex; hosts on hostmutex, by the lock of their own kind); step 2 is
/// Peterson's two-process algorithm between the two survivors. Unlike the
/// thesis listing, unlock also clears the caller's flag: without that a host
/// that locks after an RTPU unlocked waits until the RTPU locks again (the
/// model in tests/xmail shows the hang).
struct CHIMERA_API LockFix {
    enum Who : std::uint32_t { rtpu = 0, host = 1 };
    std::atomic<std::uint32_t> rtpumutex{0};
    std::atomic<std::uint32_t> hostmutex{0};
    std::atomic<std::uint32_t> turn{0};
    std::atomic<std::uint32_t> flag[2] = {0, 0};

    /// Returns false when `timeout_ns` (negative: no limit) passed; nothing held then.
    [[nodiscard]] bool lock(Who who, std::int64_t timeout_ns = -1) noexcept;
    void unlock(Who who) noexcept;
};
static_assert(sizeof(LockFix) == 20);

// ---------------------------------------------------------------- XM server

/// What the name server knows of an object.
struct ObjectRef {
    std::string segment;     ///< POSIX shm name to attach
    ipc::ObjectType type{};  ///< xmail_shm / xmail_sem / xmail_msg
};

/// Creation parameters passed to the owning RTPU (meaning per type: SHM
/// size; SEM kind and initial value; MSG blknum, blksize, policy).
struct ObjectParams {
    std::uint64_t a = 0, b = 0, c = 0, d = 0;
};

/// Splits "rtpu:name"; throws Error when either part is missing or too long.
CHIMERA_API std::pair<std::string, std::string> split_name(std::string_view full);

/// One RTPU process: its Mailbox plus its XM server thread. The server reads
/// every message, answers name-server requests for objects this RTPU owns,
/// routes replies to the local tasks that asked, and runs the handlers of
/// mailbox interrupts and of user messages.
class CHIMERA_API Rtpu {
public:
    Rtpu(std::string sys, std::string name, std::uint32_t bid, MailboxConfig config = {});
    /// Stops the server, destroys the objects this RTPU created, clears alive.
    ~Rtpu();
    Rtpu(const Rtpu&) = delete;
    Rtpu& operator=(const Rtpu&) = delete;

    Mailbox& mailbox() noexcept { return mailbox_; }
    const std::string& name() const noexcept { return mailbox_.rtpu(); }
    const std::string& sys() const noexcept { return mailbox_.sys(); }

    /// Asks the XM server of the RTPU named in "rtpu:name" to create an
    /// object there and returns where it lives. Throws Error (name exists
    /// with another type, RTPU not alive, no answer within the timeout...).
    ObjectRef create_object(std::string_view full_name, ipc::ObjectType type,
                            const ObjectParams& params);
    /// Resolves "rtpu:name" through its owner's XM server; Error when the name
    /// is unknown or the object is of another type.
    ObjectRef attach_object(std::string_view full_name, ipc::ObjectType type);
    /// Removes the name and unlinks the segment (mappings stay valid).
    void destroy_object(std::string_view full_name);

    /// Handler for user mailbox interrupt `mbox` (>= kMboxUser), run by the server.
    void install(std::uint32_t mbox, std::function<void(std::uint32_t value)> handler);
    /// Handler for express-mail messages that are not name-server traffic
    /// (their first 4 bytes must not be a kind below 0x100), run by the server.
    void on_message(std::function<void(std::uint32_t from_bid, const void*, std::size_t)> handler);

    /// Timeout of name-server requests.
    void set_request_timeout(std::int64_t ns) noexcept { request_timeout_ns_ = ns; }

private:
    struct Pending;
    struct Owned;
    void serve();
    void handle_message(std::uint32_t from, const std::byte* data, std::size_t length);
    void handle_request(const void* request);
    void reap_objects() noexcept;
    void sweep_orphans() noexcept;
    ObjectRef request(std::string_view full_name, std::uint32_t op, ipc::ObjectType type,
                      const ObjectParams& params);

    Mailbox mailbox_;
    std::atomic<bool> stop_{false};
    std::int64_t request_timeout_ns_ = 2'000'000'000;
    std::mutex mutex_;  // handlers, pending requests, owned objects
    std::map<std::uint32_t, std::function<void(std::uint32_t)>> handlers_;
    std::function<void(std::uint32_t, const void*, std::size_t)> message_handler_;
    std::condition_variable done_;  // a reply arrived
    std::map<std::uint32_t, std::shared_ptr<Pending>> pending_;
    std::uint32_t next_request_ = 1;
    std::map<std::string, std::unique_ptr<Owned>, std::less<>> owned_;
    std::thread server_;
};

}  // namespace chimera::xm
