// Prioritized message queues (thesis §5.4.3, Figure 5.2).
#include "chimera/msg.hpp"

#include <algorithm>
#include <cstring>
#include <utility>
#include <vector>

#include "detail.hpp"

namespace chimera::msg {

using layout::Geometry;
using layout::MsgBHead;
using layout::MsgHead;
using layout::QueueHeader;
using namespace xm::detail;

namespace {

constexpr ipc::SegmentKind kQueueKind{ipc::ObjectType::xmail_msg, layout::kQueueVersion};

constexpr std::uint64_t round8(std::uint64_t n) noexcept { return (n + 7) & ~std::uint64_t{7}; }

constexpr std::uint32_t kMaxBlknum = 1u << 20;
constexpr std::uint32_t kMaxBlksize = 1u << 24;

// The geometry of parameters, or why there is none (a static text).
const char* geometry_of(std::uint64_t blknum, std::uint64_t blksize, std::uint64_t policy,
                        Geometry& g) noexcept {
    if (blknum == 0 || blknum > kMaxBlknum) return "blknum must be 1..1048576";
    if (blksize == 0 || blksize > kMaxBlksize) return "blksize must be 1..16777216";
    if (policy > static_cast<std::uint32_t>(Policy::hpf)) return "policy must be FIFO, LIFO or HPF";
    g.blknum = static_cast<std::uint32_t>(blknum);
    g.blksize = static_cast<std::uint32_t>(round8(blksize));
    g.policy = static_cast<std::uint32_t>(policy);
    g.stride = static_cast<std::uint32_t>(sizeof(MsgBHead)) + g.blksize;
    const std::uint64_t off_heads = sizeof(QueueHeader);
    const std::uint64_t off_blocks = round8(off_heads + std::uint64_t{sizeof(MsgHead)} * blknum);
    g.total = off_blocks + std::uint64_t{g.stride} * blknum;
    if (g.total >= (std::uint64_t{1} << 32)) return "blknum * blksize too large for 32-bit offsets";
    g.off_heads = static_cast<std::uint32_t>(off_heads);
    g.off_blocks = static_cast<std::uint32_t>(off_blocks);
    return nullptr;
}

Geometry geometry(const Params& p) {
    Geometry g;
    if (const char* why = geometry_of(p.blknum, p.blksize, static_cast<std::uint32_t>(p.policy), g)) {
        std::string text = std::string("message queue: ") + why;
        if (p.blknum == 0 || p.blknum > kMaxBlknum) text += ", not " + std::to_string(p.blknum);
        else if (p.blksize == 0 || p.blksize > kMaxBlksize) text += ", not " + std::to_string(p.blksize);
        throw xm::Error(text);
    }
    return g;
}

}  // namespace

// The queue as this handle checked it: the segment, and the geometry kept in
// the handle. Every offset read from the segment goes through head_ok() /
// block_ok() before it is followed; a bad one becomes a Fault.
struct CHIMERA_LOCAL Queue::Ops {
    QueueHeader* q;
    const Geometry& g;

    std::byte* base() const noexcept { return reinterpret_cast<std::byte*>(q); }
    bool head_ok(std::uint32_t off) const noexcept {
        return off >= g.off_heads && off < g.off_heads + std::uint64_t{g.blknum} * sizeof(MsgHead) &&
               (off - g.off_heads) % sizeof(MsgHead) == 0;
    }
    bool block_ok(std::uint32_t off) const noexcept {
        return off >= g.off_blocks && off < g.off_blocks + std::uint64_t{g.blknum} * g.stride &&
               (off - g.off_blocks) % g.stride == 0;
    }
    MsgHead* head(std::uint32_t off) const noexcept { return reinterpret_cast<MsgHead*>(base() + off); }
    MsgBHead* block(std::uint32_t off) const noexcept { return reinterpret_cast<MsgBHead*>(base() + off); }
    std::uint32_t head_off(std::uint32_t i) const noexcept {
        return g.off_heads + i * static_cast<std::uint32_t>(sizeof(MsgHead));
    }
    std::uint32_t head_index(std::uint32_t off) const noexcept {
        return (off - g.off_heads) / static_cast<std::uint32_t>(sizeof(MsgHead));
    }
    std::uint32_t block_off(std::uint32_t i) const noexcept { return g.off_blocks + i * g.stride; }
    static std::byte* data(MsgBHead* b) noexcept { return reinterpret_cast<std::byte*>(b + 1); }

    // A link that must be a header (or nil, when `nil_ok`).
    ipc::Fault head_link(const char* field, std::uint32_t off, bool nil_ok = true,
                         std::int64_t index = -1) const noexcept {
        if ((off == 0 && nil_ok) || head_ok(off)) return {};
        return {field, index, off, g.off_heads + std::uint64_t{g.blknum} * sizeof(MsgHead),
                "a message header offset below"};
    }
    ipc::Fault block_link(const char* field, std::uint32_t off, std::int64_t index = -1) const noexcept {
        if (block_ok(off)) return {};
        return {field, index, off, g.off_blocks + std::uint64_t{g.blknum} * g.stride,
                "a data block offset below"};
    }
    // The message of header `off` occupies nblk valid blocks, chained, and
    // fits them (and `capacity`): checked before anything is copied.
    ipc::Fault chain(std::uint32_t off) const noexcept {
        const MsgHead* h = head(off);
        const auto i = static_cast<std::int64_t>(head_index(off));
        if (h->nblk > g.blknum) return {"message block count", i, h->nblk, g.blknum};
        if (h->size > std::uint64_t{h->nblk} * g.blksize)
            return {"message size", i, h->size, std::uint64_t{h->nblk} * g.blksize};
        std::uint32_t boff = h->blk;
        for (std::uint32_t k = 0; k < h->nblk; ++k) {
            if (ipc::Fault f = block_link("message block link", boff, i)) return f;
            boff = block(boff)->link;
        }
        return {};
    }

