// Express-mail mailboxes (thesis §5.3.1, Figure 5.1) over one POSIX shm
// segment per RTPU process.
#include <signal.h>
#include <unistd.h>

#include <algorithm>
#include <cstring>
#include <new>

#include "chimera/ipc/clock.hpp"
#include "chimera/ipc/futex.hpp"
#include "chimera/xmail.hpp"

namespace chimera::xm {

using layout::MailboxHeader;
using layout::RecordHeader;
using layout::RingHeader;

const char* to_string(Status s) noexcept {
    switch (s) {
        case Status::ok: return "ok";
        case Status::would_block: return "would block";
        case Status::timed_out: return "timed out";
        case Status::not_alive: return "destination RTPU not alive";
        case Status::full: return "destination buffer full";
        case Status::too_big: return "message too big";
        case Status::bad_argument: return "bad argument";
        case Status::lock_timeout: return "lock timed out";
        case Status::too_many_waiters: return "too many waiters";
        case Status::corrupt: return "shared memory corrupt (refused)";
    }
    return "unknown status";
}

namespace {

using layout::MailboxGeometry;

constexpr ipc::SegmentKind kMailboxKind{ipc::ObjectType::xmail_mailbox, layout::kMailboxVersion};

constexpr std::uint64_t round8(std::uint64_t n) noexcept { return (n + 7) & ~std::uint64_t{7}; }

constexpr std::uint32_t kMaxNrtpu = 64, kMaxNtasks = 256, kMaxNmbox = 32;
constexpr std::uint64_t kMaxBufsize = std::uint64_t{1} << 30;

std::uint32_t ring_bytes(const MailboxConfig& c) noexcept {
    return static_cast<std::uint32_t>(round8(std::max<std::uint32_t>(c.bufsize, 64)));
}

MailboxGeometry geometry_for(std::uint32_t nrtpu, std::uint32_t ntasks, std::uint32_t nmbox,
                             std::uint32_t bufsize) noexcept {
    MailboxGeometry g{};
    g.nrtpu = nrtpu;
    g.ntasks = ntasks;
    g.nmbox = nmbox;
    g.bufsize = bufsize;
    g.off_wakeup = sizeof(MailboxHeader);
    g.off_mbox = g.off_wakeup + 4ull * ntasks;
    g.off_rings = ipc::align_up(g.off_mbox + 4ull * nmbox, 64);
    g.ring_stride = ipc::align_up(sizeof(RingHeader) + std::uint64_t{bufsize}, 64);
    g.total = g.off_rings + g.ring_stride * nrtpu;
    return g;
}

MailboxGeometry geometry_for(const MailboxConfig& c) noexcept {
    return geometry_for(c.nrtpu, c.ntasks, c.nmbox, ring_bytes(c));
}

// A process that exists and is not a zombie (pid == its main thread's tid).
bool process_alive(std::int32_t pid) noexcept {
    if (pid <= 0) return false;
    const auto p = static_cast<std::uint64_t>(static_cast<std::uint32_t>(pid));
    return ipc::owner_alive(p << 32 | p);
}

template <typename T>
T* at(void* base, std::uint64_t offset) noexcept {
    return reinterpret_cast<T*>(static_cast<std::byte*>(base) + offset);
}
RingHeader* ring_at(void* base, const MailboxGeometry& g, std::uint32_t b) noexcept {
    return at<RingHeader>(base, g.off_rings + g.ring_stride * b);
}
std::byte* ring_buffer(RingHeader* r) noexcept {
    return reinterpret_cast<std::byte*>(r) + sizeof(RingHeader);
}

// Copies into / out of a ring buffer at position `pos`, wrapping.
void ring_put(std::byte* buf, std::uint32_t size, std::uint64_t pos, const void* src,
              std::size_t n) noexcept {
    const auto at = static_cast<std::uint32_t>(pos % size);
    const std::size_t first = std::min<std::size_t>(n, size - at);
    std::memcpy(buf + at, src, first);
    if (n > first) std::memcpy(buf, static_cast<const std::byte*>(src) + first, n - first);
}
void ring_get(const std::byte* buf, std::uint32_t size, std::uint64_t pos, void* dst,
              std::size_t n) noexcept {
    const auto at = static_cast<std::uint32_t>(pos % size);
    const std::size_t first = std::min<std::size_t>(n, size - at);
    std::memcpy(dst, buf + at, first);
    if (n > first) std::memcpy(static_cast<std::byte*>(dst) + first, buf, n - first);
}

// The bytes written and not yet read in a ring of `size` bytes: bounded by
// the ring, a whole number of records (8-byte units).
ipc::Fault unread_fault(std::uint64_t in, std::uint64_t out, std::uint32_t size,
                        std::int64_t ring) noexcept {
    if (in - out > size) return {"ring fill (written - read)", ring, in - out, size};
    return ipc::fault_if((in - out) % 8 != 0, "ring fill (written - read), in 8-byte units",
                         in - out, 8, "a multiple of", ring);
}

// The record at `pos`: its length, bounded by the bytes left before `in`.
ipc::Fault record_fault(const std::byte* buf, std::uint32_t size, std::uint64_t pos, std::uint64_t in,
                        std::int64_t ring, std::uint32_t& length) noexcept {
    RecordHeader rec;
    ring_get(buf, size, pos, &rec, sizeof rec);
    length = rec.length;
    const std::uint64_t left = in - pos - sizeof rec;
    return ipc::fault_if(round8(rec.length) > left, "ring record length", rec.length, left, "at most",
                         ring);
}

// Records between `out` and `in`; a fault when a length runs past `in`.
ipc::Fault count_records(const std::byte* buf, std::uint32_t size, std::uint64_t out, std::uint64_t in,
                         std::int64_t ring, std::uint64_t& count) noexcept {
    count = 0;
    if (ipc::Fault f = unread_fault(in, out, size, ring)) return f;
    for (std::uint64_t pos = out; pos != in; ++count) {
        std::uint32_t length = 0;
        if (ipc::Fault f = record_fault(buf, size, pos, in, ring, length)) return f;
        pos += sizeof(RecordHeader) + round8(length);
    }
    return {};
}

// The fixed part of a mailbox image; on success `g` is its geometry.
ipc::Fault geometry_fault(const void* image, std::size_t size, MailboxGeometry& g) noexcept {
    if (ipc::Fault f = ipc::header_fault(image, size, kMailboxKind)) return f;
    if (size < sizeof(MailboxHeader)) return {"size", -1, size, sizeof(MailboxHeader), "at least"};
    const auto& h = *static_cast<const MailboxHeader*>(image);
    using ipc::fault_if;
    if (ipc::Fault f = fault_if(h.nrtpu == 0 || h.nrtpu > kMaxNrtpu, "nrtpu", h.nrtpu, kMaxNrtpu, "1 to")) return f;
    if (ipc::Fault f = fault_if(h.bid >= h.nrtpu, "bid", h.bid, h.nrtpu, "below")) return f;
    if (ipc::Fault f = fault_if(h.ntasks == 0 || h.ntasks > kMaxNtasks, "ntasks", h.ntasks, kMaxNtasks, "1 to")) return f;
    if (ipc::Fault f = fault_if(h.nmbox < kMboxUser || h.nmbox > kMaxNmbox, "nmbox", h.nmbox, kMaxNmbox, "3 to")) return f;
    if (ipc::Fault f = fault_if(h.bufsize < 64 || h.bufsize > kMaxBufsize || h.bufsize % 8 != 0,
                                "bufsize (a multiple of 8)", h.bufsize, kMaxBufsize, "64 to"))
        return f;
    if (ipc::Fault f = fault_if(strnlen(h.rtpu, sizeof h.rtpu) == sizeof h.rtpu, "RTPU name length",
                                sizeof h.rtpu, sizeof h.rtpu - 1))
        return f;
    g = geometry_for(h.nrtpu, h.ntasks, h.nmbox, h.bufsize);
    if (ipc::Fault f = fault_if(h.off_wakeup != g.off_wakeup, "wakeup offset", h.off_wakeup, g.off_wakeup, "equal to")) return f;
    if (ipc::Fault f = fault_if(h.off_mbox != g.off_mbox, "mailbox interrupt offset", h.off_mbox, g.off_mbox, "equal to")) return f;
    if (ipc::Fault f = fault_if(h.off_rings != g.off_rings, "ring offset", h.off_rings, g.off_rings, "equal to")) return f;
    if (ipc::Fault f = fault_if(h.ring_stride != g.ring_stride, "ring stride", h.ring_stride, g.ring_stride, "equal to")) return f;
    return fault_if(g.total != size, "mailbox size", g.total, size, "equal to");
}

void copy_name(char (&dst)[32], std::string_view src) noexcept {
    std::memset(dst, 0, sizeof dst);
    std::memcpy(dst, src.data(), std::min(src.size(), sizeof dst - 1));
}

// Messages left unread in every ring of a mailbox image (a ring that cannot
// be walked counts one: something was lost there).
std::uint64_t unread_messages(void* image, std::size_t size) noexcept {
    MailboxGeometry g;
    if (geometry_fault(image, size, g)) return 0;
    std::uint64_t total = 0;
    for (std::uint32_t b = 0; b < g.nrtpu; ++b) {
        RingHeader* r = ring_at(image, g, b);
        std::uint64_t count = 0;
        if (count_records(ring_buffer(r), g.bufsize, r->out.load(std::memory_order_acquire),
                          r->in.load(std::memory_order_acquire), b, count))
            count = std::max<std::uint64_t>(count, 1);
        total += count;
    }
    return total;
}

}  // namespace

ipc::Fault validate_mailbox(const void* image, std::size_t size) noexcept {
    MailboxGeometry g;
    if (ipc::Fault f = geometry_fault(image, size, g)) return f;
    void* base = const_cast<void*>(image);  // read only below
    for (std::uint32_t b = 0; b < g.nrtpu; ++b) {
        RingHeader* r = ring_at(base, g, b);
        std::uint64_t count = 0;
        if (ipc::Fault f = count_records(ring_buffer(r), g.bufsize, r->out.load(std::memory_order_relaxed),
                                         r->in.load(std::memory_order_relaxed), b, count))
            return f;
    }
    return {};
}

std::size_t layout::mailbox_size(const MailboxConfig& config) noexcept {
    return geometry_for(config).total;
}

std::string Mailbox::segment_name(std::string_view sys, std::string_view rtpu) {
    std::string object = "xm.";
    object += rtpu;
    return ipc::segment_name(sys, object);
}

Mailbox::Mailbox(std::string sys, std::string rtpu, std::uint32_t bid, MailboxConfig config)
    : sys_(std::move(sys)), rtpu_(std::move(rtpu)), bid_(bid), config_(config) {
    const std::string where = "mailbox of RTPU '" + rtpu_ + "'";
    if (rtpu_.empty() || rtpu_.size() > layout::kNameMax || rtpu_.find(':') != std::string::npos)
        throw Error(where + ": an RTPU name has 1.." + std::to_string(layout::kNameMax) +
                    " characters and no ':'");
    if (config_.nrtpu == 0 || config_.nrtpu > 64 || bid_ >= config_.nrtpu)
        throw Error(where + ": bid " + std::to_string(bid_) + " not below nrtpu " +
                    std::to_string(config_.nrtpu) + " (nrtpu 1..64)");
    if (config_.ntasks == 0 || config_.ntasks > 256)
        throw Error(where + ": ntasks must be 1..256");
    if (config_.nmbox < kMboxUser || config_.nmbox > 32)
        throw Error(where + ": nmbox must be 3..32");
    config_.bufsize = ring_bytes(config_);
    const std::string name = segment_name(sys_, rtpu_);

    // A mailbox left behind by a process that died is ours to take over;
    // the messages it left unread are counted (see predecessor_unread).
    std::uint64_t inherited = 0;
    if (ipc::Segment::exists(name)) {
        std::int32_t pid = 0;
        try {
            ipc::AttachOptions opt;
            opt.ready_timeout_ns = 0;
            auto old = ipc::Segment::attach(name, kMailboxKind, opt);
            auto* h = static_cast<MailboxHeader*>(old.base());
            pid = h->owner_pid.load();
            if (h->alive.load() != 0 && process_alive(pid))
                throw Error(where + ": RTPU already running (pid " + std::to_string(pid) + ")");
            inherited = unread_messages(old.base(), old.size());
        } catch (const ipc::SegmentError&) {
            // A stale segment of another layout or half-built: replace it.
        }
        ipc::Segment::unlink(name);
    }

    geometry_ = geometry_for(config_);
    const MailboxGeometry& g = geometry_;
    try {
        segment_ = ipc::Segment::create(name, g.total, kMailboxKind);
    } catch (const ipc::SegmentError& e) {
        throw Error(where + ": " + e.what());
    }
    header_ = static_cast<MailboxHeader*>(segment_.base());
    out_.assign(g.nrtpu, 0);
    // The segment is zero-filled: atomics start at 0, rings empty.
    copy_name(header_->rtpu, rtpu_);
    header_->bid = bid_;
    header_->nrtpu = g.nrtpu;
    header_->ntasks = g.ntasks;
    header_->nmbox = g.nmbox;
    header_->bufsize = g.bufsize;
    header_->off_wakeup = g.off_wakeup;
    header_->off_mbox = g.off_mbox;
    header_->off_rings = g.off_rings;
    header_->ring_stride = g.ring_stride;
    header_->predecessor_unread.store(inherited, std::memory_order_relaxed);
    header_->owner_pid.store(getpid());
    header_->alive.store(1);
    segment_.publish();
}

Mailbox::~Mailbox() {
    if (!header_) return;
    header_->alive.store(0);
    // Wake senders waiting for space so they see "not alive" at once.
    for (std::uint32_t b = 0; b < geometry_.nrtpu; ++b) {
        RingHeader* r = own_ring(b);
        r->space_seq.fetch_add(1);
        ipc::futex_wake_all(r->space_seq);
    }
    {
        std::lock_guard lock(peers_mutex_);
        // The mailbox of an RTPU that died is nobody's: its last user frees it
        // (a restarted RTPU of that name has a new segment, which stays).
        auto release = [this](Peer& p) {
            if (!p.loss_counted_ && !alive(p)) (void)dead(p);  // counts its unread records
            if (p.loss_counted_) p.segment_.detach_destroy_if_last();
        };
        for (auto& [name, p] : peers_) release(*p);
        for (auto& p : retired_) release(*p);
        peers_.clear();
        retired_.clear();
    }
    const std::string name = segment_.name();
    segment_.detach();
    ipc::Segment::unlink(name);
}

RingHeader* Mailbox::own_ring(std::uint32_t b) noexcept { return ring_at(header_, geometry_, b); }

std::atomic<std::uint32_t>* Mailbox::own_wakeup() noexcept {
    return at<std::atomic<std::uint32_t>>(header_, geometry_.off_wakeup);
}

std::string Mailbox::fault_message() const { return ipc::describe(segment_.name(), fault_); }

std::string Peer::fault_message() const { return ipc::describe(segment_.name(), fault_); }

Peer& Mailbox::peer(std::string_view rtpu) {
    std::lock_guard lock(peers_mutex_);
    auto it = peers_.find(rtpu);
    if (it != peers_.end()) {
        Peer& p = *it->second;
        bool counted = false;  // once found dead, dead for good (see write()), whatever a probe says
        {
            std::lock_guard local(p.write_mutex_);
            counted = p.loss_counted_;
        }
        // The probe's system calls outside the write lock: writers of this Peer go on meanwhile.
        if (!counted && p.header_->alive.load() != 0 && process_alive(p.header_->owner_pid.load()))
            return p;
        (void)dead_locked(p);  // died or restarted: count what it left unread, then look again
        retired_.push_back(std::move(it->second));
        peers_.erase(it);
    }
    const std::string name = segment_name(sys_, rtpu);
    const std::string where = "RTPU '" + std::string(rtpu) + "'";
    auto p = std::make_unique<Peer>();
    p->rtpu_ = std::string(rtpu);
    try {
        p->segment_ = ipc::Segment::attach(name, kMailboxKind);
    } catch (const ipc::SegmentError& e) {
        if (e.error_number() == ENOENT) throw Error(where + ": no such RTPU is running");
        throw Error(where + ": " + e.what());
    }
    // Everything a sender uses is checked once here and kept in the Peer.
    if (const ipc::Fault f = geometry_fault(p->segment_.base(), p->segment_.size(), p->geometry_))
        throw Error(where + ": corrupt mailbox: " + ipc::describe(name, f));
    p->header_ = static_cast<MailboxHeader*>(p->segment_.base());
    MailboxHeader& h = *p->header_;
    p->bid_ = h.bid;
    if (h.alive.load() == 0 || !process_alive(h.owner_pid.load()))
        throw Error(where + ": not alive");
    if (bid_ >= p->geometry_.nrtpu)
        throw Error(where + ": its mailbox takes bids below " + std::to_string(p->geometry_.nrtpu) +
                    ", this RTPU is bid " + std::to_string(bid_));
    p->ring_ = ring_at(p->header_, p->geometry_, bid_);
    p->buffer_ = ring_buffer(p->ring_);
    // Claim our ring: one producer per ring is what makes sending lock-free.
    const std::int32_t me = getpid();
    std::int32_t holder = p->ring_->producer_pid.load();
    while (holder != me) {
        if (holder != 0 && process_alive(holder))
            throw Error(where + ": bid " + std::to_string(bid_) +
                        " is already used by live process " + std::to_string(holder) +
                        " (two RTPUs with the same bid)");
        if (p->ring_->producer_pid.compare_exchange_strong(holder, me)) break;
    }
    // Go on from where a predecessor with our bid stopped (its ring may hold unread messages).
    p->in_ = p->ring_->in.load(std::memory_order_acquire);
    if (const ipc::Fault f = unread_fault(p->in_, p->ring_->out.load(std::memory_order_acquire),
                                          p->geometry_.bufsize, bid_))
        throw Error(where + ": corrupt mailbox: " + ipc::describe(name, f));
    p->probe_ok_.store(true, std::memory_order_relaxed);
    p->last_probe_ns_.store(ipc::now_ns(), std::memory_order_relaxed);
    Peer& ref = *p;
    peers_.emplace(std::string(rtpu), std::move(p));
    return ref;
}

bool Mailbox::alive(Peer& peer) noexcept {
    const bool ok = peer.header_->alive.load(std::memory_order_acquire) != 0 &&
                    process_alive(peer.header_->owner_pid.load(std::memory_order_relaxed));
    peer.probe_ok_.store(ok, std::memory_order_relaxed);
    peer.last_probe_ns_.store(ipc::now_ns(), std::memory_order_relaxed);
    return ok;
}

// The cheap form of xmAlive for the hot path: the flag every time, the
// process check at most once per probe period.
bool Mailbox::probe(Peer& peer) noexcept {
    if (peer.header_->alive.load(std::memory_order_acquire) == 0) return false;
    if (ipc::now_ns() - peer.last_probe_ns_.load(std::memory_order_relaxed) < probe_period_ns_)
        return peer.probe_ok_.load(std::memory_order_relaxed);
    return alive(peer);
}

// The receiver is not alive: once per incarnation, count the messages we
// wrote that it never read (the records left between its read position and
// ours), so that the loss is reported, not silent. Returns not_alive. The
// caller holds the Peer's write lock (dead_locked() takes it).
Status Mailbox::dead_locked(Peer& peer) noexcept {
    std::lock_guard local(peer.write_mutex_);
    return dead(peer);
}

Status Mailbox::dead(Peer& peer) noexcept {
    if (peer.loss_counted_) return Status::not_alive;
    peer.loss_counted_ = true;
    std::uint64_t count = 0;
    if (ipc::Fault f = count_records(peer.buffer_, peer.geometry_.bufsize,
                                     peer.ring_->out.load(std::memory_order_acquire), peer.in_, bid_,
                                     count)) {
        // Records we cannot walk any more: at least one message was lost.
        peer.fault_ = f;
        count = std::max<std::uint64_t>(count, 1);
    }
    peer.undelivered_ += count;
    header_->undelivered.fetch_add(count, std::memory_order_relaxed);
    return Status::not_alive;
}

void Mailbox::check_peers() noexcept {
    std::lock_guard lock(peers_mutex_);
    for (auto& [name, p] : peers_) {
        std::lock_guard local(p->write_mutex_);
        if (!p->loss_counted_ && !alive(*p)) (void)dead(*p);  // counts its unread records
    }
}

void Mailbox::signal(MailboxHeader& h, std::uint32_t mbox) noexcept {
    h.pending.fetch_or(1u << mbox, std::memory_order_seq_cst);
    h.trigger.fetch_add(1, std::memory_order_seq_cst);
    // The system call only when the owner sleeps (or is about to).
    if (h.sleeping.load(std::memory_order_seq_cst) != 0) ipc::futex_wake_all(h.trigger);
}

Status Mailbox::write(Peer& peer, const void* data, std::size_t length,
                      std::int64_t timeout_ns) noexcept {
    MailboxHeader& h = *peer.header_;
    const std::uint32_t size = peer.geometry_.bufsize;
    const std::uint64_t need = sizeof(RecordHeader) + round8(length);
    if (need > size) return Status::too_big;
    if (!probe(peer)) return dead_locked(peer);
    std::lock_guard local(peer.write_mutex_);
    // Its unread messages were counted when it was found dead: a message
    // written now would be in no count, lost unreported. A probe may still
    // say alive afterwards (a pid reused; or, before owner_alive() knew
    // ESRCH from /proc, a process reaped while it was looked at).
    if (peer.loss_counted_) return Status::not_alive;
    RingHeader& r = *peer.ring_;
    const std::uint64_t in = peer.in_;
    std::uint64_t out = r.out.load(std::memory_order_acquire);
    if (ipc::Fault f = unread_fault(in, out, size, bid_)) {
        peer.fault_ = f;
        return Status::corrupt;
    }
    if (in - out + need > size) {
        // Full: sleep on the consumer's space word, bounded, re-checking alive.
        const std::int64_t deadline = ipc::now_ns() + std::max<std::int64_t>(timeout_ns, 0);
        for (;;) {
            const std::uint32_t seq = r.space_seq.load(std::memory_order_seq_cst);
            r.producer_waiting.store(1, std::memory_order_seq_cst);
            out = r.out.load(std::memory_order_seq_cst);
            if (ipc::Fault f = unread_fault(in, out, size, bid_)) {
                r.producer_waiting.store(0);
                peer.fault_ = f;
                return Status::corrupt;
            }
            if (in - out + need <= size) break;
            const std::int64_t now = ipc::now_ns();
            if (now >= deadline) {
                r.producer_waiting.store(0);
                return Status::full;
            }
            if (!alive(peer)) {
                r.producer_waiting.store(0);
                return dead(peer);
            }
            ipc::futex_wait(r.space_seq, seq, std::min<std::int64_t>(deadline - now, 10'000'000));
        }
        r.producer_waiting.store(0, std::memory_order_relaxed);
    }
    RecordHeader rec{static_cast<std::uint32_t>(length), 0};
    ring_put(peer.buffer_, size, in, &rec, sizeof rec);
    ring_put(peer.buffer_, size, in + sizeof rec, data, length);
    peer.in_ = in + need;
    r.in.store(in + need, std::memory_order_release);  // the message is visible from here
    signal(h, kMboxSigBuf);
    return Status::ok;
}

Status Mailbox::read(void* buffer, std::size_t capacity, ReadInfo* info) noexcept {
    const std::uint32_t n = geometry_.nrtpu, size = geometry_.bufsize;
    for (std::uint32_t k = 0; k < n; ++k) {
        const std::uint32_t b = (next_ring_ + k) % n;
        RingHeader& r = *own_ring(b);
        const std::uint64_t out = out_[b];
        const std::uint64_t in = r.in.load(std::memory_order_acquire);
        if (in == out) continue;
        std::byte* buf = ring_buffer(&r);
        std::uint32_t length = 0;
        ipc::Fault f = unread_fault(in, out, size, b);
        if (!f) f = record_fault(buf, size, out, in, b, length);
        if (f) {
            // A sender wrote a position or length outside its ring: refuse it,
            // drop what it left there (counted), and let the other rings go on.
            fault_ = f;
            r.discarded.fetch_add(in - out, std::memory_order_relaxed);
            out_[b] = in;
            r.out.store(in, std::memory_order_seq_cst);
            next_ring_ = (b + 1) % n;
            return Status::corrupt;
        }
        if (info) {
            info->from_bid = b;
            info->length = length;
        }
        if (length > capacity) return Status::too_big;
        ring_get(buf, size, out + sizeof(RecordHeader), buffer, length);
        out_[b] = out + sizeof(RecordHeader) + round8(length);
        r.out.store(out_[b], std::memory_order_seq_cst);
        if (r.producer_waiting.load(std::memory_order_seq_cst) != 0) {
            r.space_seq.fetch_add(1, std::memory_order_seq_cst);
            ipc::futex_wake_all(r.space_seq);
        }
        next_ring_ = (b + 1) % n;
        return Status::ok;
    }
    return Status::would_block;
}

std::uint32_t Mailbox::take_interrupts() noexcept {
    return header_->pending.exchange(0, std::memory_order_acq_rel);
}

std::uint32_t Mailbox::wait_interrupts(std::int64_t timeout_ns) noexcept {
    MailboxHeader& h = *header_;
    const std::int64_t deadline = timeout_ns < 0 ? -1 : ipc::now_ns() + timeout_ns;
    for (;;) {
        const std::uint32_t seq = h.trigger.load(std::memory_order_seq_cst);
        h.sleeping.store(1, std::memory_order_seq_cst);
        if (const std::uint32_t p = h.pending.exchange(0, std::memory_order_seq_cst)) {
            h.sleeping.store(0, std::memory_order_relaxed);
            return p;
        }
        if (deadline >= 0 && ipc::now_ns() >= deadline) {
            h.sleeping.store(0, std::memory_order_relaxed);
            return 0;
        }
        if (deadline < 0)
            ipc::futex_wait(h.trigger, seq);
        else
            ipc::futex_wait_until(h.trigger, seq, deadline);
        h.sleeping.store(0, std::memory_order_relaxed);
    }
}

std::uint32_t Mailbox::mbox_value(std::uint32_t mbox) const noexcept {
    if (mbox >= geometry_.nmbox) return 0;
    return at<std::atomic<std::uint32_t>>(header_, geometry_.off_mbox)[mbox].load(std::memory_order_acquire);
}

Status Mailbox::mbox_send(Peer& peer, std::uint32_t mbox, std::uint32_t value) noexcept {
    MailboxHeader& h = *peer.header_;
    if (mbox >= peer.geometry_.nmbox || value == 0) return Status::bad_argument;
    if (!probe(peer)) return dead_locked(peer);
    at<std::atomic<std::uint32_t>>(&h, peer.geometry_.off_mbox)[mbox].store(
        value, std::memory_order_release);  // first write: the value
    signal(h, mbox);                        // second: the trigger
    return Status::ok;
}

// Wakeup word: 0 idle, 1 woken (kept until the task blocks), 2 task asleep.
Status Mailbox::wakeup(Peer& peer, std::uint32_t task) noexcept {
    MailboxHeader& h = *peer.header_;
    if (task >= peer.geometry_.ntasks) return Status::bad_argument;
    if (!probe(peer)) return dead_locked(peer);
    auto& w = at<std::atomic<std::uint32_t>>(&h, peer.geometry_.off_wakeup)[task];
    if (w.exchange(1, std::memory_order_seq_cst) == 2) ipc::futex_wake_all(w);
    h.pending.fetch_or(1u << kMboxSigWkup, std::memory_order_relaxed);  // for observers
    return Status::ok;
}

Status Mailbox::block(std::uint32_t task, std::int64_t timeout_ns) noexcept {
    if (task >= geometry_.ntasks) return Status::bad_argument;
    auto& w = own_wakeup()[task];
    const std::int64_t deadline = timeout_ns < 0 ? -1 : ipc::now_ns() + timeout_ns;
    for (;;) {
        std::uint32_t v = w.load(std::memory_order_acquire);
        if (v == 1) {
            if (w.compare_exchange_strong(v, 0, std::memory_order_acq_rel)) return Status::ok;
            continue;
        }
        if (v == 0 && !w.compare_exchange_strong(v, 2, std::memory_order_acq_rel)) continue;
        if (deadline >= 0 && ipc::now_ns() >= deadline) {
            std::uint32_t two = 2;
            if (w.compare_exchange_strong(two, 0, std::memory_order_acq_rel)) return Status::timed_out;
            continue;  // a wakeup arrived meanwhile: take it
        }
        if (deadline < 0)
            ipc::futex_wait(w, 2);
        else
            ipc::futex_wait_until(w, 2, deadline);
    }
}

std::uint32_t Mailbox::claim_task() {
    std::lock_guard lock(tasks_mutex_);
    for (std::uint32_t t = 0; t < geometry_.ntasks; ++t) {
        if (!(tasks_used_[t / 64] >> (t % 64) & 1)) {
            tasks_used_[t / 64] |= std::uint64_t{1} << (t % 64);
            own_wakeup()[t].store(0);
            return t;
        }
    }
    throw Error("RTPU '" + rtpu_ + "': all " + std::to_string(geometry_.ntasks) +
                " task slots are in use");
}

void Mailbox::release_task(std::uint32_t task) noexcept {
    if (task >= geometry_.ntasks) return;
    std::lock_guard lock(tasks_mutex_);
    tasks_used_[task / 64] &= ~(std::uint64_t{1} << (task % 64));
}

void Mailbox::reset_buffers() noexcept {
    for (std::uint32_t b = 0; b < geometry_.nrtpu; ++b) {
        RingHeader& r = *own_ring(b);
        const std::uint64_t in = r.in.load(std::memory_order_acquire);
        // A position outside the ring is dropped like the rest (counted as one ring's worth).
        r.discarded.fetch_add(std::min<std::uint64_t>(in - out_[b], geometry_.bufsize),
                              std::memory_order_relaxed);
        out_[b] = in;
        r.out.store(in, std::memory_order_seq_cst);
        r.space_seq.fetch_add(1);
        ipc::futex_wake_all(r.space_seq);
    }
    header_->resets.fetch_add(1);
}

}  // namespace chimera::xm
