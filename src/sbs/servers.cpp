// Soft real-time tasks and the MUF deferrable, sporadic and background servers
// (thesis §6.4, §6.5.2, Listings 2-4) on the public task API. See servers.hpp.
#include "servers.hpp"

#include <algorithm>

namespace chimera::sbs::detail {

using muf::FailureAction;
using muf::infinity;

// ------------------------------------------------------------------ Listing 2

void SoftTask::on_release() noexcept {
    if (const int c = saved_; c != 0) {
        saved_ = 0;
        muf::set_criticality(c);
    }
}

void SoftTask::on_failure(muf::Failure kind) noexcept {
    switch (kind) {
        case muf::Failure::maxexec:  // E used up: go on in left-over time
            if (saved_ == 0) saved_ = muf::criticality();
            muf::set_criticality(std::min(lowered_, static_cast<int>(saved_)));
            break;
        case muf::Failure::deadline:  // missed: back to the reserved level, the next period's time
            on_release();
            break;
        case muf::Failure::minexec: break;
    }
}

// ------------------------------------------------------------------ Listing 3

void DeferrableServer::begin() noexcept {
    muf::set_dfhandler(&DeferrableServer::handler, high_, this);
    muf::set_criticality(high_);
    next_start_ = muf::clock_ns();
    muf::set_deadline(next_start_, 0, capacity_, period_);
}

FailureAction DeferrableServer::handler(muf::Failure kind, void* self) noexcept {
    auto& s = *static_cast<DeferrableServer*>(self);
    switch (kind) {
        case muf::Failure::deadline: {  // replenishment time: full capacity, high again
            s.next_start_ += s.period_;
            // After a long hold-off, catch up rather than replenish once per lost period.
            const std::int64_t now = muf::clock_ns();
            if (now - s.next_start_ >= s.period_) s.next_start_ += (now - s.next_start_) / s.period_ * s.period_;
            muf::set_criticality(s.high_);
            muf::set_deadline(s.next_start_, 0, s.capacity_, s.period_);
            break;
        }
        case muf::Failure::maxexec:  // capacity used up
            muf::set_criticality(s.low_);
            break;
        case muf::Failure::minexec: break;  // MINEXEC is never set
    }
    return FailureAction::resume;
}

// ------------------------------------------------------------------ Listing 4

void SporadicServer::begin() noexcept {
    head_ = 0;
    size_ = 0;
    muf::set_dfhandler(&SporadicServer::handler, high_, this);
    muf::set_criticality(high_);
    muf::set_deadline(muf::clock_ns(), 0, capacity_, infinity);
}

void SporadicServer::event_begin() noexcept {
    // In exhausted mode the budget is infinite: nothing of it is capacity.
    const std::int64_t left = muf::execleft();
    left_at_start_ = left == infinity ? 0 : left;
    event_start_ = muf::execstart();
}

void SporadicServer::event_end() noexcept {
    const std::int64_t used = muf::execend() - event_start_;
    // Only what was used of the capacity comes back (time used at `low` was left-over time).
    const std::int64_t from_capacity = std::min(used, left_at_start_);
    if (from_capacity <= 0) return;
    muf::enter_critical();  // the handler pops while we push
    push(event_start_ + period_, from_capacity);
    muf::leave_critical();
}

void SporadicServer::push(std::int64_t at, std::int64_t amount) noexcept {
    if (size_ == kQueue) {  // full: merge into the newest entry (it comes back a little later)
        Replenishment& last = queue_[(head_ + size_ - 1) % kQueue];
        last.at = std::max(last.at, at);
        last.amount += amount;
        return;
    }
    queue_[(head_ + size_) % kQueue] = Replenishment{at, amount};
    size_ = size_ + 1;
}

void SporadicServer::refill() noexcept {
    std::int64_t left = muf::execleft();
    if (left == infinity) left = 0;
    const std::int64_t now = muf::clock_ns();
    while (size_ > 0 && queue_[head_].at <= now) {
        left += queue_[head_].amount;
        head_ = (head_ + 1) % kQueue;
        size_ = size_ - 1;
    }
    left = std::min(left, capacity_);
    const std::int64_t until_next = size_ > 0 ? queue_[head_].at - now : infinity;
    if (left <= 0) {
        // No capacity: low until the next replenishment (there is one: the
        // capacity was used, so it is in the list).
        muf::set_deadline(now, 0, infinity, size_ > 0 ? until_next : period_);
        muf::set_criticality(low_);
    } else {
        muf::set_deadline(now, 0, left, until_next);
        muf::set_criticality(high_);
    }
}

FailureAction SporadicServer::handler(muf::Failure kind, void* self) noexcept {
    // DEADLINE (a replenishment is due) and MAXEXEC (capacity used up) alike.
    if (kind != muf::Failure::minexec) static_cast<SporadicServer*>(self)->refill();
    return FailureAction::resume;
}

// ------------------------------------------------------------------ background

void BackgroundServer::begin() noexcept {
    muf::set_dfhandler(nullptr, 0, nullptr);
    muf::set_criticality(level_);
    muf::set_deadline(muf::clock_ns(), 0, infinity, infinity);
}

}  // namespace chimera::sbs::detail
