// Remote semaphores (thesis §5.4.2).
#include "chimera/sem.hpp"

#include <cstring>
#include <utility>

#include "detail.hpp"

namespace chimera::sem {

using layout::SemHeader;
using namespace xm::detail;

namespace {

constexpr ipc::SegmentKind kSemKind{ipc::ObjectType::xmail_sem, layout::kSemVersion};

void check_args(std::string_view name, Kind kind, std::int32_t initial) {
    if (kind != Kind::binary && kind != Kind::counting)
        throw xm::Error("semaphore '" + std::string(name) + "': kind must be binary or counting");
    if (initial < 0 || (kind == Kind::binary && initial > 1))
        throw xm::Error("semaphore '" + std::string(name) + "': initial value " +
                        std::to_string(initial) +
                        (kind == Kind::binary ? " (binary: 0 or 1)" : " (counting: >= 0)"));
}

void init_body(SemHeader* h, Kind kind, std::int32_t initial, std::string_view label) noexcept {
    std::memset(reinterpret_cast<std::byte*>(h) + sizeof(ipc::SegmentHeader), 0,
                sizeof(SemHeader) - sizeof(ipc::SegmentHeader));
    std::memcpy(h->name, label.data(), std::min(label.size(), sizeof h->name - 1));
    h->kind = static_cast<std::uint32_t>(kind);
    h->value = initial;
}

// The fixed part: what attach and bind refuse.
ipc::Fault fixed_fault(const void* image, std::size_t size) noexcept {
    if (ipc::Fault f = ipc::header_fault(image, size, kSemKind)) return f;
    // The segment header's own size matches the image; the semaphore after it
    // must fit too (a peer can publish a segment too short for one).
    if (ipc::Fault f = ipc::fault_if(size < sizeof(SemHeader), "segment size", size, sizeof(SemHeader), "at least"))
        return f;
    const auto& h = *static_cast<const SemHeader*>(image);
    using ipc::fault_if;
    if (ipc::Fault f = fault_if(h.kind > static_cast<std::uint32_t>(Kind::counting), "kind", h.kind,
                                static_cast<std::uint32_t>(Kind::counting)))
        return f;
    return fault_if(strnlen(h.name, sizeof h.name) == sizeof h.name, "name length", sizeof h.name,
                    sizeof h.name - 1);
}

}  // namespace

ipc::Fault validate(const void* image, std::size_t size) noexcept {
    if (ipc::Fault f = fixed_fault(image, size)) return f;
    const auto& h = *static_cast<const SemHeader*>(image);
    const std::int64_t most = h.kind == static_cast<std::uint32_t>(Kind::binary) ? 1 : INT32_MAX;
    if (h.value < 0 || h.value > most)
        return {"value", -1, static_cast<std::uint64_t>(static_cast<std::int64_t>(h.value)),
                static_cast<std::uint64_t>(most), "0 to"};
    for (std::uint32_t i = 0; i < layout::kMaxWaiters; ++i)
        if (ipc::Fault f = ipc::fault_if(h.waiters[i].state > kSignaled, "waiter state", h.waiters[i].state,
                                         kSignaled, "at most", i))
            return f;
    return {};
}

ipc::Segment create_segment_body(const std::string& segment, const std::string& full_name,
                                 const xm::ObjectParams& params) {
    const auto kind = static_cast<Kind>(params.a);
    const auto initial = static_cast<std::int32_t>(static_cast<std::int64_t>(params.b));
    check_args(full_name, kind, initial);
    ipc::Segment seg = ipc::Segment::create(segment, sizeof(SemHeader), kSemKind);
    init_body(static_cast<SemHeader*>(seg.base()), kind, initial, full_name);
    seg.publish();
    return seg;
}

Semaphore::Semaphore(Semaphore&& o) noexcept
    : h_(std::exchange(o.h_, nullptr)), segment_(std::move(o.segment_)), name_(std::move(o.name_)) {}

Semaphore& Semaphore::operator=(Semaphore&& o) noexcept {
    if (this != &o) {
        detach();
        h_ = std::exchange(o.h_, nullptr);
        segment_ = std::move(o.segment_);
        name_ = std::move(o.name_);
    }
    return *this;
}

Semaphore::~Semaphore() { detach(); }

Semaphore Semaphore::create(xm::Rtpu& self, std::string_view full_name, Kind kind,
                            std::int32_t initial) {
    check_args(full_name, kind, initial);
    xm::ObjectParams op;
    op.a = static_cast<std::uint32_t>(kind);
    op.b = static_cast<std::uint64_t>(initial);
    return map(self.create_object(full_name, ipc::ObjectType::xmail_sem, op), full_name);
}

Semaphore Semaphore::attach(xm::Rtpu& self, std::string_view full_name) {
    return map(self.attach_object(full_name, ipc::ObjectType::xmail_sem), full_name);
}

Semaphore Semaphore::map(const xm::ObjectRef& ref, std::string_view full_name) {
    Semaphore s;
    try {
        s.segment_ = ipc::Segment::attach(ref.segment, kSemKind);
    } catch (const ipc::SegmentError& e) {
        throw xm::Error("semaphore '" + std::string(full_name) + "': " + e.what());
    }
    if (const ipc::Fault f = fixed_fault(s.segment_.base(), s.segment_.size()))
        throw xm::Error("semaphore '" + std::string(full_name) + "': corrupt: " + ipc::describe(ref.segment, f));
    s.h_ = static_cast<SemHeader*>(s.segment_.base());
    s.name_ = std::string(full_name);
    return s;
}

Semaphore Semaphore::over(void* memory, Kind kind, std::int32_t initial, std::string_view label) {
    check_args(label, kind, initial);
    auto* h = static_cast<SemHeader*>(memory);
    ipc::init_header(h->segment, kSemKind, sizeof(SemHeader));
    init_body(h, kind, initial, label);
    h->segment.state.store(static_cast<std::uint32_t>(ipc::SegmentState::ready),
                           std::memory_order_release);
    Semaphore s;
    s.h_ = h;
    s.name_ = std::string(label);
    return s;
}

Semaphore Semaphore::bind(void* memory) {
    auto* h = static_cast<SemHeader*>(memory);
    try {
        ipc::validate_header("semaphore", h->segment, kSemKind, sizeof(SemHeader));
    } catch (const ipc::SegmentError& e) {
        throw xm::Error(e.what());
    }
    if (const ipc::Fault f = fixed_fault(memory, sizeof(SemHeader)))
        throw xm::Error("semaphore: corrupt: " + ipc::describe("<memory>", f));
    Semaphore s;
    s.h_ = h;
    s.name_ = std::string(h->name, strnlen(h->name, sizeof h->name));
    return s;
}

void Semaphore::detach() noexcept {
    if (segment_.valid()) segment_.detach_destroy_if_last();
    h_ = nullptr;
}

void Semaphore::destroy(xm::Rtpu& self) {
    // Name first: detaching first could free the object as its last user.
    self.destroy_object(name_);
    h_ = nullptr;
    segment_.detach();
}

Status Semaphore::lock() noexcept {
    return lock_object(h_->mutex, h_->recoveries, [this] { repair(); });
}

xm::layout::Waiter* Semaphore::release_unit() noexcept {
    Waiter* w = waiter_pick(h_->waiters, layout::kMaxWaiters);
    if (w) {
        waiter_signal(*w);  // the unit goes straight to the waiter: value unchanged
        return w;
    }
    if (h_->kind == static_cast<std::uint32_t>(Kind::counting) || h_->value < 1) ++h_->value;
    return nullptr;
}

void Semaphore::repair() noexcept {
    // A unit granted to a waiter that died before taking it is passed on.
    for (std::uint32_t i = 0; i < layout::kMaxWaiters; ++i) {
        Waiter& w = h_->waiters[i];
        if (w.state == kFree) continue;
        if (thread_alive(w.pid, w.tid)) {
            if (w.state == kSignaled) waiter_rearm(w);
            continue;
        }
        const bool granted = w.state == kSignaled;
        waiter_free(w);
        ++h_->reclaimed_waiters;
        if (granted)
            if (Waiter* next = release_unit()) waiter_wake(*next);
    }
    if (h_->value < 0) h_->value = 0;
    if (h_->kind == static_cast<std::uint32_t>(Kind::binary) && h_->value > 1) h_->value = 1;
}

// Units granted to waiters that died before taking them are passed on (lock
// held). Returns true when a unit came back or moved on.
bool Semaphore::reclaim_granted() noexcept {
    bool back = false;
    for (std::uint32_t i = 0; i < layout::kMaxWaiters; ++i) {
        Waiter& w = h_->waiters[i];
        if (w.state != kSignaled || thread_alive(w.pid, w.tid)) continue;
        waiter_free(w);
        ++h_->reclaimed_waiters;
        if (Waiter* next = release_unit()) waiter_wake(*next);
        back = true;
    }
    return back;
}

// A sleeper's look at every slice: a unit granted to a waiter that died
// since (after its wake-up reached it) would otherwise strand the waiters
// still blocked here, which sleep on their own words.
void Semaphore::pass_on_dead_grants(const Waiter* self) noexcept {
    if (!signalled_dead(h_->waiters, layout::kMaxWaiters, self)) return;
    if (lock() != Status::ok) return;
    reclaim_granted();
    unlock_object(h_->mutex);
}

Status Semaphore::p(std::int64_t timeout_ns, std::int32_t priority) noexcept {
    if (!h_) return Status::bad_argument;
    WaitDeadline deadline(timeout_ns);
    Waiter* me = nullptr;
    for (;;) {
        if (const Status s = lock(); s != Status::ok) return s;
        if (me) {
            const bool granted = me->state == kSignaled;
            waiter_free(*me);
            me = nullptr;
            if (granted) {
                unlock_object(h_->mutex);
                return Status::ok;
            }
        }
        if (h_->value <= 0) reclaim_granted();
        if (h_->value > 0) {
            --h_->value;
            unlock_object(h_->mutex);
            return Status::ok;
        }
        Status fail = Status::ok;
        if (timeout_ns == 0)
            fail = Status::would_block;
        else if (deadline.passed())
            fail = Status::timed_out;
        else if (!(me = waiter_add(h_->waiters, layout::kMaxWaiters, h_->next_ticket, priority)))
            fail = Status::too_many_waiters;
        unlock_object(h_->mutex);
        if (fail != Status::ok) return fail;
        waiter_sleep(*me, h_->waiters, layout::kMaxWaiters, deadline, [&] { pass_on_dead_grants(me); });
    }
}

Status Semaphore::v() noexcept {
    if (!h_) return Status::bad_argument;
    if (const Status s = lock(); s != Status::ok) return s;
    Waiter* w = release_unit();
    WaiterId id = w ? id_of(*w) : WaiterId{};
    unlock_object(h_->mutex);
    // No unit stays with a waiter that died (killed, reaped or not): when the
    // wake-up reaches nobody and the thread is gone, take the unit back and
    // pass it on, before V returns.
    while (w && !waiter_wake_checked(*w, id)) {
        if (lock() != Status::ok) return Status::ok;  // the sleepers' slices pass it on
        Waiter* dead = w;
        w = nullptr;
        if (still_signalled(*dead, id)) {
            waiter_free(*dead);
            ++h_->reclaimed_waiters;
            if ((w = release_unit())) id = id_of(*w);
        }
        unlock_object(h_->mutex);
    }
    return Status::ok;
}

std::int32_t Semaphore::value() noexcept {
    if (!h_ || lock() != Status::ok) return -1;
    reclaim_granted();  // a unit granted to a waiter that died is available
    const std::int32_t v = h_->value;
    unlock_object(h_->mutex);
    return v;
}

std::uint32_t Semaphore::waiting() noexcept {
    if (!h_ || lock() != Status::ok) return 0;
    const std::uint32_t n = waiter_count(h_->waiters, layout::kMaxWaiters);
    unlock_object(h_->mutex);
    return n;
}

}  // namespace chimera::sem

namespace chimera::xm::detail {
ipc::Segment create_sem_segment(const std::string& segment, const std::string& full_name,
                                const ObjectParams& params) {
    return sem::create_segment_body(segment, full_name, params);
}
}  // namespace chimera::xm::detail
