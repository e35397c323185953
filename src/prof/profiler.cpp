// TaskProfiler: per-cycle CPU time from the kernel's per-thread accounting
// (see prof.hpp for the method) and the lock-free publication of §6.7's
// counters.
#include <linux/perf_event.h>
#include <sys/mman.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <ctime>
#include <string>
#include <utility>

#include "chimera/ipc/clock.hpp"
#include "chimera/prof.hpp"
#include "chimera/trace.hpp"
#include "seqlock.hpp"

namespace chimera::prof {

namespace {

struct PageRead {
    std::uint32_t seq;
    std::uint64_t count;
    std::int64_t wall;
};

// The perf_event_mmap_page protocol (linux/perf_event.h): `lock` changes
// around every kernel update. The wall clock is read inside the same window,
// so `seq` is the page's state at time `wall`.
inline PageRead read_page(const perf_event_mmap_page* pg) noexcept {
    const volatile perf_event_mmap_page* p = pg;
    for (;;) {
        const std::uint32_t seq = p->lock;
        std::atomic_signal_fence(std::memory_order_seq_cst);
        const auto count = static_cast<std::uint64_t>(p->offset);
        const std::int64_t wall = ipc::now_ns();
        std::atomic_signal_fence(std::memory_order_seq_cst);
        if (p->lock == seq) return {seq, count, wall};
    }
}

int open_task_clock() noexcept {
    perf_event_attr attr;
    std::memset(&attr, 0, sizeof attr);
    attr.size = sizeof attr;
    attr.type = PERF_TYPE_SOFTWARE;
    attr.config = PERF_COUNT_SW_TASK_CLOCK;
    int fd = static_cast<int>(
        syscall(SYS_perf_event_open, &attr, 0 /*this thread*/, -1, -1, PERF_FLAG_FD_CLOEXEC));
    if (fd < 0 && (errno == EACCES || errno == EPERM)) {
        attr.exclude_kernel = 1;
        attr.exclude_hv = 1;
        fd = static_cast<int>(
            syscall(SYS_perf_event_open, &attr, 0, -1, -1, PERF_FLAG_FD_CLOEXEC));
    }
    return fd;
}

// The task is a cell's only writer: a plain increment, published by the seqlock.
template <typename T>
inline void count_one(std::atomic<T>& cell) noexcept {
    cell.store(cell.load(std::memory_order_relaxed) + 1, std::memory_order_relaxed);
}

}  // namespace

TaskProfiler::TaskProfiler(TaskSlot slot, bool allow_perf) : slot_(slot) {
    if (!slot_.valid()) throw StatusError("TaskProfiler: invalid task slot");
    slot_.set_tid(static_cast<int>(gettid()));

    std::string why;
    if (allow_perf) {
        const int fd = open_task_clock();
        if (fd >= 0) {
            void* page = mmap(nullptr, static_cast<std::size_t>(sysconf(_SC_PAGESIZE)), PROT_READ,
                              MAP_SHARED, fd, 0);
            if (page != MAP_FAILED) {
                perf_fd_ = fd;
                perf_page_ = page;
                clock_ = CpuClock::perf_switch;
                take_anchor();
            } else {
                why = std::string("mmap of the perf page: ") + std::strerror(errno);
                ::close(fd);
            }
        } else {
            why = std::string("perf_event_open: ") + std::strerror(errno);
        }
    } else {
        why = "perf page not wanted";
    }
    if (clock_ == CpuClock::none) {
        clock_ = CpuClock::thread_cputime;
        if (allow_perf)
            slot_.warning("profiling: " + why +
                          "; CPU time from CLOCK_THREAD_CPUTIME_ID (2 system calls per cycle)");
    }

    // Continue from what the slot holds (the task is its only writer).
    ProfileData& p = slot_.data()->profile;
    cycles_ = p.cycles.load(std::memory_order_relaxed);
    misses_ = p.misses.load(std::memory_order_relaxed);
    accounted_ = p.accounted.load(std::memory_order_relaxed);
    q_total_ = p.q_total.load(std::memory_order_relaxed);
    q_min_ = p.q_min.load(std::memory_order_relaxed);
    q_max_ = p.q_max.load(std::memory_order_relaxed);
    q_last_ = p.q_last.load(std::memory_order_relaxed);
    switched_ = p.switched.load(std::memory_order_relaxed);
    epoch_ = p.epoch_seen.load(std::memory_order_relaxed);
    accounting_ = static_cast<Accounting>(p.accounting.load(std::memory_order_relaxed));
    tick_ns_ = p.unit_num.load(std::memory_order_relaxed);
    if (accounting_ != Accounting::half_tick || tick_ns_ <= 0) tick_ns_ = 1;
    hist_width_ns_ = p.hist_width_ns.load(std::memory_order_relaxed);
    publish_begin();
    p.cpu_clock.store(static_cast<std::uint32_t>(clock_), std::memory_order_relaxed);
    publish_end();
}

TaskProfiler::TaskProfiler(TaskProfiler&& o) noexcept { *this = std::move(o); }

TaskProfiler& TaskProfiler::operator=(TaskProfiler&& o) noexcept {
    if (this == &o) return *this;
    close();
    slot_ = std::exchange(o.slot_, TaskSlot());
    clock_ = std::exchange(o.clock_, CpuClock::none);
    perf_fd_ = std::exchange(o.perf_fd_, -1);
    perf_page_ = std::exchange(o.perf_page_, nullptr);
    in_cycle_ = std::exchange(o.in_cycle_, false);
    begin_seq_ = o.begin_seq_;
    begin_count_ = o.begin_count_;
    begin_wall_ = o.begin_wall_;
    begin_cpu_ = o.begin_cpu_;
    begin_release_ = o.begin_release_;
    anchor_valid_ = o.anchor_valid_;
    anchor_seq_ = o.anchor_seq_;
    anchor_count_ = o.anchor_count_;
    anchor_wall_ = o.anchor_wall_;
    last_cycle_ns_ = o.last_cycle_ns_;
    depth_.store(0);
    pending_misses_.store(o.pending_misses_.exchange(0));
    cycles_ = o.cycles_;
    misses_ = o.misses_;
    accounted_ = o.accounted_;
    q_total_ = o.q_total_;
    q_min_ = o.q_min_;
    q_max_ = o.q_max_;
    q_last_ = o.q_last_;
    switched_ = o.switched_;
    epoch_ = o.epoch_;
    accounting_ = o.accounting_;
    tick_ns_ = o.tick_ns_;
    hist_width_ns_ = o.hist_width_ns_;
    return *this;
}

TaskProfiler::~TaskProfiler() { close(); }

void TaskProfiler::close() noexcept {
    if (perf_page_) munmap(perf_page_, static_cast<std::size_t>(sysconf(_SC_PAGESIZE)));
    if (perf_fd_ >= 0) ::close(perf_fd_);
    perf_page_ = nullptr;
    perf_fd_ = -1;
}

void TaskProfiler::start() {
    if (!slot_.valid()) return;
    StatusHeader* h = slot_.header();
    ipc::LockGuard guard(h->lock);
    if (!guard.owns())
        throw StatusError("TaskProfiler::start: status header lock: " +
                          std::string(ipc::to_string(guard.status())));
    RtpuBlock* b = h->rtpu_blocks.in(static_cast<void*>(h)) + slot_.rtpu();
    detail::write_begin(b->seq);
    b->epoch.store(b->epoch.load(std::memory_order_relaxed) + 1, std::memory_order_relaxed);
    b->start_ns.store(ipc::now_ns(), std::memory_order_relaxed);
    detail::write_end(b->seq);
}

std::int64_t TaskProfiler::thread_cpu_ns() const noexcept {
    timespec ts;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
    return static_cast<std::int64_t>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec;
}

void TaskProfiler::take_anchor() noexcept {
    // Set-up path and switched cycles only: one read() of the exact counter.
    const auto* pg = static_cast<const perf_event_mmap_page*>(perf_page_);
    std::uint64_t count = 0;
    const PageRead before = read_page(pg);
    if (::read(perf_fd_, &count, sizeof count) != sizeof count) {
        anchor_valid_ = false;
        return;
    }
    const PageRead after = read_page(pg);
    // A switch during the read() would make the pair inexact: no anchor then.
    anchor_valid_ = before.seq == after.seq;
    anchor_seq_ = after.seq;
    anchor_count_ = count;
    anchor_wall_ = before.wall;  // the count is taken just after this, in the call
}

void TaskProfiler::cycle_begin() noexcept { cycle_begin(0); }

void TaskProfiler::cycle_begin(std::int64_t release_ns) noexcept {
    begin_release_ = release_ns;
    if (clock_ == CpuClock::perf_switch) {
        const PageRead r = read_page(static_cast<const perf_event_mmap_page*>(perf_page_));
        begin_seq_ = r.seq;
        begin_wall_ = r.wall;
        if (anchor_valid_ && r.seq == anchor_seq_) {
            // Running since the anchor: exact.
            begin_count_ = anchor_count_ + static_cast<std::uint64_t>(r.wall - anchor_wall_);
        } else {
            // Switched since: the kernel's count at the last switch (the
            // switch-in that woke the task) — the cycle is charged from there.
            begin_count_ = r.count;
            anchor_valid_ = false;
        }
    } else if (clock_ == CpuClock::thread_cputime) {
        begin_cpu_ = thread_cpu_ns();
        begin_wall_ = ipc::now_ns();
    } else {
        return;
    }
    in_cycle_ = true;
    CHIMERA_TRACE_CYCLE_BEGIN(slot_.data()->rmod, slot_.index(), cycles_ + 1);
}

void TaskProfiler::cycle_end() noexcept {
    if (!in_cycle_) return;
    in_cycle_ = false;
    std::uint64_t c = 0;
    bool switched = false;
    std::int64_t wall;
    if (clock_ == CpuClock::perf_switch) {
        const PageRead r = read_page(static_cast<const perf_event_mmap_page*>(perf_page_));
        wall = r.wall;
        if (r.seq == begin_seq_) {
            // Not switched out since cycle_begin(): it ran the whole time.
            c = static_cast<std::uint64_t>(r.wall - begin_wall_);
            anchor_valid_ = true;  // exact or not, the count now is begin's + c
            anchor_seq_ = r.seq;
            anchor_count_ = begin_count_ + c;
            anchor_wall_ = r.wall;
        } else {
            // Switched out at least once: the counter's exact value now,
            // minus its value when the cycle began.
            switched = true;
            take_anchor();
            const std::int64_t after_end = anchor_wall_ - r.wall;  // ran since r
            if (anchor_valid_ && after_end >= 0 &&
                anchor_count_ >= begin_count_ + static_cast<std::uint64_t>(after_end))
                c = anchor_count_ - begin_count_ - static_cast<std::uint64_t>(after_end);
            else
                c = static_cast<std::uint64_t>(r.wall - begin_wall_);  // upper bound
        }
    } else {
        c = static_cast<std::uint64_t>(thread_cpu_ns() - begin_cpu_);
        wall = ipc::now_ns();
    }
    last_cycle_ns_ = c;

    publish_begin();
    check_epoch();
    ++cycles_;
    const std::uint64_t q =
        accounting_ == Accounting::half_tick ? half_ticks(c, static_cast<std::uint64_t>(tick_ns_)) : c;
    q_last_ = q;
    if (switched) ++switched_;
    if (cycles_ > 1) {  // §6.7: the first cycle after a reset is dropped
        ++accounted_;
        q_total_ += q;
        if (q < q_min_) q_min_ = q;
        if (q > q_max_) q_max_ = q;
        if (hist_width_ns_ != 0) {
            std::uint64_t b = c / hist_width_ns_;
            if (b >= kHistogramBuckets) b = kHistogramBuckets - 1;
            count_one(slot_.data()->profile.hist[b]);
        }
    }
    // Issue 14.11: every cycle, the first after a reset too (it is a real wake-up).
    ProfileData& p = slot_.data()->profile;
    count_one(p.cycle_time[time_bucket(static_cast<std::uint64_t>(std::max<std::int64_t>(wall - begin_wall_, 0)))]);
    if (begin_release_ > 0)
        count_one(p.lateness[time_bucket(static_cast<std::uint64_t>(std::max<std::int64_t>(begin_wall_ - begin_release_, 0)))]);
    slot_.data()->profile.last_end_ns.store(wall, std::memory_order_relaxed);
    publish_end();
    CHIMERA_TRACE_CYCLE_END(slot_.data()->rmod, slot_.index(), cycles_, c, switched ? 1 : 0);
}

void TaskProfiler::missed(std::uint32_t n) noexcept {
    if (!slot_.valid() || n == 0) return;
    CHIMERA_TRACE_DEADLINE_MISS(slot_.data()->rmod, slot_.index(), cycles_, n);
    if (depth_.load(std::memory_order_relaxed) != 0) {
        // A publication is in progress in the code this handler interrupted.
        pending_misses_.fetch_add(n, std::memory_order_relaxed);
        return;
    }
    publish_begin();
    check_epoch();
    misses_ += n;
    publish_end();
}

void TaskProfiler::set_histogram(std::uint64_t bucket_width_ns) noexcept {
    if (!slot_.valid()) return;
    publish_begin();
    hist_width_ns_ = bucket_width_ns;
    ProfileData& p = slot_.data()->profile;
    p.hist_width_ns.store(bucket_width_ns, std::memory_order_relaxed);
    for (auto& b : p.hist) b.store(0, std::memory_order_relaxed);
    publish_end();
}

void TaskProfiler::publish_begin() noexcept {
    const int d = depth_.load(std::memory_order_relaxed);
    depth_.store(d + 1, std::memory_order_relaxed);
    std::atomic_signal_fence(std::memory_order_seq_cst);
    if (d == 0) detail::write_begin(slot_.data()->profile.seq);
}

void TaskProfiler::publish_end() noexcept {
    ProfileData& p = slot_.data()->profile;
    for (;;) {
        misses_ += pending_misses_.exchange(0, std::memory_order_relaxed);
        p.cycles.store(cycles_, std::memory_order_relaxed);
        p.misses.store(misses_, std::memory_order_relaxed);
        p.accounted.store(accounted_, std::memory_order_relaxed);
        p.q_total.store(q_total_, std::memory_order_relaxed);
        p.q_min.store(q_min_, std::memory_order_relaxed);
        p.q_max.store(q_max_, std::memory_order_relaxed);
        p.q_last.store(q_last_, std::memory_order_relaxed);
        p.switched.store(switched_, std::memory_order_relaxed);
        const int d = depth_.load(std::memory_order_relaxed) - 1;
        if (d == 0) detail::write_end(p.seq);
        std::atomic_signal_fence(std::memory_order_seq_cst);
        depth_.store(d, std::memory_order_relaxed);
        // A miss that arrived after the fold above: publish it too.
        if (d != 0 || pending_misses_.load(std::memory_order_relaxed) == 0) return;
        publish_begin();
    }
}

void TaskProfiler::check_epoch() noexcept {
    StatusHeader* h = slot_.header();
    const RtpuBlock* b = h->rtpu_blocks.in(static_cast<const void*>(h)) + slot_.rtpu();
    if (b->epoch.load(std::memory_order_acquire) == epoch_) return;
    // A reset was requested: start a new profile (counts from this cycle on).
    std::uint32_t epoch = 0;
    std::uint32_t acc = 0;
    std::int64_t tick = 1;
    detail::read_consistent(b->seq, [&]() noexcept {
        epoch = b->epoch.load(std::memory_order_relaxed);
        acc = b->accounting.load(std::memory_order_relaxed);
        tick = b->tick_ns.load(std::memory_order_relaxed);
    });
    epoch_ = epoch;
    accounting_ = static_cast<Accounting>(acc);
    tick_ns_ = (accounting_ == Accounting::half_tick && tick > 0) ? tick : 1;
    cycles_ = misses_ = accounted_ = q_total_ = q_max_ = q_last_ = switched_ = 0;
    q_min_ = UINT64_MAX;
    ProfileData& p = slot_.data()->profile;
    p.epoch_seen.store(epoch_, std::memory_order_relaxed);
    p.accounting.store(acc, std::memory_order_relaxed);
    p.unit_num.store(accounting_ == Accounting::half_tick ? tick_ns_ : 1, std::memory_order_relaxed);
    p.unit_den.store(accounting_ == Accounting::half_tick ? 2 : 1, std::memory_order_relaxed);
    for (auto& cell : p.hist) cell.store(0, std::memory_order_relaxed);
    for (auto& cell : p.lateness) cell.store(0, std::memory_order_relaxed);
    for (auto& cell : p.cycle_time) cell.store(0, std::memory_order_relaxed);
}

}  // namespace chimera::prof
