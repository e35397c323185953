// Prioritized message queues (thesis §5.4.3, Figure 5.2).
#include "chimera/msg.hpp"

#include <algorithm>
#include <cstring>
#include <utility>
#include <vector>

#include "detail.hpp"

namespace chimera::msg {

using layout::MsgBHead;
using layout::MsgHead;
using layout::QueueHeader;
using namespace xm::detail;

namespace {

constexpr ipc::SegmentKind kQueueKind{ipc::ObjectType::xmail_msg, layout::kQueueVersion};

constexpr std::uint64_t round8(std::uint64_t n) noexcept { return (n + 7) & ~std::uint64_t{7}; }

struct Geometry {
    std::uint32_t blksize, stride, off_heads, off_blocks;
    std::uint64_t total;
};

Geometry geometry(const Params& p) {
    if (p.blknum == 0 || p.blknum > (1u << 20))
        throw xm::Error("message queue: blknum must be 1..1048576, not " + std::to_string(p.blknum));
    if (p.blksize == 0 || p.blksize > (1u << 24))
        throw xm::Error("message queue: blksize must be 1..16777216, not " +
                        std::to_string(p.blksize));
    if (p.policy != Policy::fifo && p.policy != Policy::lifo && p.policy != Policy::hpf)
        throw xm::Error("message queue: policy must be FIFO, LIFO or HPF");
    Geometry g{};
    g.blksize = static_cast<std::uint32_t>(round8(p.blksize));
    g.stride = sizeof(MsgBHead) + g.blksize;
    g.off_heads = sizeof(QueueHeader);
    g.off_blocks = static_cast<std::uint32_t>(round8(g.off_heads + std::uint64_t{sizeof(MsgHead)} * p.blknum));
    g.total = g.off_blocks + std::uint64_t{g.stride} * p.blknum;
    if (g.total >= (std::uint64_t{1} << 32))
        throw xm::Error("message queue: blknum * blksize too large for 32-bit offsets");
    return g;
}

// --- offset arithmetic: every link is an offset from the queue's base.
std::byte* base(QueueHeader* q) noexcept { return reinterpret_cast<std::byte*>(q); }
MsgHead* head_at(QueueHeader* q, std::uint32_t off) noexcept {
    return reinterpret_cast<MsgHead*>(base(q) + off);
}
std::uint32_t head_off(const QueueHeader* q, std::uint32_t index) noexcept {
    return q->off_heads + index * static_cast<std::uint32_t>(sizeof(MsgHead));
}
std::uint32_t head_index(const QueueHeader* q, std::uint32_t off) noexcept {
    return (off - q->off_heads) / static_cast<std::uint32_t>(sizeof(MsgHead));
}
bool head_valid(const QueueHeader* q, std::uint32_t off) noexcept {
    return off >= q->off_heads && off < q->off_heads + q->blknum * sizeof(MsgHead) &&
           (off - q->off_heads) % sizeof(MsgHead) == 0;
}
MsgBHead* block_at(QueueHeader* q, std::uint32_t off) noexcept {
    return reinterpret_cast<MsgBHead*>(base(q) + off);
}
std::uint32_t block_off(const QueueHeader* q, std::uint32_t index) noexcept {
    return q->off_blocks + index * q->block_stride;
}
bool block_valid(const QueueHeader* q, std::uint32_t off) noexcept {
    return off >= q->off_blocks && off < q->off_blocks + std::uint64_t{q->blknum} * q->block_stride &&
           (off - q->off_blocks) % q->block_stride == 0;
}
std::byte* block_data(MsgBHead* b) noexcept { return reinterpret_cast<std::byte*>(b + 1); }

// Policy order: true when a must come before b in headused.
bool before(const QueueHeader* q, const MsgHead* a, const MsgHead* b) noexcept {
    const auto seq_less = [](std::uint32_t x, std::uint32_t y) {
        return static_cast<std::int32_t>(x - y) < 0;
    };
    switch (static_cast<Policy>(q->flags)) {
        case Policy::fifo: return seq_less(a->seq, b->seq);
        case Policy::lifo: return seq_less(b->seq, a->seq);
        case Policy::hpf:
            return a->priority > b->priority ||
                   (a->priority == b->priority && seq_less(a->seq, b->seq));
    }
    return false;
}

// Inserts header `off` into headused: O(1) for FIFO/LIFO, insertion sort for HPF.
void insert_used(QueueHeader* q, std::uint32_t off) noexcept {
    MsgHead* h = head_at(q, off);
    const auto policy = static_cast<Policy>(q->flags);
    if (q->headused == 0) {
        h->link = 0;
        q->headused = q->tailused = off;
        return;
    }
    if (policy == Policy::fifo && !before(q, h, head_at(q, q->tailused))) {
        h->link = 0;
        head_at(q, q->tailused)->link = off;
        q->tailused = off;
        return;
    }
    if (policy == Policy::lifo || before(q, h, head_at(q, q->headused))) {
        h->link = q->headused;
        q->headused = off;
        return;
    }
    std::uint32_t prev = q->headused;
    for (;;) {
        MsgHead* p = head_at(q, prev);
        if (p->link == 0 || before(q, h, head_at(q, p->link))) {
            h->link = p->link;
            p->link = off;
            if (h->link == 0) q->tailused = off;
            return;
        }
        prev = p->link;
    }
}

void set_me(MsgHead* h) noexcept {
    const std::uint64_t me = ipc::self_owner_id();
    h->pid = ipc::owner_pid(me);
    h->tid = ipc::owner_tid(me);
}

// A receiver killed after a message was handed to it, before it took it:
// the message goes back into the queue (lock held). Only looked at when the
// queue seems empty while handed messages are outstanding.
void reclaim_handed(QueueHeader* q) noexcept {
    for (Waiter& w : q->recv_waiters) {
        if (w.state != kSignaled || thread_alive(w.pid, w.tid)) continue;
        if (w.handed != 0) {
            const std::uint32_t off = head_off(q, w.handed - 1);
            head_at(q, off)->state = layout::kHeadQueued;
            insert_used(q, off);
            ++q->nmsgs;
            --q->nhanded;
        }
        waiter_free(w);
        ++q->reclaimed_waiters;
    }
}

void init_body(QueueHeader* q, const Params& p, const Geometry& g, std::string_view label) noexcept {
    std::memset(reinterpret_cast<std::byte*>(q) + sizeof(ipc::SegmentHeader), 0,
                g.total - sizeof(ipc::SegmentHeader));
    std::memcpy(q->segname, label.data(), std::min(label.size(), sizeof q->segname - 1));
    q->blknum = p.blknum;
    q->blksize = g.blksize;
    q->flags = static_cast<std::uint32_t>(p.policy);
    q->block_stride = g.stride;
    q->off_heads = g.off_heads;
    q->off_blocks = g.off_blocks;
    // Everything starts on the free lists, in index order.
    for (std::uint32_t i = 0; i < p.blknum; ++i) {
        head_at(q, head_off(q, i))->link = i + 1 < p.blknum ? head_off(q, i + 1) : 0;
        block_at(q, block_off(q, i))->link = i + 1 < p.blknum ? block_off(q, i + 1) : 0;
    }
    q->headfree = head_off(q, 0);
    q->blkfree = block_off(q, 0);
    q->nfree_heads = q->nfree_blks = p.blknum;
}

}  // namespace

// ---------------------------------------------------------------- set-up

std::size_t Queue::memory_size(const Params& params) { return geometry(params).total; }

Queue::Queue(Queue&& o) noexcept
    : q_(std::exchange(o.q_, nullptr)), segment_(std::move(o.segment_)), name_(std::move(o.name_)) {}

Queue& Queue::operator=(Queue&& o) noexcept {
    if (this != &o) {
        detach();
        q_ = std::exchange(o.q_, nullptr);
        segment_ = std::move(o.segment_);
        name_ = std::move(o.name_);
    }
    return *this;
}

Queue::~Queue() { detach(); }

Queue Queue::over(void* memory, std::size_t size, const Params& params, std::string_view label) {
    const Geometry g = geometry(params);
    if (size < g.total)
        throw xm::Error("message queue '" + std::string(label) + "': needs " +
                        std::to_string(g.total) + " bytes, given " + std::to_string(size));
    auto* q = static_cast<QueueHeader*>(memory);
    ipc::init_header(q->segment, kQueueKind, g.total);
    init_body(q, params, g, label);
    q->segment.state.store(static_cast<std::uint32_t>(ipc::SegmentState::ready),
                           std::memory_order_release);
    Queue out;
    out.q_ = q;
    out.name_ = std::string(label);
    return out;
}

Queue Queue::bind(void* memory, std::size_t size) {
    auto* q = static_cast<QueueHeader*>(memory);
    try {
        ipc::validate_header("message queue", q->segment, kQueueKind,
                             std::min<std::size_t>(size, q->segment.total_size));
    } catch (const ipc::SegmentError& e) {
        throw xm::Error(e.what());
    }
    if (size < q->segment.total_size)
        throw xm::Error("message queue '" + std::string(q->segname) + "': memory smaller than the queue");
    Queue out;
    out.q_ = q;
    out.name_ = q->segname;
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
    init_body(static_cast<QueueHeader*>(seg.base()), p, g, full_name);
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
    Queue q;
    try {
        q.segment_ = ipc::Segment::attach(ref.segment, kQueueKind);
    } catch (const ipc::SegmentError& e) {
        throw xm::Error("message queue '" + std::string(full_name) + "': " + e.what());
    }
    q.q_ = static_cast<QueueHeader*>(q.segment_.base());
    q.name_ = std::string(full_name);
    return q;
}

Queue Queue::attach(xm::Rtpu& self, std::string_view full_name) {
    const xm::ObjectRef ref = self.attach_object(full_name, ipc::ObjectType::xmail_msg);
    Queue q;
    try {
        q.segment_ = ipc::Segment::attach(ref.segment, kQueueKind);
    } catch (const ipc::SegmentError& e) {
        throw xm::Error("message queue '" + std::string(full_name) + "': " + e.what());
    }
    q.q_ = static_cast<QueueHeader*>(q.segment_.base());
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

// ---------------------------------------------------------------- hot paths

Status Queue::lock() noexcept {
    return lock_object(q_->mutex, q_->recoveries, [this] { repair(); });
}

Status Queue::send(const void* data, std::size_t size, std::uint32_t type, std::int32_t priority,
                   std::int64_t timeout_ns) noexcept {
    if (!q_) return Status::bad_argument;
    QueueHeader* q = q_;
    const std::uint64_t need64 = (size + q->blksize - 1) / q->blksize;
    if (need64 > q->blknum) return Status::too_big;
    const auto need = static_cast<std::uint32_t>(need64);
    const std::int64_t deadline = deadline_for(timeout_ns);
    Waiter* me = nullptr;
    for (;;) {
        if (const Status s = lock(); s != Status::ok) return s;
        if (me) {
            waiter_free(*me);
            me = nullptr;
        }
        if (q->headfree != 0 && q->nfree_blks >= need) break;
        Status fail = Status::ok;
        if (timeout_ns == 0)
            fail = Status::would_block;
        else if (deadline >= 0 && ipc::now_ns() >= deadline)
            fail = Status::timed_out;
        else if (!(me = waiter_add(q->send_waiters, layout::kMaxWaiters, q->next_ticket, priority)))
            fail = Status::too_many_waiters;
        ipc::unlock(q->mutex);
        if (fail != Status::ok) return fail;
        waiter_sleep(*me, deadline);
    }

    // Take a header off headfree and the blocks off blkfree, copying as we go.
    const std::uint32_t off = q->headfree;
    MsgHead* h = head_at(q, off);
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
    const std::uint32_t owner = head_index(q, off) + 1;
    std::uint32_t* prev_link = &h->blk;
    const auto* src = static_cast<const std::byte*>(data);
    std::size_t done = 0;
    for (std::uint32_t i = 0; i < need; ++i) {
        const std::uint32_t boff = q->blkfree;
        MsgBHead* b = block_at(q, boff);
        q->blkfree = b->link;
        --q->nfree_blks;
        b->owner = owner;
        b->link = 0;
        *prev_link = boff;
        prev_link = &b->link;
        const std::size_t chunk = std::min<std::size_t>(q->blksize, size - done);
        std::memcpy(block_data(b), src + done, chunk);
        done += chunk;
    }
    h->seq = q->next_seq++;
    std::atomic_thread_fence(std::memory_order_release);
    h->state = layout::kHeadQueued;  // commit point: from here the message exists
    ++q->sends;

    Waiter* wake = waiter_pick(q->recv_waiters, layout::kMaxWaiters, &q->reclaimed_waiters);
    if (wake) {
        // Hand the message straight to the highest-priority waiting receiver.
        h->state = layout::kHeadHanded;
        wake->handed = owner;
        ++q->nhanded;
        waiter_signal(*wake);
    } else {
        insert_used(q, off);
        ++q->nmsgs;
    }
    ipc::unlock(q->mutex);
    if (wake) waiter_wake(*wake);
    return Status::ok;
}

Status Queue::receive(void* buffer, std::size_t capacity, Info* info, std::int64_t timeout_ns,
                      std::int32_t task_priority) noexcept {
    if (!q_) return Status::bad_argument;
    QueueHeader* q = q_;
    const std::int64_t deadline = deadline_for(timeout_ns);
    Waiter* me = nullptr;
    std::uint32_t off = 0;
    for (;;) {
        if (const Status s = lock(); s != Status::ok) return s;
        if (me) {
            const std::uint32_t handed = me->state == kSignaled ? me->handed : 0;
            waiter_free(*me);
            me = nullptr;
            if (handed != 0) {
                off = head_off(q, handed - 1);
                --q->nhanded;
                MsgHead* h = head_at(q, off);
                if (h->size > capacity) {
                    // Does not fit: back into the queue for someone who can take it.
                    h->state = layout::kHeadQueued;
                    insert_used(q, off);
                    ++q->nmsgs;
                    if (info) *info = Info{h->type, h->priority, h->size};
                    ipc::unlock(q->mutex);
                    return Status::too_big;
                }
                break;
            }
        }
        if (q->nmsgs == 0 && q->nhanded > 0) reclaim_handed(q);
        if (q->nmsgs > 0) {
            off = q->headused;
            MsgHead* h = head_at(q, off);
            if (h->size > capacity) {
                if (info) *info = Info{h->type, h->priority, h->size};
                ipc::unlock(q->mutex);
                return Status::too_big;
            }
            q->headused = h->link;
            if (q->headused == 0) q->tailused = 0;
            --q->nmsgs;
            break;
        }
        Status fail = Status::ok;
        if (timeout_ns == 0)
            fail = Status::would_block;
        else if (deadline >= 0 && ipc::now_ns() >= deadline)
            fail = Status::timed_out;
        else if (!(me = waiter_add(q->recv_waiters, layout::kMaxWaiters, q->next_ticket,
                                   task_priority)))
            fail = Status::too_many_waiters;
        ipc::unlock(q->mutex);
        if (fail != Status::ok) return fail;
        waiter_sleep(*me, deadline);
    }

    // Copy the message out of its blocks, then free header and blocks.
    MsgHead* h = head_at(q, off);
    h->state = layout::kHeadReading;
    set_me(h);
    auto* dst = static_cast<std::byte*>(buffer);
    std::size_t done = 0;
    for (std::uint32_t boff = h->blk; boff != 0 && done < h->size;) {
        MsgBHead* b = block_at(q, boff);
        const std::size_t chunk = std::min<std::size_t>(q->blksize, h->size - done);
        std::memcpy(dst + done, block_data(b), chunk);
        done += chunk;
        boff = b->link;
    }
    if (info) *info = Info{h->type, h->priority, h->size};
    std::atomic_thread_fence(std::memory_order_release);
    h->state = layout::kHeadFree;  // commit point: the message is consumed
    for (std::uint32_t boff = h->blk; boff != 0;) {
        MsgBHead* b = block_at(q, boff);
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
    Waiter* wake = waiter_pick(q->send_waiters, layout::kMaxWaiters, &q->reclaimed_waiters);
    if (wake) waiter_signal(*wake);
    ipc::unlock(q->mutex);
    if (wake) waiter_wake(*wake);
    return Status::ok;
}

// ---------------------------------------------------------------- recovery

// Runs with the lock held, after its previous holder died: replay the
// per-header journal and rebuild every list from it.
void Queue::repair() noexcept {
    QueueHeader* q = q_;
    const std::uint32_t n = q->blknum;
    auto dead = [](const Waiter& w) {
        const std::uint64_t id = static_cast<std::uint64_t>(static_cast<std::uint32_t>(w.pid)) << 32 |
                                 static_cast<std::uint32_t>(w.tid);
        return !ipc::owner_alive(id);
    };
    // Waiters: drop the dead; re-arm the word of signalled ones (the signaller
    // may have died between setting the state and the word).
    for (Waiter* list : {q->recv_waiters, q->send_waiters}) {
        for (std::uint32_t i = 0; i < layout::kMaxWaiters; ++i) {
            Waiter& w = list[i];
            if (w.state == kFree) continue;
            if (dead(w)) {
                waiter_free(w);
                ++q->reclaimed_waiters;
            } else if (w.state == kSignaled) {
                w.word.store(1, std::memory_order_release);
            }
        }
    }
    // A waiting (not yet signalled) slot holds no message: a sender that died
    // halfway through a hand-off may have named its header in the slot before
    // signalling it. The header then goes back into the queue below.
    for (Waiter& w : q->recv_waiters)
        if (w.state != kSignaled) w.handed = 0;
    // Header states: roll interrupted operations back.
    for (std::uint32_t i = 0; i < n; ++i) {
        MsgHead* h = head_at(q, head_off(q, i));
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
        if (w.handed != 0 && (w.handed > n || head_at(q, head_off(q, w.handed - 1))->state != layout::kHeadHanded))
            w.handed = 0;
    // Blocks: owned exactly by the chains of live messages.
    for (std::uint32_t j = 0; j < n; ++j) block_at(q, block_off(q, j))->owner = 0;
    for (std::uint32_t i = 0; i < n; ++i) {
        MsgHead* h = head_at(q, head_off(q, i));
        if (h->state != layout::kHeadQueued && h->state != layout::kHeadHanded) continue;
        bool sound = h->size <= std::uint64_t{h->nblk} * q->blksize;
        std::uint32_t boff = h->blk;
        for (std::uint32_t k = 0; sound && k < h->nblk; ++k) {
            if (!block_valid(q, boff) || block_at(q, boff)->owner != 0) {
                sound = false;
                break;
            }
            block_at(q, boff)->owner = i + 1;
            boff = block_at(q, boff)->link;
        }
        if (!sound || boff != 0) {
            // Cannot happen with the commit order above; never keep a broken chain.
            for (std::uint32_t j = 0; j < n; ++j)
                if (block_at(q, block_off(q, j))->owner == i + 1) block_at(q, block_off(q, j))->owner = 0;
            h->state = layout::kHeadFree;
        }
    }
    q->blkfree = 0;
    q->nfree_blks = 0;
    for (std::uint32_t j = n; j-- > 0;) {
        MsgBHead* b = block_at(q, block_off(q, j));
        if (b->owner != 0) continue;
        b->link = q->blkfree;
        q->blkfree = block_off(q, j);
        ++q->nfree_blks;
    }
    // Header lists, headused in policy order.
    q->headfree = q->headused = q->tailused = 0;
    q->nfree_heads = q->nmsgs = q->nhanded = 0;
    for (std::uint32_t i = n; i-- > 0;) {
        const std::uint32_t off = head_off(q, i);
        MsgHead* h = head_at(q, off);
        if (h->state == layout::kHeadFree) {
            h->blk = 0;
            h->link = q->headfree;
            q->headfree = off;
            ++q->nfree_heads;
        } else if (h->state == layout::kHeadQueued) {
            insert_used(q, off);
            ++q->nmsgs;
        } else {
            ++q->nhanded;
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
    ipc::unlock(q_->mutex);
    return s;
}

std::string Queue::check() {
    if (!q_) return "not attached";
    if (lock() != Status::ok) return "lock timed out";
    QueueHeader* q = q_;
    if (q->nhanded > 0) reclaim_handed(q);
    const std::uint32_t n = q->blknum;
    std::string err;
    auto fail = [&](const std::string& m) {
        if (err.empty()) err = m;
    };
    std::vector<int> seen(n, 0);
    // headfree
    std::uint32_t count = 0;
    for (std::uint32_t off = q->headfree; off != 0 && count <= n; off = head_at(q, off)->link, ++count) {
        if (!head_valid(q, off)) { fail("headfree: bad offset"); break; }
        const std::uint32_t i = head_index(q, off);
        if (seen[i]++) fail("header " + std::to_string(i) + " on two lists");
        if (head_at(q, off)->state != layout::kHeadFree) fail("headfree: header not FREE");
    }
    if (count != q->nfree_heads) fail("headfree holds " + std::to_string(count) + ", nfree_heads " +
                                      std::to_string(q->nfree_heads));
    // headused
    count = 0;
    std::uint32_t last = 0;
    for (std::uint32_t off = q->headused; off != 0 && count <= n; off = head_at(q, off)->link, ++count) {
        if (!head_valid(q, off)) { fail("headused: bad offset"); break; }
        const std::uint32_t i = head_index(q, off);
        if (seen[i]++) fail("header " + std::to_string(i) + " on two lists");
        if (head_at(q, off)->state != layout::kHeadQueued) fail("headused: header not QUEUED");
        if (last != 0 && before(q, head_at(q, off), head_at(q, last)))
            fail("headused out of policy order");
        last = off;
    }
    if (count != q->nmsgs) fail("headused holds " + std::to_string(count) + ", nmsgs " +
                                std::to_string(q->nmsgs));
    if (q->tailused != last) fail("tailused is not the last of headused");
    // handed and the rest
    std::uint32_t handed = 0, live_blocks = 0;
    for (std::uint32_t i = 0; i < n; ++i) {
        MsgHead* h = head_at(q, head_off(q, i));
        if (h->state == layout::kHeadHanded) {
            ++handed;
            bool held = false;
            for (const Waiter& w : q->recv_waiters) held = held || (w.state == kSignaled && w.handed == i + 1);
            if (!held) fail("header " + std::to_string(i) + " handed to no waiter");
        } else if (!seen[i]) {
            fail("header " + std::to_string(i) + " on no list (state " + std::to_string(h->state) + ")");
        }
        if (h->state == layout::kHeadQueued || h->state == layout::kHeadHanded) {
            if (h->size > std::uint64_t{h->nblk} * q->blksize ||
                (h->nblk > 0 && h->size <= std::uint64_t{h->nblk - 1} * q->blksize))
                fail("header " + std::to_string(i) + ": size does not match its block count");
            std::uint32_t boff = h->blk;
            for (std::uint32_t k = 0; k < h->nblk; ++k) {
                if (!block_valid(q, boff) || block_at(q, boff)->owner != i + 1) {
                    fail("header " + std::to_string(i) + ": broken block chain");
                    break;
                }
                boff = block_at(q, boff)->link;
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
        if (w.handed > n || head_at(q, head_off(q, w.handed - 1))->state != layout::kHeadHanded)
            fail("receive waiter " + std::to_string(k) + " holds a header that is not HANDED");
    }
    count = 0;
    for (std::uint32_t off = q->blkfree; off != 0 && count <= n; off = block_at(q, off)->link, ++count) {
        if (!block_valid(q, off)) { fail("blkfree: bad offset"); break; }
        if (block_at(q, off)->owner != 0) fail("blkfree: block owned by a message");
    }
    if (count != q->nfree_blks) fail("blkfree holds " + std::to_string(count) + ", nfree_blks " +
                                     std::to_string(q->nfree_blks));
    if (count + live_blocks != n) fail("blocks lost: " + std::to_string(count) + " free + " +
                                       std::to_string(live_blocks) + " used != " + std::to_string(n));
    ipc::unlock(q->mutex);
    return err;
}

std::string Queue::dump() {
    std::string out;
    if (!q_ || lock() != Status::ok) return out;
    for (std::uint32_t off = q_->headused; off != 0; off = head_at(q_, off)->link) {
        const MsgHead* h = head_at(q_, off);
        if (!out.empty()) out += ' ';
        out += std::to_string(h->priority) + ':' + std::to_string(h->type) + ':' + std::to_string(h->size);
    }
    ipc::unlock(q_->mutex);
    return out;
}

}  // namespace chimera::msg

namespace chimera::xm::detail {
ipc::Segment create_msg_segment(const std::string& segment, const std::string& full_name,
                                const ObjectParams& params) {
    return msg::create_segment_body(segment, full_name, params);
}
}  // namespace chimera::xm::detail
