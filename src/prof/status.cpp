// The status segment: layout, claim/release, resets, the task-slot setters,
// consistent snapshots and the §4.4.1 derivation.
#include <signal.h>
#include <unistd.h>

#include <algorithm>
#include <bit>
#include <cerrno>
#include <cmath>
#include <cstring>

#include "chimera/ipc/clock.hpp"
#include "chimera/prof.hpp"
#include "seqlock.hpp"

namespace chimera::prof {

namespace {

constexpr ipc::SegmentKind kKind{ipc::ObjectType::prof_status, kStatusLayoutVersion};

void copy_string(char* dst, std::size_t cap, std::string_view src) noexcept {
    // Not memcpy: an empty view may have no data (nullptr), which memcpy must not get.
    const std::size_t n = src.copy(dst, cap - 1);
    dst[n] = '\0';
}

std::string read_string(const char* src, std::size_t cap) {
    char buf[kVarListMax];
    const std::size_t n = std::min(cap, sizeof buf);
    std::memcpy(buf, src, n);
    buf[n - 1] = '\0';
    return std::string(buf);
}

RtpuBlock* rtpu_block(StatusHeader* h, int rtpu) noexcept {
    return h->rtpu_blocks.in(static_cast<void*>(h)) + rtpu;
}
const RtpuBlock* rtpu_block(const StatusHeader* h, int rtpu) noexcept {
    return h->rtpu_blocks.in(static_cast<const void*>(h)) + rtpu;
}
TaskSlotData* slot_at(StatusHeader* h, std::uint32_t i) noexcept {
    return h->slots.in(static_cast<void*>(h)) + i;
}
const TaskSlotData* slot_at(const StatusHeader* h, std::uint32_t i) noexcept {
    return h->slots.in(static_cast<const void*>(h)) + i;
}

RtpuEpoch read_rtpu(const StatusHeader* h, int rtpu) noexcept {
    RtpuEpoch e;
    const RtpuBlock* b = rtpu_block(h, rtpu);
    detail::read_consistent(b->seq, [&]() noexcept {
        e.epoch = b->epoch.load(std::memory_order_relaxed);
        e.status_epoch = b->status_epoch.load(std::memory_order_relaxed);
        e.start_ns = b->start_ns.load(std::memory_order_relaxed);
        e.tick_ns = b->tick_ns.load(std::memory_order_relaxed);
        e.accounting = static_cast<Accounting>(b->accounting.load(std::memory_order_relaxed));
    });
    if (e.tick_ns <= 0) e.tick_ns = 1;
    // Set before the segment was published, never changed.
    e.name = read_string(b->name, kNameMax);
    e.cpu = b->cpu;
    return e;
}

void check_rtpu(const StatusHeader* h, int rtpu, const std::string& where) {
    if (rtpu < 0 || static_cast<std::uint32_t>(rtpu) >= h->rtpus)
        throw StatusError(where + ": RTPU " + std::to_string(rtpu) + " out of range (0.." +
                          std::to_string(static_cast<int>(h->rtpus) - 1) + ")");
}

class HeaderLock {
public:
    HeaderLock(StatusHeader* h, const std::string& where) : guard_(h->lock) {
        if (!guard_.owns())
            throw StatusError(where + ": status header lock: " +
                              ipc::to_string(guard_.status()));
    }

private:
    ipc::LockGuard guard_;
};

// Caller holds the header lock.
void bump_epoch(StatusHeader* h, int rtpu, const Accounting* accounting,
                const std::int64_t* tick_ns) noexcept {
    RtpuBlock* b = rtpu_block(h, rtpu);
    detail::write_begin(b->seq);
    if (accounting) b->accounting.store(static_cast<std::uint32_t>(*accounting),
                                        std::memory_order_relaxed);
    if (tick_ns) b->tick_ns.store(*tick_ns, std::memory_order_relaxed);
    b->epoch.store(b->epoch.load(std::memory_order_relaxed) + 1, std::memory_order_relaxed);
    b->status_epoch.store(b->status_epoch.load(std::memory_order_relaxed) + 1,
                          std::memory_order_relaxed);
    b->start_ns.store(ipc::now_ns(), std::memory_order_relaxed);
    detail::write_end(b->seq);
}

void set_rtpu_accounting(StatusHeader* h, const std::string& name, int rtpu, Accounting accounting,
                         std::int64_t tick_ns) {
    check_rtpu(h, rtpu, "status segment " + name);
    if (accounting == Accounting::half_tick && tick_ns <= 0)
        throw StatusError("status segment " + name + ": half-tick accounting needs a tick > 0");
    const std::int64_t tick = accounting == Accounting::half_tick ? tick_ns : 1;
    HeaderLock lock(h, "status segment " + name);
    bump_epoch(h, rtpu, &accounting, &tick);
}

std::optional<RawSlot> read_slot(const StatusHeader* h, std::uint32_t index) {
    const TaskSlotData* s = slot_at(h, index);
    for (int attempt = 0; attempt < 1000; ++attempt) {
        const std::uint32_t gen = s->generation.load(std::memory_order_acquire);
        if (s->in_use.load(std::memory_order_acquire) == 0) return std::nullopt;
        RawSlot r;
        r.index = index;
        r.generation = gen;
        r.rmod = read_string(s->rmod, kNameMax);
        r.inputs = read_string(s->inputs, kVarListMax);
        r.outputs = read_string(s->outputs, kVarListMax);
        r.rtpu = s->rtpu;
        r.cpu = s->cpu;
        r.type = static_cast<char>(s->type);

        const InfoData& in = s->info;
        char policy[kPolicyMax], warning[kMessageMax], error[kMessageMax];
        const bool info_ok = detail::read_consistent(in.seq, [&]() noexcept {
            r.tid = in.tid.load(std::memory_order_relaxed);
            r.state = static_cast<TaskState>(in.state.load(std::memory_order_relaxed));
            r.crit = in.crit.load(std::memory_order_relaxed);
            r.ref_f = std::bit_cast<double>(in.ref_freq_bits.load(std::memory_order_relaxed));
            r.warn_epoch = in.warn_epoch.load(std::memory_order_relaxed);
            r.warnings = in.warnings.load(std::memory_order_relaxed);
            r.has_error = in.has_error.load(std::memory_order_relaxed) != 0;
            std::memcpy(policy, in.policy, sizeof policy);
            std::memcpy(warning, in.warning, sizeof warning);
            std::memcpy(error, in.error, sizeof error);
        });
        r.policy = read_string(policy, sizeof policy);
        r.warning = read_string(warning, sizeof warning);
        r.error = read_string(error, sizeof error);

        const ProfileData& p = s->profile;
        const bool prof_ok = detail::read_consistent(p.seq, [&]() noexcept {
            r.epoch_seen = p.epoch_seen.load(std::memory_order_relaxed);
            r.cpu_clock = static_cast<CpuClock>(p.cpu_clock.load(std::memory_order_relaxed));
            r.accounting = static_cast<Accounting>(p.accounting.load(std::memory_order_relaxed));
            r.unit_num = p.unit_num.load(std::memory_order_relaxed);
            r.unit_den = p.unit_den.load(std::memory_order_relaxed);
            r.cycles = p.cycles.load(std::memory_order_relaxed);
            r.misses = p.misses.load(std::memory_order_relaxed);
            r.accounted = p.accounted.load(std::memory_order_relaxed);
            r.q_total = p.q_total.load(std::memory_order_relaxed);
            r.q_min = p.q_min.load(std::memory_order_relaxed);
            r.q_max = p.q_max.load(std::memory_order_relaxed);
            r.q_last = p.q_last.load(std::memory_order_relaxed);
            r.switched = p.switched.load(std::memory_order_relaxed);
            r.last_end_ns = p.last_end_ns.load(std::memory_order_relaxed);
            r.histogram.bucket_width_ns = p.hist_width_ns.load(std::memory_order_relaxed);
            for (std::size_t b = 0; b < kHistogramBuckets; ++b)
                r.histogram.counts[b] = p.hist[b].load(std::memory_order_relaxed);
            for (std::size_t b = 0; b < kTimeBuckets; ++b) {
                r.lateness.counts[b] = p.lateness[b].load(std::memory_order_relaxed);
                r.cycle_time.counts[b] = p.cycle_time[b].load(std::memory_order_relaxed);
            }
        });
        r.consistent = info_ok && prof_ok;
        std::atomic_thread_fence(std::memory_order_acquire);
        if (s->generation.load(std::memory_order_relaxed) == gen &&
            s->in_use.load(std::memory_order_relaxed) != 0)
            return r;
    }
    return std::nullopt;  // claimed and released faster than we can read: skip
}

std::vector<TaskStatus> snapshot_of(const StatusHeader* h, std::int64_t now_ns) {
    std::vector<TaskStatus> out;
    std::vector<RtpuEpoch> epochs(h->rtpus);
    for (std::uint32_t r = 0; r < h->rtpus; ++r) epochs[r] = read_rtpu(h, static_cast<int>(r));
    for (std::uint32_t i = 0; i < h->max_tasks; ++i) {
        auto raw = read_slot(h, i);
        if (!raw) continue;
        const auto r = static_cast<std::uint32_t>(raw->rtpu);
        out.push_back(derive(*raw, r < epochs.size() ? epochs[r] : RtpuEpoch{}, now_ns));
    }
    return out;
}

StatusHeader* header_of(const ipc::Segment& s) noexcept {
    return s.valid() ? static_cast<StatusHeader*>(s.base()) : nullptr;
}

void validate_body(const ipc::Segment& s) {
    const StatusHeader* h = header_of(s);
    const std::size_t need = sizeof(StatusHeader) + std::size_t{h->rtpus} * sizeof(RtpuBlock) +
                             std::size_t{h->max_tasks} * sizeof(TaskSlotData);
    if (h->rtpus == 0 || h->rtpus > kMaxRtpus || s.size() < need ||
        h->rtpu_blocks.value + h->rtpus * sizeof(RtpuBlock) > s.size() ||
        h->slots.value + std::size_t{h->max_tasks} * sizeof(TaskSlotData) > s.size())
        throw StatusError("status segment " + s.name() + ": inconsistent layout (" +
                          std::to_string(h->rtpus) + " RTPUs, " + std::to_string(h->max_tasks) +
                          " slots in " + std::to_string(s.size()) + " bytes)");
}

}  // namespace

// ---------------------------------------------------------------------------

const char* to_string(TaskState state) noexcept {
    switch (state) {
        case TaskState::not_created: return "NOT-CREATED";
        case TaskState::off: return "OFF";
        case TaskState::on: return "ON";
        case TaskState::error: return "ERROR";
        case TaskState::spawning: return "SPAWNING";
        case TaskState::killing: return "KILLING";
    }
    return "?";
}

const char* to_string(Accounting accounting) noexcept {
    return accounting == Accounting::half_tick ? "half-tick" : "ns";
}

const char* to_string(CpuClock clock) noexcept {
    switch (clock) {
        case CpuClock::none: return "none";
        case CpuClock::perf_switch: return "perf-page";
        case CpuClock::thread_cputime: return "thread-cputime";
    }
    return "?";
}

// --------------------------------------------------------------- Histogram

std::uint64_t Histogram::total() const noexcept {
    std::uint64_t n = 0;
    for (auto c : counts) n += c;
    return n;
}

double Histogram::psi(std::size_t bucket) const noexcept {
    const std::uint64_t n = total();
    if (n == 0) return 0.0;
    std::uint64_t below = 0;
    for (std::size_t i = 0; i <= bucket && i < counts.size(); ++i) below += counts[i];
    return static_cast<double>(below) / static_cast<double>(n);
}

std::optional<std::uint64_t> Histogram::effective_ns(double hardness) const noexcept {
    const std::uint64_t n = total();
    if (n == 0 || bucket_width_ns == 0 || !(hardness > 0.0) || hardness > 1.0) return std::nullopt;
    std::uint64_t below = 0;
    // Ψ(t) >= H  <=>  below >= H*n; compared in integers where H*n is exact enough.
    for (std::size_t i = 0; i + 1 < counts.size(); ++i) {
        below += counts[i];
        if (static_cast<double>(below) >= hardness * static_cast<double>(n) - 1e-9)
            return (i + 1) * bucket_width_ns;
    }
    return std::nullopt;
}

// ------------------------------------------------------------ TimeHistogram

std::uint64_t TimeHistogram::total() const noexcept {
    std::uint64_t n = 0;
    for (auto c : counts) n += c;
    return n;
}

std::optional<std::uint64_t> TimeHistogram::percentile_ns(std::uint32_t ppm) const noexcept {
    const std::uint64_t n = total();
    if (n == 0) return std::nullopt;
    // rank = ceil(ppm * n / 1e6) in integers (exact: no 0.99 * 100 = 99.000001),
    // split so that nothing overflows for any n.
    constexpr std::uint64_t kMillion = 1'000'000;
    const std::uint64_t q = std::min<std::uint64_t>(ppm, kMillion);
    std::uint64_t rank = n / kMillion * q + (n % kMillion * q + kMillion - 1) / kMillion;
    if (rank == 0) rank = 1;
    std::uint64_t seen = 0;
    for (std::size_t b = 0; b < kTimeBuckets; ++b) {
        seen += counts[b];
        if (seen >= rank) return time_bucket_high(b);
    }
    return std::nullopt;  // unreachable: seen reaches n >= rank
}

std::optional<std::uint64_t> TimeHistogram::max_ns() const noexcept {
    for (std::size_t b = kTimeBuckets; b-- > 0;)
        if (counts[b] != 0) return time_bucket_high(b);
    return std::nullopt;
}

TimeHistogram TimeHistogram::since(const TimeHistogram& now, const TimeHistogram& base) noexcept {
    TimeHistogram d;
    for (std::size_t b = 0; b < kTimeBuckets; ++b)
        d.counts[b] = now.counts[b] >= base.counts[b] ? now.counts[b] - base.counts[b] : 0;
    return d;
}

// ------------------------------------------------------------------ derive

TaskStatus derive(const RawSlot& raw, const RtpuEpoch& rtpu, std::int64_t now_ns) {
    TaskStatus t;
    t.slot = raw.index;
    t.rmod = raw.rmod;
    t.rtpu = raw.rtpu;
    t.cpu = raw.cpu;
    t.tid = raw.tid;
    t.type = raw.type;
    t.crit = raw.crit;
    t.state = raw.state;
    t.ref_f = raw.ref_f;
    t.ref_t = raw.ref_f > 0 ? 1.0 / raw.ref_f : 0.0;
    t.policy = raw.policy;
    t.inputs = raw.inputs;
    t.outputs = raw.outputs;
    t.cpu_clock = raw.cpu_clock;
    t.consistent = raw.consistent;
    t.error = raw.has_error ? raw.error : std::string();
    if (raw.warn_epoch == rtpu.status_epoch) {
        t.warn = raw.warnings;
        t.warning = raw.warning;
    }

    t.reset_pending = raw.epoch_seen != rtpu.epoch;
    // Counters belong to the RTPU's current epoch only once the task has seen it.
    const Accounting acc = t.reset_pending ? rtpu.accounting : raw.accounting;
    t.accounting = acc;
    const bool half = acc == Accounting::half_tick;
    const std::int64_t tick_ns = half ? std::max<std::int64_t>(rtpu.tick_ns, 1) : 1;
    t.tick = static_cast<double>(tick_ns) * 1e-9;

    // ptime: Q_total ticks (half-tick mode) or ns.
    const std::int64_t elapsed = std::max<std::int64_t>(now_ns - rtpu.start_ns, 0);
    const std::int64_t q_total_res = elapsed / tick_ns;  // in resolution units
    t.ptime = static_cast<double>(q_total_res) * t.tick;

    t.histogram.bucket_width_ns = raw.histogram.bucket_width_ns;
    t.rtpu_name = rtpu.name;
    if (t.reset_pending) return t;

    t.cycle = raw.cycles;
    t.miss = raw.misses;
    t.accounted = raw.accounted;
    t.switched = raw.switched;
    t.histogram = raw.histogram;
    t.lateness = raw.lateness;
    t.cycle_time = raw.cycle_time;

    const double unit_s = static_cast<double>(raw.unit_num) /
                          static_cast<double>(raw.unit_den > 0 ? raw.unit_den : 1) * 1e-9;
    t.tot_c = static_cast<double>(raw.q_total) * unit_s;
    t.last_c = static_cast<double>(raw.q_last) * unit_s;
    if (raw.accounted > 0) {
        t.min_c = static_cast<double>(raw.q_min) * unit_s;
        t.max_c = static_cast<double>(raw.q_max) * unit_s;
        // The dropped first cycle is not in q_t, so it is not in the divisor either.
        t.avg_c = static_cast<double>(raw.q_total) / static_cast<double>(raw.accounted) * unit_s;
    }
    if (t.ptime > 0) t.mez_f = static_cast<double>(raw.cycles) / t.ptime;
    const std::uint64_t n = raw.cycles + raw.misses;
    if (n > 0 && q_total_res > 0) {
        // Nearest multiple of the resolution, halves rounded up.
        const auto q = static_cast<std::uint64_t>(q_total_res);
        const std::uint64_t periods = (2 * q + n) / (2 * n);
        t.mez_t = static_cast<double>(periods) * t.tick;
    }
    // Utilisation per cycle against the reference period (measured mean
    // period for aperiodic tasks).
    double period = t.ref_t;
    if (period <= 0 && raw.cycles > 0 && t.ptime > 0)
        period = t.ptime / static_cast<double>(raw.cycles);
    if (period > 0) {
        t.min_u = t.min_c / period * 100.0;
        t.max_u = t.max_c / period * 100.0;
        t.avg_u = t.avg_c / period * 100.0;
    }
    return t;
}

namespace {

// Whether `base` starts a window of `now`: the same task, the same epoch, and
// nothing went backwards (which a reset would do).
bool window_base_usable(const RawSlot& now, const RawSlot& base, const RtpuEpoch& rtpu) noexcept {
    return base.generation == now.generation && base.epoch_seen == now.epoch_seen &&
           now.epoch_seen == rtpu.epoch && base.cycles <= now.cycles && base.misses <= now.misses &&
           base.accounted <= now.accounted && base.q_total <= now.q_total;
}

}  // namespace

TaskStatus derive_window(const RawSlot& now, const RawSlot* base, std::int64_t base_ns,
                         const RtpuEpoch& rtpu, std::int64_t now_ns) {
    if (base == nullptr || !window_base_usable(now, *base, rtpu)) return derive(now, rtpu, now_ns);
    RawSlot d = now;
    d.cycles -= base->cycles;
    d.misses -= base->misses;
    d.accounted -= base->accounted;
    d.q_total -= base->q_total;
    d.switched = d.switched >= base->switched ? d.switched - base->switched : 0;
    if (base->warn_epoch == now.warn_epoch) {
        d.warnings = now.warnings >= base->warnings ? now.warnings - base->warnings : 0;
        if (d.warnings == 0) d.warning.clear();
    }
    if (base->histogram.bucket_width_ns == now.histogram.bucket_width_ns)
        for (std::size_t b = 0; b < kHistogramBuckets; ++b)
            d.histogram.counts[b] = now.histogram.counts[b] >= base->histogram.counts[b]
                                        ? now.histogram.counts[b] - base->histogram.counts[b]
                                        : 0;
    d.lateness = TimeHistogram::since(now.lateness, base->lateness);
    d.cycle_time = TimeHistogram::since(now.cycle_time, base->cycle_time);
    RtpuEpoch window = rtpu;
    window.start_ns = std::max(rtpu.start_ns, base_ns);
    TaskStatus t = derive(d, window, now_ns);
    t.windowed = true;
    return t;
}

// ----------------------------------------------------------------- TaskSlot

std::uint32_t TaskSlot::index() const noexcept {
    return static_cast<std::uint32_t>(slot_ - slot_at(header_, 0));
}
int TaskSlot::rtpu() const noexcept { return slot_->rtpu; }

void TaskSlot::info_begin() noexcept {
    auto& d = slot_->info.depth;
    const std::int32_t depth = d.load(std::memory_order_relaxed);
    d.store(depth + 1, std::memory_order_relaxed);
    std::atomic_signal_fence(std::memory_order_seq_cst);
    if (depth == 0) detail::write_begin(slot_->info.seq);
}

void TaskSlot::info_end() noexcept {
    auto& d = slot_->info.depth;
    const std::int32_t depth = d.load(std::memory_order_relaxed) - 1;
    if (depth == 0) detail::write_end(slot_->info.seq);
    std::atomic_signal_fence(std::memory_order_seq_cst);
    d.store(depth, std::memory_order_relaxed);
}

void TaskSlot::set_tid(int tid) noexcept {
    info_begin();
    slot_->info.tid.store(tid, std::memory_order_relaxed);
    info_end();
}

void TaskSlot::set_state(TaskState state) noexcept {
    info_begin();
    slot_->info.state.store(static_cast<std::uint32_t>(state), std::memory_order_relaxed);
    info_end();
}

void TaskSlot::set_crit(int crit) noexcept {
    info_begin();
    slot_->info.crit.store(crit, std::memory_order_relaxed);
    info_end();
}

void TaskSlot::set_ref_freq(double hz) noexcept {
    info_begin();
    slot_->info.ref_freq_bits.store(std::bit_cast<std::uint64_t>(hz), std::memory_order_relaxed);
    info_end();
}

void TaskSlot::set_policy(std::string_view policy) noexcept {
    info_begin();
    copy_string(slot_->info.policy, kPolicyMax, policy);
    info_end();
}

void TaskSlot::warning(std::string_view message) noexcept {
    const std::uint32_t epoch =
        rtpu_block(header_, slot_->rtpu)->status_epoch.load(std::memory_order_acquire);
    InfoData& in = slot_->info;
    info_begin();
    if (in.warn_epoch.load(std::memory_order_relaxed) != epoch) {
        in.warn_epoch.store(epoch, std::memory_order_relaxed);
        in.warnings.store(0, std::memory_order_relaxed);
        in.warning[0] = '\0';
    }
    const std::uint32_t n = in.warnings.load(std::memory_order_relaxed);
    if (n == 0) copy_string(in.warning, kMessageMax, message);
    in.warnings.store(n + 1, std::memory_order_relaxed);
    info_end();
}

void TaskSlot::error(std::string_view message) noexcept {
    info_begin();
    copy_string(slot_->info.error, kMessageMax, message);
    slot_->info.has_error.store(1, std::memory_order_relaxed);
    info_end();
}

void TaskSlot::clear_error() noexcept {
    info_begin();
    slot_->info.has_error.store(0, std::memory_order_relaxed);
    slot_->info.error[0] = '\0';
    info_end();
}

// ------------------------------------------------------------ StatusSegment

StatusSegment::~StatusSegment() { close(); }

StatusSegment& StatusSegment::operator=(StatusSegment&& other) noexcept {
    if (this != &other) {
        close();
        segment_ = std::move(other.segment_);
    }
    return *this;
}

void StatusSegment::close() noexcept {
    if (!segment_.valid()) return;
    if (segment_.creator()) {
        // The subsystem is going away: readers keep their mapping but see it
        // destroyed, and the name is freed for a restart.
        const std::string name = segment_.name();
        segment_.header().state.store(static_cast<std::uint32_t>(ipc::SegmentState::destroyed),
                                      std::memory_order_release);
        ipc::Segment::unlink(name);
    }
    segment_.detach();
}

StatusSegment StatusSegment::create(std::string_view subsystem, std::uint32_t max_tasks,
                                    const StatusOptions& options) {
    const std::string name = ipc::segment_name(subsystem, "status");
    std::uint32_t rtpus = options.rtpus;
    if (rtpus == 0) {
        const long online = sysconf(_SC_NPROCESSORS_ONLN);
        rtpus = online > 0 ? static_cast<std::uint32_t>(online) : 1;
    }
    if (rtpus > kMaxRtpus)
        throw StatusError("status segment " + name + ": " + std::to_string(rtpus) +
                          " RTPUs, at most " + std::to_string(kMaxRtpus));
    if (max_tasks == 0) throw StatusError("status segment " + name + ": max_tasks is 0");
    if (options.accounting == Accounting::half_tick && options.tick_ns <= 0)
        throw StatusError("status segment " + name + ": half-tick accounting needs a tick > 0");
    if (subsystem.size() >= kSubsystemMax)
        throw StatusError("status segment " + name + ": subsystem name longer than " +
                          std::to_string(kSubsystemMax - 1));

    if (options.replace_stale && ipc::Segment::exists(name)) {
        // Left by a subsystem that died? Its creator's pid tells.
        bool stale = true;
        try {
            ipc::AttachOptions ao;
            ao.prefault = false;
            ao.ready_timeout_ns = 50'000'000;
            ipc::Segment old = ipc::Segment::attach(name, kKind, ao);
            const int pid = old.header().creator_pid;
            stale = !(pid > 0 && (kill(pid, 0) == 0 || errno == EPERM));
            if (!stale)
                throw StatusError("status segment " + name + " exists and its creator (pid " +
                                  std::to_string(pid) + ") is running");
        } catch (const ipc::SegmentError&) {
            stale = true;  // unreadable or half-built: nobody can use it
        }
        if (stale) ipc::Segment::unlink(name);
    }

    const std::size_t rtpu_off = sizeof(StatusHeader);
    const std::size_t slots_off = ipc::align_up(rtpu_off + rtpus * sizeof(RtpuBlock), 64);
    const std::size_t size = slots_off + std::size_t{max_tasks} * sizeof(TaskSlotData);
    ipc::CreateOptions co;
    co.mode = options.mode;
    ipc::Segment seg = ipc::Segment::create(name, size, kKind, co);
    auto* h = static_cast<StatusHeader*>(seg.base());
    h->max_tasks = max_tasks;
    h->rtpus = rtpus;
    h->rtpu_blocks.value = rtpu_off;
    h->slots.value = slots_off;
    copy_string(h->subsystem, kSubsystemMax, subsystem);
    const std::int64_t now = ipc::now_ns();
    for (std::uint32_t r = 0; r < rtpus; ++r) {
        RtpuBlock* b = rtpu_block(h, static_cast<int>(r));
        b->epoch.store(1, std::memory_order_relaxed);
        b->status_epoch.store(1, std::memory_order_relaxed);
        b->start_ns.store(now, std::memory_order_relaxed);
        b->tick_ns.store(options.accounting == Accounting::half_tick ? options.tick_ns : 1,
                         std::memory_order_relaxed);
        b->accounting.store(static_cast<std::uint32_t>(options.accounting),
                            std::memory_order_relaxed);
        b->cpu = r < options.rtpu_cpus.size() ? options.rtpu_cpus[r] : -1;
        copy_string(b->name, kNameMax, r < options.rtpu_names.size() ? options.rtpu_names[r] : "");
    }
    seg.publish();
    return StatusSegment(std::move(seg));
}

StatusSegment StatusSegment::attach(std::string_view subsystem) {
    ipc::Segment seg = ipc::Segment::attach(ipc::segment_name(subsystem, "status"), kKind);
    validate_body(seg);
    return StatusSegment(std::move(seg));
}

StatusHeader* StatusSegment::header() const noexcept { return header_of(segment_); }
std::uint32_t StatusSegment::max_tasks() const noexcept { return header()->max_tasks; }
std::uint32_t StatusSegment::rtpus() const noexcept { return header()->rtpus; }

TaskSlot StatusSegment::claim(const TaskIdentity& id) {
    StatusHeader* h = header();
    const std::string where = "status segment " + name() + ", task " + std::string(id.rmod);
    check_rtpu(h, id.rtpu, where);
    if (id.rmod.empty()) throw StatusError("status segment " + name() + ": task without an rmod name");
    HeaderLock lock(h, where);
    for (std::uint32_t i = 0; i < h->max_tasks; ++i) {
        TaskSlotData* s = slot_at(h, i);
        if (s->in_use.load(std::memory_order_relaxed) != 0) continue;
        s->generation.fetch_add(1, std::memory_order_relaxed);
        s->rtpu = id.rtpu;
        s->cpu = id.cpu;
        s->type = static_cast<std::uint32_t>(static_cast<unsigned char>(id.type));
        copy_string(s->rmod, kNameMax, id.rmod);
        copy_string(s->inputs, kVarListMax, id.inputs);
        copy_string(s->outputs, kVarListMax, id.outputs);

        const std::uint32_t epoch =
            rtpu_block(h, id.rtpu)->status_epoch.load(std::memory_order_relaxed);
        InfoData& in = s->info;
        detail::write_begin(in.seq);
        in.depth.store(0, std::memory_order_relaxed);
        in.tid.store(0, std::memory_order_relaxed);
        in.state.store(static_cast<std::uint32_t>(TaskState::not_created), std::memory_order_relaxed);
        in.crit.store(id.crit, std::memory_order_relaxed);
        in.ref_freq_bits.store(std::bit_cast<std::uint64_t>(id.ref_freq), std::memory_order_relaxed);
        in.warn_epoch.store(epoch, std::memory_order_relaxed);
        in.warnings.store(0, std::memory_order_relaxed);
        in.has_error.store(0, std::memory_order_relaxed);
        in.policy[0] = in.warning[0] = in.error[0] = '\0';
        detail::write_end(in.seq);

        const RtpuEpoch e = read_rtpu(h, id.rtpu);
        ProfileData& p = s->profile;
        detail::write_begin(p.seq);
        p.epoch_seen.store(e.epoch, std::memory_order_relaxed);
        p.cpu_clock.store(static_cast<std::uint32_t>(CpuClock::none), std::memory_order_relaxed);
        p.accounting.store(static_cast<std::uint32_t>(e.accounting), std::memory_order_relaxed);
        p.unit_num.store(e.accounting == Accounting::half_tick ? e.tick_ns : 1, std::memory_order_relaxed);
        p.unit_den.store(e.accounting == Accounting::half_tick ? 2 : 1, std::memory_order_relaxed);
        p.cycles.store(0, std::memory_order_relaxed);
        p.misses.store(0, std::memory_order_relaxed);
        p.accounted.store(0, std::memory_order_relaxed);
        p.q_total.store(0, std::memory_order_relaxed);
        p.q_min.store(UINT64_MAX, std::memory_order_relaxed);
        p.q_max.store(0, std::memory_order_relaxed);
        p.q_last.store(0, std::memory_order_relaxed);
        p.switched.store(0, std::memory_order_relaxed);
        p.last_end_ns.store(0, std::memory_order_relaxed);
        p.hist_width_ns.store(0, std::memory_order_relaxed);
        for (auto& b : p.hist) b.store(0, std::memory_order_relaxed);
        for (auto& b : p.lateness) b.store(0, std::memory_order_relaxed);
        for (auto& b : p.cycle_time) b.store(0, std::memory_order_relaxed);
        detail::write_end(p.seq);

        s->in_use.store(1, std::memory_order_release);
        s->generation.fetch_add(1, std::memory_order_release);
        h->generation.fetch_add(1, std::memory_order_release);
        return TaskSlot(h, s);
    }
    throw StatusError(where + ": all " + std::to_string(h->max_tasks) + " task slots are in use");
}

void StatusSegment::release(TaskSlot& slot) {
    if (!slot.valid()) return;
    StatusHeader* h = header();
    HeaderLock lock(h, "status segment " + name());
    slot.slot_->in_use.store(0, std::memory_order_release);
    slot.slot_->generation.fetch_add(1, std::memory_order_release);
    h->generation.fetch_add(1, std::memory_order_release);
    slot = TaskSlot();
}

void StatusSegment::reset_all() {
    StatusHeader* h = header();
    HeaderLock lock(h, "status segment " + name());
    for (std::uint32_t r = 0; r < h->rtpus; ++r) bump_epoch(h, static_cast<int>(r), nullptr, nullptr);
}

void StatusSegment::reset_rtpu(int rtpu) {
    StatusHeader* h = header();
    check_rtpu(h, rtpu, "status segment " + name());
    HeaderLock lock(h, "status segment " + name());
    bump_epoch(h, rtpu, nullptr, nullptr);
}

void StatusSegment::set_accounting(int rtpu, Accounting accounting, std::int64_t tick_ns) {
    set_rtpu_accounting(header(), name(), rtpu, accounting, tick_ns);
}

std::vector<TaskStatus> StatusSegment::snapshot() const { return snapshot(ipc::now_ns()); }
std::vector<TaskStatus> StatusSegment::snapshot(std::int64_t now_ns) const {
    return snapshot_of(header(), now_ns);
}

// ------------------------------------------------------------- StatusReader

namespace {

// The status segment of `subsystem` as a reader (attach) or a watcher (watch).
ipc::Segment map_status(std::string_view subsystem, bool watcher, std::int64_t ready_timeout_ns) {
    ipc::AttachOptions ao;
    ao.prefault = false;
    ao.ready_timeout_ns = ready_timeout_ns;
    const std::string name = ipc::segment_name(subsystem, "status");
    ipc::Segment seg = watcher ? ipc::Segment::watch(name, kKind, ao) : ipc::Segment::attach(name, kKind, ao);
    validate_body(seg);
    return seg;
}

}  // namespace

StatusReader StatusReader::attach(std::string_view subsystem) {
    return StatusReader(map_status(subsystem, false, ipc::AttachOptions{}.ready_timeout_ns));
}

StatusReader StatusReader::watch(std::string_view subsystem) {
    return StatusReader(map_status(subsystem, true, ipc::AttachOptions{}.ready_timeout_ns));
}

std::optional<StatusReader> StatusReader::try_attach(std::string_view subsystem) {
    const std::string name = ipc::segment_name(subsystem, "status");
    if (!ipc::Segment::exists(name)) return std::nullopt;
    try {
        return StatusReader(map_status(subsystem, false, 100'000'000));
    } catch (const ipc::SegmentError&) {
        return std::nullopt;  // being built or destroyed: try again later
    }
}

std::optional<StatusReader> StatusReader::try_attach(std::string_view subsystem, int& error_number,
                                                     std::string& why) {
    return try_map(subsystem, false, error_number, why);
}

std::optional<StatusReader> StatusReader::try_watch(std::string_view subsystem, int& error_number,
                                                    std::string& why) {
    return try_map(subsystem, true, error_number, why);
}

std::optional<StatusReader> StatusReader::try_map(std::string_view subsystem, bool watcher, int& error_number,
                                                  std::string& why) {
    error_number = 0;
    why.clear();
    try {
        // No exists() first: it cannot tell a segment this user may not open from none.
        return StatusReader(map_status(subsystem, watcher, 100'000'000));
    } catch (const ipc::SegmentError& e) {
        error_number = e.error_number();
        why = e.what();
    } catch (const StatusError& e) {
        why = e.what();
    }
    return std::nullopt;
}

void StatusReader::check_writable(const char* what) const {
    if (segment_.read_only())
        throw StatusError("status segment " + name() + ": permission denied: " + what +
                          " changes what every reader sees, and this reader only watches (read-only); " +
                          ipc::permission_advice(name(), true));
}

std::vector<TaskStatus> StatusReader::snapshot() const { return snapshot(ipc::now_ns()); }
std::vector<TaskStatus> StatusReader::snapshot(std::int64_t now_ns) const {
    return snapshot_of(header_of(segment_), now_ns);
}

std::optional<RawSlot> StatusReader::raw(std::uint32_t index) const {
    const StatusHeader* h = header_of(segment_);
    if (index >= h->max_tasks) return std::nullopt;
    return read_slot(h, index);
}

RtpuEpoch StatusReader::rtpu_epoch(int rtpu) const {
    const StatusHeader* h = header_of(segment_);
    check_rtpu(h, rtpu, "status segment " + name());
    return read_rtpu(h, rtpu);
}

std::vector<TaskStatus> StatusReader::status_and_reset() {
    auto s = snapshot();
    reset_all();
    return s;
}

void StatusReader::reset_all() {
    check_writable("a reset");
    StatusHeader* h = header_of(segment_);
    HeaderLock lock(h, "status segment " + name());
    for (std::uint32_t r = 0; r < h->rtpus; ++r) bump_epoch(h, static_cast<int>(r), nullptr, nullptr);
}

void StatusReader::reset_rtpu(int rtpu) {
    check_writable("a reset");
    StatusHeader* h = header_of(segment_);
    check_rtpu(h, rtpu, "status segment " + name());
    HeaderLock lock(h, "status segment " + name());
    bump_epoch(h, rtpu, nullptr, nullptr);
}

void StatusReader::set_accounting(int rtpu, Accounting accounting, std::int64_t tick_ns) {
    check_writable("changing the accounting");
    set_rtpu_accounting(header_of(segment_), name(), rtpu, accounting, tick_ns);
}

// ------------------------------------------------------------- StatusWindow

namespace {

// Every RTPU's epoch, then every slot (free slots nullopt). The epochs first:
// a slot read after a reset shows the reset (its epoch moved past the one
// read here) rather than a window across it.
struct Reading {
    std::vector<RtpuEpoch> epochs;
    std::vector<std::optional<RawSlot>> slots;
};

Reading read_all(const StatusReader& reader) {
    Reading g;
    g.epochs.resize(reader.rtpus());
    for (std::uint32_t r = 0; r < g.epochs.size(); ++r) g.epochs[r] = reader.rtpu_epoch(static_cast<int>(r));
    g.slots.resize(reader.max_tasks());
    for (std::uint32_t i = 0; i < g.slots.size(); ++i) g.slots[i] = reader.raw(i);
    return g;
}

std::vector<TaskStatus> derive_all(const Reading& g, const std::vector<std::optional<RawSlot>>& base,
                                   std::int64_t base_ns, std::int64_t now_ns) {
    std::vector<TaskStatus> out;
    for (std::uint32_t i = 0; i < g.slots.size(); ++i) {
        if (!g.slots[i]) continue;
        const auto r = static_cast<std::uint32_t>(g.slots[i]->rtpu);
        const RawSlot* b = i < base.size() && base[i] ? &*base[i] : nullptr;
        out.push_back(derive_window(*g.slots[i], b, base_ns, r < g.epochs.size() ? g.epochs[r] : RtpuEpoch{}, now_ns));
    }
    return out;
}

}  // namespace

std::vector<TaskStatus> StatusWindow::snapshot(const StatusReader& reader) const {
    return snapshot(reader, ipc::now_ns());
}

std::vector<TaskStatus> StatusWindow::snapshot(const StatusReader& reader, std::int64_t now_ns) const {
    return derive_all(read_all(reader), base_, started_ns_, now_ns);
}

void StatusWindow::restart(const StatusReader& reader) { restart(reader, ipc::now_ns()); }

void StatusWindow::restart(const StatusReader& reader, std::int64_t now_ns) {
    base_ = read_all(reader).slots;
    started_ns_ = now_ns;
}

std::vector<TaskStatus> StatusWindow::take(const StatusReader& reader) {
    // One reading serves both: a cycle is in the window shown or in the next, never lost.
    const std::int64_t now = ipc::now_ns();
    Reading g = read_all(reader);
    std::vector<TaskStatus> shown = derive_all(g, base_, started_ns_, now);
    base_ = std::move(g.slots);
    started_ns_ = now;
    return shown;
}

bool StatusReader::alive() const noexcept {
    if (!segment_.valid()) return false;
    const auto& hdr = segment_.header();
    if (hdr.state.load(std::memory_order_acquire) !=
        static_cast<std::uint32_t>(ipc::SegmentState::ready))
        return false;
    const int pid = hdr.creator_pid;
    return pid > 0 && (kill(pid, 0) == 0 || errno == EPERM);
}

std::int64_t StatusReader::created_ns() const noexcept {
    return segment_.valid() ? static_cast<std::int64_t>(segment_.header().created_ns) : 0;
}

int StatusReader::creator_pid() const noexcept {
    return segment_.valid() ? segment_.header().creator_pid : 0;
}

std::string StatusReader::subsystem() const {
    return read_string(header_of(segment_)->subsystem, kSubsystemMax);
}
std::uint32_t StatusReader::max_tasks() const noexcept { return header_of(segment_)->max_tasks; }
std::uint32_t StatusReader::rtpus() const noexcept { return header_of(segment_)->rtpus; }

}  // namespace chimera::prof