    // Policy order: true when a must come before b in headused.
    bool before(const MsgHead* a, const MsgHead* b) const noexcept {
        const auto seq_less = [](std::uint32_t x, std::uint32_t y) {
            return static_cast<std::int32_t>(x - y) < 0;
        };
        switch (static_cast<Policy>(g.policy)) {
            case Policy::fifo: return seq_less(a->seq, b->seq);
            case Policy::lifo: return seq_less(b->seq, a->seq);
            case Policy::hpf:
                return a->priority > b->priority || (a->priority == b->priority && seq_less(a->seq, b->seq));
        }
        return false;
    }

    // Where header `off` goes in headused: after `prev` (0: at the head).
    ipc::Fault place(std::uint32_t off, std::uint32_t& prev) const noexcept {
        return place(head(off)->priority, head(off)->seq, prev);
    }
    // Where a message of this priority and sequence number goes in headused
    // (found before anything is changed). O(1) for FIFO/LIFO, insertion sort
    // for HPF; every link on the way checked.
    ipc::Fault place(std::int32_t priority, std::uint32_t seq, std::uint32_t& prev) const noexcept {
        MsgHead probe{};
        probe.priority = priority;
        probe.seq = seq;
        const MsgHead* h = &probe;
        prev = 0;
        if (q->headused == 0) return {};
        if (ipc::Fault f = head_link("headused", q->headused, false)) return f;
        if (static_cast<Policy>(g.policy) == Policy::fifo) {
            if (ipc::Fault f = head_link("tailused", q->tailused, false)) return f;
            if (!before(h, head(q->tailused))) {
                prev = q->tailused;
                return {};
            }
        }
        if (static_cast<Policy>(g.policy) == Policy::lifo || before(h, head(q->headused))) return {};
        std::uint32_t at = q->headused;
        for (std::uint32_t steps = 0;; ++steps) {
            if (steps > g.blknum) return {"headused length", -1, steps, g.blknum};
            const std::uint32_t next = head(at)->link;
            if (ipc::Fault f = head_link("headused link", next)) return f;
            if (next == 0 || before(h, head(next))) {
                prev = at;
                return {};
            }
            at = next;
        }
    }
    void link_after(std::uint32_t prev, std::uint32_t off) noexcept {
        MsgHead* h = head(off);
        if (prev == 0) {
            h->link = q->headused;
            q->headused = off;
            if (h->link == 0) q->tailused = off;
        } else {
            h->link = head(prev)->link;
            head(prev)->link = off;
            if (h->link == 0) q->tailused = off;
        }
    }
    // Queues header `off` in policy order.
    ipc::Fault enqueue(std::uint32_t off) noexcept {
        std::uint32_t prev = 0;
        if (ipc::Fault f = place(off, prev)) return f;
        head(off)->state = layout::kHeadQueued;
        link_after(prev, off);
        poke(q->nmsgs, q->nmsgs + 1);
        return {};
    }

    // A committed message goes to the highest-priority waiting receiver, or
    // into the queue. Returns the receiver to wake (after unlocking).
    Waiter* hand_or_queue(std::uint32_t off, ipc::Fault& fault) noexcept {
        Waiter* w = waiter_pick(q->recv_waiters, layout::kMaxWaiters);
        if (!w) {
            fault = enqueue(off);
            return nullptr;
        }
        head(off)->state = layout::kHeadHanded;
        w->handed = head_index(off) + 1;
        poke(q->nhanded, q->nhanded + 1);
        waiter_signal(*w);
        return w;
    }

    // Receivers given a message, and senders given the turn, that died
    // before taking it: the message is handed on (or queued), the turn
    // passed to the next sender (lock held). Wakes whom it passes to.
    ipc::Fault reclaim_dead_signalled() noexcept {
        for (Waiter& w : q->recv_waiters) {
            if (w.state != kSignaled || thread_alive(w.pid, w.tid)) continue;
            const std::uint32_t handed = w.handed;
            waiter_free(w);
            ++q->reclaimed_waiters;
            if (handed == 0) continue;
            if (handed > g.blknum) return {"receive waiter's handed message", &w - q->recv_waiters, handed, g.blknum};
            poke(q->nhanded, q->nhanded - 1);
            ipc::Fault fault;
            if (Waiter* next = hand_or_queue(head_off(handed - 1), fault)) waiter_wake(*next);
            if (fault) return fault;
        }
        bool turn_lost = false;
        for (Waiter& w : q->send_waiters) {
            if (w.state != kSignaled || thread_alive(w.pid, w.tid)) continue;
            waiter_free(w);
            ++q->reclaimed_waiters;
            turn_lost = true;
        }
        if (turn_lost)
            if (Waiter* next = waiter_pick(q->send_waiters, layout::kMaxWaiters)) {
                waiter_signal(*next);
                waiter_wake(*next);
            }
        return {};
    }
};

namespace {

void set_me(MsgHead* h) noexcept {
    const std::uint64_t me = ipc::self_owner_id();
    h->pid = ipc::owner_pid(me);
    h->tid = ipc::owner_tid(me);
}

void init_body(QueueHeader* q, const Geometry& g, std::string_view label) noexcept {
    std::memset(reinterpret_cast<std::byte*>(q) + sizeof(ipc::SegmentHeader), 0,
                g.total - sizeof(ipc::SegmentHeader));
    std::memcpy(q->segname, label.data(), std::min(label.size(), sizeof q->segname - 1));
    q->blknum = g.blknum;
    q->blksize = g.blksize;
    q->flags = g.policy;
    q->block_stride = g.stride;
    q->off_heads = g.off_heads;
    q->off_blocks = g.off_blocks;
    Queue::Ops ops{q, g};
    // Everything starts on the free lists, in index order.
    for (std::uint32_t i = 0; i < g.blknum; ++i) {
        ops.head(ops.head_off(i))->link = i + 1 < g.blknum ? ops.head_off(i + 1) : 0;
        ops.block(ops.block_off(i))->link = i + 1 < g.blknum ? ops.block_off(i + 1) : 0;
    }
    q->headfree = ops.head_off(0);
    q->blkfree = ops.block_off(0);
    q->nfree_heads = q->nfree_blks = g.blknum;
}

// The fixed part of an image; on success `g` is its geometry.
ipc::Fault geometry_fault(const void* image, std::size_t size, Geometry& g) noexcept {
    if (ipc::Fault f = ipc::header_fault(image, size, kQueueKind)) return f;
    if (size < sizeof(QueueHeader)) return {"size", -1, size, sizeof(QueueHeader), "at least"};
    const auto* q = static_cast<const QueueHeader*>(image);
    if (geometry_of(q->blknum, q->blksize, q->flags, g) != nullptr) {
        if (q->blknum == 0 || q->blknum > kMaxBlknum) return {"blknum", -1, q->blknum, kMaxBlknum, "1 to"};
        if (q->blksize == 0 || q->blksize > kMaxBlksize) return {"blksize", -1, q->blksize, kMaxBlksize, "1 to"};
        if (q->flags > 2) return {"policy", -1, q->flags, 2};
        return {"blknum * blksize", -1, std::uint64_t{q->blknum} * q->blksize, std::uint64_t{1} << 32, "below"};
    }
    using ipc::fault_if;
    if (ipc::Fault f = fault_if(q->blksize != g.blksize, "blksize (a multiple of 8)", q->blksize, g.blksize, "equal to")) return f;
    if (ipc::Fault f = fault_if(q->block_stride != g.stride, "block stride", q->block_stride, g.stride, "equal to")) return f;
    if (ipc::Fault f = fault_if(q->off_heads != g.off_heads, "header offset", q->off_heads, g.off_heads, "equal to")) return f;
    if (ipc::Fault f = fault_if(q->off_blocks != g.off_blocks, "block offset", q->off_blocks, g.off_blocks, "equal to")) return f;
    return fault_if(g.total > size, "queue size", g.total, size);
}

std::string label_of(const QueueHeader* q) { return std::string(q->segname, strnlen(q->segname, sizeof q->segname)); }

}  // namespace

ipc::Fault validate_geometry(const void* image, std::size_t size) noexcept {
    Geometry g;
    return geometry_fault(image, size, g);
}

ipc::Fault validate(const void* image, std::size_t size) noexcept {
    Geometry g;
    if (ipc::Fault f = geometry_fault(image, size, g)) return f;
    // The walks below only read; a const_cast gives them the Ops helpers.
    Queue::Ops ops{static_cast<QueueHeader*>(const_cast<void*>(image)), g};
    const QueueHeader* q = ops.q;
    const std::uint32_t n = g.blknum;
    std::uint32_t count = 0;
    for (std::uint32_t off = q->headfree; off != 0; off = ops.head(off)->link) {
        if (ipc::Fault f = ops.head_link("headfree link", off)) return f;
        if (++count > n) return {"headfree length", -1, count, n};
    }
    if (count != q->nfree_heads) return {"nfree_heads", -1, q->nfree_heads, count, "equal to"};
    count = 0;
    std::uint32_t last = 0;
    for (std::uint32_t off = q->headused; off != 0; off = ops.head(off)->link) {
        if (ipc::Fault f = ops.head_link("headused link", off)) return f;
        if (++count > n) return {"headused length", -1, count, n};
        if (ipc::Fault f = ops.chain(off)) return f;
        last = off;
    }
    if (count != q->nmsgs) return {"nmsgs", -1, q->nmsgs, count, "equal to"};
    if (q->tailused != last) return {"tailused", -1, q->tailused, last, "equal to"};
    count = 0;
    for (std::uint32_t off = q->blkfree; off != 0; off = ops.block(off)->link) {
        if (ipc::Fault f = ops.block_link("blkfree link", off)) return f;
        if (++count > n) return {"blkfree length", -1, count, n};
    }
    if (count != q->nfree_blks) return {"nfree_blks", -1, q->nfree_blks, count, "equal to"};
    for (std::uint32_t k = 0; k < layout::kMaxWaiters; ++k) {
        const std::uint32_t handed = q->recv_waiters[k].handed;
        if (handed > n) return {"receive waiter's handed message", k, handed, n};
        if (handed != 0)
            if (ipc::Fault f = ops.chain(ops.head_off(handed - 1))) return f;
    }
    return {};
}

// ---------------------------------------------------------------- set-up

std::size_t Queue::memory_size(const Params& params) { return geometry(params).total; }

Queue::Queue(Queue&& o) noexcept { *this = std::move(o); }

Queue& Queue::operator=(Queue&& o) noexcept {
    if (this != &o) {
        detach();
        q_ = std::exchange(o.q_, nullptr);
        g_ = o.g_;
        segment_ = std::move(o.segment_);
        name_ = std::move(o.name_);
        where_ = std::move(o.where_);
        fault_ = o.fault_;
        hint_head_ = std::exchange(o.hint_head_, 0);
        hint_block_ = std::exchange(o.hint_block_, 0);
    }
    return *this;
}

Queue::~Queue() { detach(); }

// A handle on a queue whose geometry was checked: keeps it.
Queue Queue::bound(QueueHeader* q, std::size_t size, std::string where) {
    Queue out;
    try {
        ipc::validate_header(where, q->segment, kQueueKind, std::min<std::size_t>(size, q->segment.total_size));
    } catch (const ipc::SegmentError& e) {
        throw xm::Error(std::string("message queue: ") + e.what());
    }
    if (const ipc::Fault f = geometry_fault(q, size, out.g_))
        throw xm::Error("message queue: " + ipc::describe(where, f));
    out.q_ = q;
    out.where_ = std::move(where);
    return out;
}

Queue Queue::over(void* memory, std::size_t size, const Params& params, std::string_view label) {
    const Geometry g = geometry(params);
    if (size < g.total)
        throw xm::Error("message queue '" + std::string(label) + "': needs " +
                        std::to_string(g.total) + " bytes, given " + std::to_string(size));
    auto* q = static_cast<QueueHeader*>(memory);
    ipc::init_header(q->segment, kQueueKind, g.total);
    init_body(q, g, label);
    q->segment.state.store(static_cast<std::uint32_t>(ipc::SegmentState::ready),
                           std::memory_order_release);
    Queue out = bound(q, g.total, std::string(label));
    out.name_ = std::string(label);
    return out;
}

Queue Queue::bind(void* memory, std::size_t size) {
    auto* q = static_cast<QueueHeader*>(memory);
    if (size < sizeof(ipc::SegmentHeader)) throw xm::Error("message queue: memory smaller than a queue");
    // The queue may be smaller than the block it was laid over.
    const std::size_t used = std::min<std::size_t>(size, q->segment.total_size);
    Queue out = bound(q, used, "message queue '" + label_of(q) + "'");
    out.name_ = label_of(q);
    return out;
}

ipc::Segment create_segment_body(const std::string& segment, const std::string& full_name,
                                 const xm::ObjectParams& params) {
    Params p;
    p.blknum = static_cast<std::uint32_t>(params.a);
    p.blksize = static_cast<std::uint32_t>(params.b);
    p.policy = static_cast<Policy>(params.c);
    if (params.a > 0xffffffffu || params.b > 0xffffffffu) p.blknum = 0;  // refused by geometry()
    Geometry g{};
    try {
        g = geometry(p);
    } catch (const xm::Error& e) {
        throw xm::Error("'" + full_name + "': " + e.what());
    }
    ipc::Segment seg = ipc::Segment::create(segment, g.total, kQueueKind);
    init_body(static_cast<QueueHeader*>(seg.base()), g, full_name);
    seg.publish();
    return seg;
}

Queue Queue::create(xm::Rtpu& self, std::string_view full_name, const Params& params) {
    geometry(params);  // refuse bad parameters before asking the owner
    xm::ObjectParams op;
    op.a = params.blknum;
    op.b = params.blksize;
    op.c = static_cast<std::uint32_t>(params.policy);
    const xm::ObjectRef ref = self.create_object(full_name, ipc::ObjectType::xmail_msg, op);
    return attach_ref(ref, full_name);
}

Queue Queue::attach(xm::Rtpu& self, std::string_view full_name) {
    return attach_ref(self.attach_object(full_name, ipc::ObjectType::xmail_msg), full_name);
}

Queue Queue::attach_ref(const xm::ObjectRef& ref, std::string_view full_name) {
    ipc::Segment seg;
    try {
        seg = ipc::Segment::attach(ref.segment, kQueueKind);
    } catch (const ipc::SegmentError& e) {
        throw xm::Error("message queue '" + std::string(full_name) + "': " + e.what());
    }
    Queue q = bound(static_cast<QueueHeader*>(seg.base()), seg.size(), ref.segment);
    q.segment_ = std::move(seg);
    q.name_ = std::string(full_name);
    return q;
}

void Queue::detach() noexcept {
    if (segment_.valid()) segment_.detach_destroy_if_last();
    q_ = nullptr;
}

void Queue::destroy(xm::Rtpu& self) {
    // Name first: detaching first could free the object as its last user.
    self.destroy_object(name_);
    q_ = nullptr;
    segment_.detach();
}

std::string Queue::fault_message() const { return ipc::describe(where_, fault_); }

// ---------------------------------------------------------------- hot paths

// Across CPUs every line a send or receive writes was last written by the
// other side, and taken one after another — the lock, the counters, the
// header, its block: each address known only from the line before — they
// cost a cache miss each, in series (a hand-off cost about 285 ns more than
// a bare futex ping-pong's). Asked for all at once before the lock, they
// come in parallel (bench/results/xmail.md). The header and block are a guess: the ones this handle used
// last, which a ping-pong uses again (LIFO free lists). A wrong guess costs
// two useless prefetches.
void Queue::prefetch_hot_lines() const noexcept {
    prefetch_for_write(&q_->mutex);
    prefetch_for_write(&q_->headfree);     // the lists and counts
    prefetch_for_write(&q_->sends);        // the operation counters, the next line
    prefetch_for_write(&q_->recv_waiters[0]);
    // peek/poke: threads sharing a handle may send and receive at once (a
    // stale guess is harmless; a torn read is not allowed).
    if (const std::uint32_t head = peek(hint_head_); head != 0) {
        const auto* h = reinterpret_cast<const std::byte*>(q_) + head;
        prefetch_for_write(h);
        prefetch_for_write(h + sizeof(MsgHead) - 1);  // a header may straddle two lines
        prefetch_for_write(reinterpret_cast<const std::byte*>(q_) + peek(hint_block_));
    }
}

Status Queue::lock() noexcept {
    return lock_object(q_->mutex, q_->recoveries, [this] { repair(); });
}

// A refusal: the fault kept for fault_message(), the lock let go, nothing changed.
Status Queue::refuse(const ipc::Fault& f) noexcept {
    fault_ = f;
    unlock_object(q_->mutex);
    return Status::corrupt;
}

Status Queue::send(const void* data, std::size_t size, std::uint32_t type, std::int32_t priority,
                   std::int64_t timeout_ns) noexcept {
    if (!q_) return Status::bad_argument;
    QueueHeader* q = q_;
    Ops ops{q, g_};
    const std::uint64_t need64 = (size + g_.blksize - 1) / g_.blksize;
    if (need64 > g_.blknum) return Status::too_big;
    const auto need = static_cast<std::uint32_t>(need64);
    WaitDeadline deadline(timeout_ns);
    Waiter* me = nullptr;
    for (;;) {
        if (!me) prefetch_hot_lines();  // after a sleep: done as it ended
        if (const Status s = lock(); s != Status::ok) return s;
        if (me) {
            waiter_free(*me);
            me = nullptr;
        }
        if (q->headfree != 0 && q->nfree_blks >= need) break;
        Status fail = Status::ok;
        if (timeout_ns == 0)
            fail = Status::would_block;
        else if (deadline.passed())
            fail = Status::timed_out;
        else if (!(me = waiter_add(q->send_waiters, layout::kMaxWaiters, q->next_ticket, priority)))
            fail = Status::too_many_waiters;
        unlock_object(q->mutex);
        if (fail != Status::ok) return fail;
        waiter_sleep(*me, q->send_waiters, layout::kMaxWaiters, deadline, [&] { pass_on_dead(me); },
                     [this] { prefetch_hot_lines(); });
    }

    // Check the header and the blocks it will take, and where it will go if
    // nobody waits for it, before changing anything.
    const std::uint32_t off = q->headfree;
    if (ipc::Fault f = ops.head_link("headfree", off, false)) return refuse(f);
    if (ipc::Fault f = ops.head_link("headfree link", ops.head(off)->link)) return refuse(f);
    for (std::uint32_t i = 0, boff = q->blkfree; i < need; ++i, boff = ops.block(boff)->link)
        if (ipc::Fault f = ops.block_link(i == 0 ? "blkfree" : "blkfree link", boff)) return refuse(f);
    std::uint32_t prev = 0;
    Waiter* wake = waiter_pick(q->recv_waiters, layout::kMaxWaiters);
    if (!wake)
        if (ipc::Fault f = ops.place(priority, q->next_seq, prev)) return refuse(f);

    // Take the header off headfree and the blocks off blkfree, copying as we go.
    MsgHead* h = ops.head(off);
    q->headfree = h->link;
    --q->nfree_heads;
    h->state = layout::kHeadWriting;
    set_me(h);
    h->link = 0;
    h->type = type;
    h->priority = priority;
    h->size = static_cast<std::uint32_t>(size);
    h->nblk = need;
    h->blk = 0;
    const std::uint32_t owner = ops.head_index(off) + 1;
    std::uint32_t* prev_link = &h->blk;
    const auto* src = static_cast<const std::byte*>(data);
    std::size_t done = 0;
    for (std::uint32_t i = 0; i < need; ++i) {
        const std::uint32_t boff = q->blkfree;
        MsgBHead* b = ops.block(boff);
        q->blkfree = b->link;
        --q->nfree_blks;
        b->owner = owner;
        b->link = 0;
        *prev_link = boff;
        prev_link = &b->link;
        const std::size_t chunk = std::min<std::size_t>(g_.blksize, size - done);
        std::memcpy(Ops::data(b), src + done, chunk);
        done += chunk;
    }
    poke(hint_head_, off);
    poke(hint_block_, h->blk);
    h->seq = q->next_seq++;
    // Armed before the commit: killed from here to the wake-up, this sender
    // has the kernel wake the receiver, which finds the message under the
    // lock (the repair queues it) instead of sleeping on without a timer.
    if (wake) waiter_arm(*wake);
    std::atomic_thread_fence(std::memory_order_release);
    h->state = layout::kHeadQueued;  // commit point: from here the message exists
    ++q->sends;
    if (wake) {
        // Hand the message straight to the highest-priority waiting receiver.
        h->state = layout::kHeadHanded;
        wake->handed = owner;
        poke(q->nhanded, q->nhanded + 1);
        waiter_signal_armed(*wake);
    } else {
        ops.link_after(prev, off);
        poke(q->nmsgs, q->nmsgs + 1);
    }
    return unlock_and_wake(wake);
}

// Lets the lock go and wakes `w`; when the wake-up reaches nobody and its
// thread is gone, takes back what it was given and passes it on (the next
// receiver or the queue; the next sender), so nothing stays with the dead.
Status Queue::unlock_and_wake(Waiter* w) noexcept {
    WaiterId id = w ? id_of(*w) : WaiterId{};
    unlock_object(q_->mutex);
    while (w && !waiter_wake_checked(*w, id)) {
        if (lock() != Status::ok) break;  // the sleepers' slices pass it on
        Ops ops{q_, g_};
        Waiter* dead = w;
        w = nullptr;
        if (still_signalled(*dead, id)) {
            const bool receiver = dead >= q_->recv_waiters && dead < q_->recv_waiters + layout::kMaxWaiters;
            const std::uint32_t handed = dead->handed;
            waiter_free(*dead);
            ++q_->reclaimed_waiters;
            ipc::Fault f;
            if (!receiver) {
                if ((w = waiter_pick(q_->send_waiters, layout::kMaxWaiters))) waiter_signal(*w);
            } else if (handed > g_.blknum) {
                f = {"receive waiter's handed message", dead - q_->recv_waiters, handed, g_.blknum};
            } else if (handed != 0) {
                poke(q_->nhanded, q_->nhanded - 1);
                w = ops.hand_or_queue(ops.head_off(handed - 1), f);
            }
            if (f) return refuse(f);
            if (w) id = id_of(*w);
        }
        unlock_object(q_->mutex);
    }
    return Status::ok;
}

// A sleeper's look at every slice: a message handed to (or a turn given to)
// a waiter that died since would otherwise strand those still blocked.
void Queue::pass_on_dead(const Waiter* self) noexcept {
    if (!signalled_dead(q_->recv_waiters, layout::kMaxWaiters, self) &&
        !signalled_dead(q_->send_waiters, layout::kMaxWaiters, self))
        return;
    if (lock() != Status::ok) return;
    if (ipc::Fault f = Ops{q_, g_}.reclaim_dead_signalled()) {
        // A waiter's look has nobody to tell: the fault is kept for
        // fault_message(), and the next send/receive meets it and refuses.
        (void)refuse(f);
        return;
    }
    unlock_object(q_->mutex);
}

Status Queue::receive(void* buffer, std::size_t capacity, Info* info, std::int64_t timeout_ns,
                      std::int32_t task_priority) noexcept {
    if (!q_) return Status::bad_argument;
    QueueHeader* q = q_;
    Ops ops{q, g_};
    // Polling an empty queue takes no lock (a hint: re-checked under the lock).
    if (timeout_ns == 0 && peek(q->nmsgs) == 0 && peek(q->nhanded) == 0) return Status::would_block;
    WaitDeadline deadline(timeout_ns);
    Waiter* me = nullptr;
    std::uint32_t off = 0;
    for (;;) {
        if (!me) prefetch_hot_lines();  // after a sleep: done as it ended
        if (const Status s = lock(); s != Status::ok) return s;
        if (me) {
            const std::uint32_t handed = me->state == kSignaled ? me->handed : 0;
            // A handed message is checked before anything changes.
            if (handed > g_.blknum) return refuse({"receive waiter's handed message", -1, handed, g_.blknum});
            if (handed != 0)
                if (ipc::Fault f = ops.chain(ops.head_off(handed - 1))) return refuse(f);
            waiter_free(*me);
            me = nullptr;
            if (handed != 0) {
                off = ops.head_off(handed - 1);
                poke(q->nhanded, q->nhanded - 1);
                if (ops.head(off)->size > capacity) {
                    // Does not fit: back into the queue for someone who can take it.
                    const MsgHead* h = ops.head(off);
                    if (info) *info = Info{h->type, h->priority, h->size};
                    ipc::Fault f;
                    Waiter* next = ops.hand_or_queue(off, f);
                    if (f) return refuse(f);
                    if (const Status s = unlock_and_wake(next); s != Status::ok) return s;
                    return Status::too_big;
                }
                break;
            }
        }
        if (q->nmsgs == 0 && q->nhanded > 0)
            if (ipc::Fault f = ops.reclaim_dead_signalled()) return refuse(f);
        if (q->nmsgs > 0) {
            off = q->headused;
            if (ipc::Fault f = ops.head_link("headused", off, false)) return refuse(f);
            MsgHead* h = ops.head(off);
            if (ipc::Fault f = ops.head_link("headused link", h->link)) return refuse(f);
            if (h->size > capacity) {
                if (info) *info = Info{h->type, h->priority, h->size};
                unlock_object(q->mutex);
                return Status::too_big;
            }
            if (ipc::Fault f = ops.chain(off)) return refuse(f);
            q->headused = h->link;
            if (q->headused == 0) q->tailused = 0;
            poke(q->nmsgs, q->nmsgs - 1);
            break;
        }
        Status fail = Status::ok;
        if (timeout_ns == 0)
            fail = Status::would_block;
        else if (deadline.passed())
            fail = Status::timed_out;
        else if (!(me = waiter_add(q->recv_waiters, layout::kMaxWaiters, q->next_ticket,
                                   task_priority)))
            fail = Status::too_many_waiters;
        unlock_object(q->mutex);
        if (fail != Status::ok) return fail;
        waiter_sleep(*me, q->recv_waiters, layout::kMaxWaiters, deadline, [&] { pass_on_dead(me); },
                     [this] { prefetch_hot_lines(); });
    }

    // Copy the message out of its blocks (checked above), then free header and blocks.
    MsgHead* h = ops.head(off);
    h->state = layout::kHeadReading;
    set_me(h);
    auto* dst = static_cast<std::byte*>(buffer);
    std::size_t done = 0;
    std::uint32_t boff = h->blk;
    for (std::uint32_t k = 0; k < h->nblk; ++k) {
        MsgBHead* b = ops.block(boff);
        const std::size_t chunk = std::min<std::size_t>(g_.blksize, h->size - done);
        std::memcpy(dst + done, Ops::data(b), chunk);
        done += chunk;
        boff = b->link;
    }
    if (info) *info = Info{h->type, h->priority, h->size};
    std::atomic_thread_fence(std::memory_order_release);
    h->state = layout::kHeadFree;  // commit point: the message is consumed
    boff = h->blk;
    poke(hint_head_, off);
    poke(hint_block_, boff);
    for (std::uint32_t k = 0; k < h->nblk; ++k) {
        MsgBHead* b = ops.block(boff);
        const std::uint32_t next = b->link;
        b->owner = 0;
        b->link = q->blkfree;
        q->blkfree = boff;
        ++q->nfree_blks;
        boff = next;
    }
    h->blk = 0;
    h->link = q->headfree;
    q->headfree = off;
    ++q->nfree_heads;
    ++q->receives;
    Waiter* wake = waiter_pick(q->send_waiters, layout::kMaxWaiters);
    if (wake) waiter_signal(*wake);
    return unlock_and_wake(wake);
}

// ---------------------------------------------------------------- recovery

// Runs with the lock held, after its previous holder died: replay the
// per-header journal and rebuild every list from it. Touches only headers
// and blocks by index (never follows a list), so a damaged link cannot lead
// it outside the queue.
void Queue::repair() noexcept {
    QueueHeader* q = q_;
    Ops ops{q, g_};
    const std::uint32_t n = g_.blknum;
    // Waiters: drop the dead; re-arm and wake the signalled ones (their
    // signaller may have died before its wake-up).
    for (Waiter* list : {q->recv_waiters, q->send_waiters}) {
        for (std::uint32_t i = 0; i < layout::kMaxWaiters; ++i) {
            Waiter& w = list[i];
            if (w.state == kFree) continue;
            if (!thread_alive(w.pid, w.tid)) {
                waiter_free(w);
                ++q->reclaimed_waiters;
            } else if (w.state == kSignaled) {
                waiter_rearm(w);
            }
        }
    }
    // A waiting (not yet signalled) slot holds no message: a sender that died
    // halfway through a hand-off may have named its header in the slot before
    // signalling it. The header then goes back into the queue below.
    for (Waiter& w : q->recv_waiters)
        if (w.state != kSignaled || w.handed > n) w.handed = 0;
    // Header states: roll interrupted operations back.
    for (std::uint32_t i = 0; i < n; ++i) {
        MsgHead* h = ops.head(ops.head_off(i));
        switch (h->state) {
            case layout::kHeadWriting: h->state = layout::kHeadFree; break;
            case layout::kHeadReading: h->state = layout::kHeadQueued; break;
            case layout::kHeadHanded: {
                bool held = false;
                for (const Waiter& w : q->recv_waiters)
                    held = held || (w.state == kSignaled && w.handed == i + 1);
                if (!held) h->state = layout::kHeadQueued;
                break;
            }
            case layout::kHeadQueued:
            case layout::kHeadFree: break;
            default: h->state = layout::kHeadFree; break;
        }
    }
    // And a signalled slot holds only a header that is HANDED (the sender's
    // stores need not have reached memory in program order before it died).
    for (Waiter& w : q->recv_waiters)
        if (w.handed != 0 && ops.head(ops.head_off(w.handed - 1))->state != layout::kHeadHanded)
            w.handed = 0;
    // Blocks: owned exactly by the chains of live messages.
    for (std::uint32_t j = 0; j < n; ++j) ops.block(ops.block_off(j))->owner = 0;
    for (std::uint32_t i = 0; i < n; ++i) {
        MsgHead* h = ops.head(ops.head_off(i));
        if (h->state != layout::kHeadQueued && h->state != layout::kHeadHanded) continue;
        bool sound = h->nblk <= n && h->size <= std::uint64_t{h->nblk} * g_.blksize;
        std::uint32_t boff = h->blk;
        for (std::uint32_t k = 0; sound && k < h->nblk; ++k) {
            if (!ops.block_ok(boff) || ops.block(boff)->owner != 0) {
                sound = false;
                break;
            }
            ops.block(boff)->owner = i + 1;
            boff = ops.block(boff)->link;
        }
        if (!sound || boff != 0) {
            // Cannot happen with the commit order above; never keep a broken chain.
            for (std::uint32_t j = 0; j < n; ++j)
                if (ops.block(ops.block_off(j))->owner == i + 1) ops.block(ops.block_off(j))->owner = 0;
            h->state = layout::kHeadFree;
            for (Waiter& w : q->recv_waiters)
                if (w.handed == i + 1) w.handed = 0;
        }
    }
    q->blkfree = 0;
    q->nfree_blks = 0;
    for (std::uint32_t j = n; j-- > 0;) {
        MsgBHead* b = ops.block(ops.block_off(j));
        if (b->owner != 0) continue;
        b->link = q->blkfree;
        q->blkfree = ops.block_off(j);
        ++q->nfree_blks;
    }
    // Header lists, headused in policy order (every link just written here).
    q->headfree = q->headused = q->tailused = 0;
    q->nfree_heads = 0;
    poke(q->nmsgs, 0);
    poke(q->nhanded, 0);
    for (std::uint32_t i = n; i-- > 0;) {
        const std::uint32_t off = ops.head_off(i);
        MsgHead* h = ops.head(off);
        if (h->state == layout::kHeadFree) {
            h->blk = 0;
            h->link = q->headfree;
            q->headfree = off;
            ++q->nfree_heads;
        } else if (h->state == layout::kHeadQueued) {
            // A link repair cannot follow is kept for fault_message(); the
            // next send/receive checks the chain and refuses.
            if (ipc::Fault f = ops.enqueue(off)) fault_ = f;
        } else {
            poke(q->nhanded, q->nhanded + 1);
        }
    }
    // Space or messages may have appeared for sleepers: let them re-check.
    for (Waiter* list : {q->recv_waiters, q->send_waiters})
        for (std::uint32_t i = 0; i < layout::kMaxWaiters; ++i)
            if (list[i].state == kWaiting) {
                waiter_signal(list[i]);
                waiter_wake(list[i]);
            }
}

Stats Queue::stats() noexcept {
    Stats s;
    if (!q_ || lock() != Status::ok) return s;
    s.messages = q_->nmsgs;
    s.handed = q_->nhanded;
    s.free_headers = q_->nfree_heads;
    s.free_blocks = q_->nfree_blks;
    s.receive_waiters = waiter_count(q_->recv_waiters, layout::kMaxWaiters);
    s.send_waiters = waiter_count(q_->send_waiters, layout::kMaxWaiters);
    s.recoveries = q_->recoveries;
    s.reclaimed_waiters = q_->reclaimed_waiters;
    s.lock_recoveries = q_->mutex.recoveries.load();
    unlock_object(q_->mutex);
    return s;
}

std::string Queue::check() {
    if (!q_) return "not attached";
    if (lock() != Status::ok) return "lock timed out";
    QueueHeader* q = q_;
    Ops ops{q, g_};
    std::string err;
    auto fail = [&](const std::string& m) {
        if (err.empty()) err = m;
    };
    if (q->nhanded > 0)
        if (ipc::Fault f = ops.reclaim_dead_signalled()) fail(ipc::describe(where_, f));
    // Bounds first (every link and chain inside the queue), then the invariants.
    if (err.empty())
        if (ipc::Fault f = validate(q, g_.total)) fail(ipc::describe(where_, f));
    if (!err.empty()) {
        unlock_object(q->mutex);
        return err;
    }
    const std::uint32_t n = g_.blknum;
    std::vector<int> seen(n, 0);
    for (std::uint32_t off = q->headfree; off != 0; off = ops.head(off)->link) {
        const std::uint32_t i = ops.head_index(off);
        if (seen[i]++) fail("header " + std::to_string(i) + " on two lists");
        if (ops.head(off)->state != layout::kHeadFree) fail("headfree: header not FREE");
    }
    std::uint32_t last = 0;
    for (std::uint32_t off = q->headused; off != 0; off = ops.head(off)->link) {
        const std::uint32_t i = ops.head_index(off);
        if (seen[i]++) fail("header " + std::to_string(i) + " on two lists");
        if (ops.head(off)->state != layout::kHeadQueued) fail("headused: header not QUEUED");
        if (last != 0 && ops.before(ops.head(off), ops.head(last))) fail("headused out of policy order");
        last = off;
    }
    std::uint32_t handed = 0, live_blocks = 0;
    for (std::uint32_t i = 0; i < n; ++i) {
        MsgHead* h = ops.head(ops.head_off(i));
        if (h->state == layout::kHeadHanded) {
            ++handed;
            bool held = false;
            for (const Waiter& w : q->recv_waiters) held = held || (w.state == kSignaled && w.handed == i + 1);
            if (!held) fail("header " + std::to_string(i) + " handed to no waiter");
        } else if (!seen[i]) {
            fail("header " + std::to_string(i) + " on no list (state " + std::to_string(h->state) + ")");
        }
        if (h->state == layout::kHeadQueued || h->state == layout::kHeadHanded) {
            if (ops.chain(ops.head_off(i)) ||
                (h->nblk > 0 && h->size <= std::uint64_t{h->nblk - 1} * g_.blksize))
                fail("header " + std::to_string(i) + ": size does not match its block count");
            std::uint32_t boff = h->blk;
            for (std::uint32_t k = 0; k < h->nblk && ops.block_ok(boff); ++k) {
                if (ops.block(boff)->owner != i + 1) {
                    fail("header " + std::to_string(i) + ": broken block chain");
                    break;
                }
                boff = ops.block(boff)->link;
            }
            live_blocks += h->nblk;
        }
    }
    if (handed != q->nhanded) fail("nhanded mismatch");
    // The other direction: a slot names only a HANDED header, and only once signalled.
    for (std::uint32_t k = 0; k < layout::kMaxWaiters; ++k) {
        const Waiter& w = q->recv_waiters[k];
        if (w.handed == 0) continue;
        if (w.state != kSignaled) fail("receive waiter " + std::to_string(k) + " holds a message unsignalled");
        if (ops.head(ops.head_off(w.handed - 1))->state != layout::kHeadHanded)
            fail("receive waiter " + std::to_string(k) + " holds a header that is not HANDED");
    }
    for (std::uint32_t off = q->blkfree; off != 0; off = ops.block(off)->link)
        if (ops.block(off)->owner != 0) fail("blkfree: block owned by a message");
    if (q->nfree_blks + live_blocks != n)
        fail("blocks lost: " + std::to_string(q->nfree_blks) + " free + " + std::to_string(live_blocks) +
             " used != " + std::to_string(n));
    unlock_object(q->mutex);
    return err;
}

std::string Queue::dump() {
    std::string out;
    if (!q_ || lock() != Status::ok) return out;
    Ops ops{q_, g_};
    std::uint32_t steps = 0;
    for (std::uint32_t off = q_->headused; off != 0 && ops.head_ok(off) && steps++ <= g_.blknum;
         off = ops.head(off)->link) {
        const MsgHead* h = ops.head(off);
        if (!out.empty()) out += ' ';
        out += std::to_string(h->priority) + ':' + std::to_string(h->type) + ':' + std::to_string(h->size);
    }
    unlock_object(q_->mutex);
    return out;
}

}  // namespace chimera::msg

namespace chimera::xm::detail {
ipc::Segment create_msg_segment(const std::string& segment, const std::string& full_name,
                                const ObjectParams& params) {
    return msg::create_segment_body(segment, full_name, params);
}
}  // namespace chimera::xm::detail
