// Tests of the prof service: §6.7 arithmetic (exact, with a chosen clock),
// the profiler against threads whose CPU use is controlled, reset and
// warning semantics, seqlock consistency across processes, system calls.
#include "syscall_counter.hpp"
#include "process.hpp"
#include "segment_guard.hpp"
#include <gtest/gtest.h>
#include <linux/perf_event.h>
#include <pthread.h>
#include <sched.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <csignal>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <string>
#include <thread>

#include "chimera/ipc/clock.hpp"
#include "chimera/prof.hpp"

using namespace chimera;
using namespace chimera::prof;

namespace {

std::string unique_subsystem(const char* tag) {
    static int n = 0;
    return std::string("proftest_") + tag + "_" + std::to_string(getpid()) + "_" + std::to_string(n++);
}

std::int64_t thread_cpu_ns() {
    timespec ts;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
    return ts.tv_sec * 1'000'000'000LL + ts.tv_nsec;
}

// Burns `ns` of this thread's own CPU time (not wall time).
void burn_cpu(std::int64_t ns) {
    const std::int64_t end = thread_cpu_ns() + ns;
    while (thread_cpu_ns() < end) {
    }
}

bool pin_to(int cpu) {
    cpu_set_t set;
    CPU_ZERO(&set);
    CPU_SET(cpu, &set);
    return pthread_setaffinity_np(pthread_self(), sizeof set, &set) == 0;
}

TaskIdentity id(std::string_view rmod, int rtpu, double ref_freq = 0) {
    TaskIdentity t;
    t.rmod = rmod;
    t.rtpu = rtpu;
    t.ref_freq = ref_freq;
    return t;
}

RtpuEpoch make_epoch(std::uint32_t epoch, std::uint32_t status_epoch, std::int64_t start_ns,
                     std::int64_t tick_ns, Accounting accounting) {
    RtpuEpoch e;
    e.epoch = epoch;
    e.status_epoch = status_epoch;
    e.start_ns = start_ns;
    e.tick_ns = tick_ns;
    e.accounting = accounting;
    return e;
}

StatusOptions one_rtpu() {
    StatusOptions o;
    o.rtpus = 1;
    return o;
}

RawSlot raw_with(std::uint64_t cycles, std::uint64_t misses, std::uint64_t q_total,
                 std::uint64_t q_min, std::uint64_t q_max) {
    RawSlot r;
    r.rmod = "t";
    r.epoch_seen = 7;
    r.cycles = cycles;
    r.misses = misses;
    r.accounted = cycles > 0 ? cycles - 1 : 0;
    r.q_total = q_total;
    r.q_min = q_min;
    r.q_max = q_max;
    return r;
}

}  // namespace

// ----------------------------------------------------------- pure arithmetic

TEST(HalfTicks, WholeTicksCountTwoPartialTickOne) {
    constexpr std::uint64_t ms = 1'000'000;
    static_assert(half_ticks(0, ms) == 0);
    EXPECT_EQ(half_ticks(1, ms), 1u);
    EXPECT_EQ(half_ticks(ms, ms), 2u);
    EXPECT_EQ(half_ticks(2 * ms, ms), 4u);
    EXPECT_EQ(half_ticks(2'300'000, ms), 5u);  // 2.3 ms and 2.7 ms are the same 2.5 ms
    EXPECT_EQ(half_ticks(2'700'000, ms), 5u);
    EXPECT_EQ(half_ticks(2 * ms + 1, ms), 5u);
    EXPECT_EQ(half_ticks(3 * ms - 1, ms), 5u);
}

TEST(Derive, NanosecondModeExact) {
    // 400 Hz task, profiled for exactly 1 s: 400 cycles, the first dropped.
    RawSlot r = raw_with(400, 0, 399 * 500'000ull, 400'000, 700'000);
    r.ref_f = 400;
    const RtpuEpoch e = make_epoch(7, 1, 1'000'000'000, 1, Accounting::nanoseconds);
    const TaskStatus t = derive(r, e, 2'000'000'000);
    EXPECT_FALSE(t.reset_pending);
    EXPECT_EQ(t.cycle, 400u);
    EXPECT_DOUBLE_EQ(t.ptime, 1.0);
    EXPECT_DOUBLE_EQ(t.mez_f, 400.0);
    EXPECT_DOUBLE_EQ(t.mez_t, 0.0025);
    EXPECT_DOUBLE_EQ(t.ref_t, 0.0025);
    EXPECT_DOUBLE_EQ(t.tick, 1e-9);
    EXPECT_NEAR(t.tot_c, 0.1995, 1e-12);
    EXPECT_NEAR(t.min_c, 400e-6, 1e-15);
    EXPECT_NEAR(t.max_c, 700e-6, 1e-15);
    EXPECT_NEAR(t.avg_c, 500e-6, 1e-15);  // q_t over the 399 accounted cycles
    EXPECT_NEAR(t.min_u, 16.0, 1e-9);      // 0.4 ms of a 2.5 ms period
    EXPECT_NEAR(t.max_u, 28.0, 1e-9);
    EXPECT_NEAR(t.avg_u, 20.0, 1e-9);
}

TEST(Derive, HalfTickModeReproducesThesisQuantisation) {
    // Tick 1 ms; 400 Hz cannot be a whole number of ticks: mezT is 2 or 3
    // ticks (§4.4.1), here ptime/(n_c+n_m) = 1000/400 = 2.5 rounds to 3.
    RawSlot r = raw_with(400, 0, 399 * 3ull, 3, 5);  // in half-ticks
    r.accounting = Accounting::half_tick;
    r.unit_num = 1'000'000;
    r.unit_den = 2;
    r.ref_f = 400;
    const RtpuEpoch e = make_epoch(7, 1, 0, 1'000'000, Accounting::half_tick);
    const TaskStatus t = derive(r, e, 1'000'400'000);  // 1000.4 ticks elapsed: Q_total = 1000
    EXPECT_DOUBLE_EQ(t.tick, 0.001);
    EXPECT_DOUBLE_EQ(t.ptime, 1.0);
    EXPECT_DOUBLE_EQ(t.mez_t, 0.003);
    EXPECT_DOUBLE_EQ(t.mez_f, 400.0);
    EXPECT_DOUBLE_EQ(t.min_c, 0.0015);
    EXPECT_DOUBLE_EQ(t.max_c, 0.0025);
    EXPECT_DOUBLE_EQ(t.avg_c, 0.0015);
    EXPECT_NEAR(t.tot_c, 399 * 0.0015, 1e-12);

    // 333 cycles and 1 miss in 1000 ticks: 1000/334 = 2.99 -> 3 ticks.
    RawSlot r2 = raw_with(333, 1, 0, UINT64_MAX, 0);
    r2.accounting = Accounting::half_tick;
    r2.unit_num = 1'000'000;
    r2.unit_den = 2;
    EXPECT_DOUBLE_EQ(derive(r2, e, 1'000'000'000).mez_t, 0.003);
    // 1000 ticks / 450 = 2.22 -> 2 ticks.
    RawSlot r3 = raw_with(450, 0, 0, UINT64_MAX, 0);
    r3.accounting = Accounting::half_tick;
    EXPECT_DOUBLE_EQ(derive(r3, e, 1'000'000'000).mez_t, 0.002);
}

TEST(Derive, MissesLowerTheMeasuredFrequencyButNotThePeriod) {
    RawSlot r = raw_with(90, 10, 0, UINT64_MAX, 0);
    r.ref_f = 100;
    const RtpuEpoch e = make_epoch(7, 1, 0, 1, Accounting::nanoseconds);
    const TaskStatus t = derive(r, e, 1'000'000'000);
    EXPECT_DOUBLE_EQ(t.mez_f, 90.0);
    EXPECT_DOUBLE_EQ(t.mez_t, 0.01);  // ptime / (n_c + n_m)
    EXPECT_EQ(t.miss, 10u);
}

TEST(Derive, PendingResetShowsZeroCountersAndNoWarning) {
    RawSlot r = raw_with(50, 3, 1000, 10, 30);
    r.warn_epoch = 7;
    r.warnings = 2;
    r.warning = "w";
    const RtpuEpoch e = make_epoch(8, 8, 0, 1, Accounting::nanoseconds);
    const TaskStatus t = derive(r, e, 1'000);
    EXPECT_TRUE(t.reset_pending);
    EXPECT_EQ(t.cycle, 0u);
    EXPECT_EQ(t.miss, 0u);
    EXPECT_EQ(t.tot_c, 0.0);
    EXPECT_EQ(t.warn, 0u);
    EXPECT_EQ(t.warning, "");
}

TEST(Derive, AperiodicUtilisationUsesTheMeasuredMeanPeriod) {
    RawSlot r = raw_with(11, 0, 10 * 1'000'000ull, 1'000'000, 1'000'000);  // 1 ms each
    const RtpuEpoch e = make_epoch(7, 1, 0, 1, Accounting::nanoseconds);
    const TaskStatus t = derive(r, e, 110'000'000);  // 11 events in 110 ms
    EXPECT_DOUBLE_EQ(t.ref_f, 0.0);
    EXPECT_NEAR(t.avg_u, 10.0, 1e-9);
}

TEST(HistogramTest, EffectiveExecutionTimeForAHardness) {
    Histogram h;
    h.bucket_width_ns = 1000;
    h.counts[0] = 10;
    h.counts[5] = 80;  // 90% within 6 us
    h.counts[9] = 10;  // all within 10 us (Figure 6.6's shape)
    EXPECT_EQ(h.total(), 100u);
    EXPECT_DOUBLE_EQ(h.psi(5), 0.9);
    EXPECT_EQ(h.effective_ns(0.9), 6000u);
    EXPECT_EQ(h.effective_ns(1.0), 10000u);  // E = C for a hard task
    EXPECT_EQ(h.effective_ns(0.05), 1000u);
    EXPECT_FALSE(h.effective_ns(0.0).has_value());
    h.counts[kHistogramBuckets - 1] = 100;  // half the cycles beyond the range
    EXPECT_FALSE(h.effective_ns(1.0).has_value());
    EXPECT_FALSE(Histogram{}.effective_ns(0.5).has_value());
}

// ------------------------------------------- lateness and cycle time (14.11)

TEST(TimeBuckets, ExactBelowSixteenThenSixteenPerOctave) {
    for (std::uint64_t v = 0; v < 16; ++v) {
        EXPECT_EQ(time_bucket(v), v);
        EXPECT_EQ(time_bucket_low(v), v);
        EXPECT_EQ(time_bucket_high(v), v);
    }
    // [16, 32): still one value per bucket; [32, 64): two; [1024, 2048): 64.
    EXPECT_EQ(time_bucket(16), 16u);
    EXPECT_EQ(time_bucket(31), 31u);
    EXPECT_EQ(time_bucket(32), 32u);
    EXPECT_EQ(time_bucket(33), 32u);
    EXPECT_EQ(time_bucket(34), 33u);
    EXPECT_EQ(time_bucket_low(32), 32u);
    EXPECT_EQ(time_bucket_high(32), 33u);
    EXPECT_EQ(time_bucket(1024), 16u + 6 * 16);
    EXPECT_EQ(time_bucket_low(16 + 6 * 16), 1024u);
    EXPECT_EQ(time_bucket_high(16 + 6 * 16), 1087u);
    EXPECT_EQ(time_bucket((1ull << 32) - 1), kTimeOverflowBucket - 1);
    EXPECT_EQ(time_bucket(1ull << 32), kTimeOverflowBucket);
    EXPECT_EQ(time_bucket(UINT64_MAX), kTimeOverflowBucket);
    EXPECT_EQ(time_bucket_high(kTimeOverflowBucket), UINT64_MAX);
    // The buckets tile [0, 2^32) without gaps or overlaps, each at most 1/16 of its low edge wide.
    for (std::size_t b = 0; b + 1 < kTimeOverflowBucket; ++b) {
        ASSERT_EQ(time_bucket_low(b + 1), time_bucket_high(b) + 1) << b;
        ASSERT_EQ(time_bucket(time_bucket_low(b)), b) << b;
        ASSERT_EQ(time_bucket(time_bucket_high(b)), b) << b;
        ASSERT_LE((time_bucket_high(b) - time_bucket_low(b) + 1) * 16, std::max<std::uint64_t>(time_bucket_low(b), 16)) << b;
    }
}

TEST(TimeHistogramTest, NearestRankPercentilesExact) {
    TimeHistogram h;
    EXPECT_FALSE(h.percentile_ns(500'000).has_value());
    EXPECT_FALSE(h.max_ns().has_value());
    for (std::uint64_t v = 1; v <= 100; ++v) ++h.counts[time_bucket(v)];
    EXPECT_EQ(h.total(), 100u);
    EXPECT_EQ(h.percentile_ns(0), 1u);          // the first sample
    EXPECT_EQ(h.percentile_ns(10'000), 1u);     // p1: rank 1
    EXPECT_EQ(h.percentile_ns(500'000), 51u);   // rank 50: 50 in [50, 51]
    EXPECT_EQ(h.percentile_ns(990'000), 99u);   // rank 99 exactly (not 100): [98, 99]
    EXPECT_EQ(h.percentile_ns(990'001), 103u);  // rank 100: [100, 103]
    EXPECT_EQ(h.percentile_ns(1'000'000), 103u);
    EXPECT_EQ(h.max_ns(), 103u);
    // 1000 samples of 1 us and 10 of 1 ms: p99 is still 1 us's bucket, p99.5 is 1 ms's.
    TimeHistogram t;
    t.counts[time_bucket(1000)] = 1000;
    t.counts[time_bucket(1'000'000)] = 10;
    EXPECT_EQ(t.percentile_ns(500'000), time_bucket_high(time_bucket(1000)));
    EXPECT_EQ(t.percentile_ns(990'000), time_bucket_high(time_bucket(1000)));  // rank 1000 of 1010
    EXPECT_EQ(t.percentile_ns(995'000), time_bucket_high(time_bucket(1'000'000)));
    EXPECT_GE(*t.percentile_ns(995'000), 1'000'000u);
    EXPECT_LE(*t.percentile_ns(995'000), 1'000'000u + 1'000'000u / 16);
    // A sample beyond the range: UINT64_MAX, never a made-up number.
    t.counts[kTimeOverflowBucket] = 1000;
    EXPECT_EQ(t.percentile_ns(990'000), UINT64_MAX);
    // Window differences, bucket by bucket.
    TimeHistogram base;
    base.counts[time_bucket(1000)] = 400;
    const TimeHistogram d = TimeHistogram::since(t, base);
    EXPECT_EQ(d.counts[time_bucket(1000)], 600u);
    EXPECT_EQ(d.counts[kTimeOverflowBucket], 1000u);
    EXPECT_EQ(d.total(), 1610u);
}

TEST(Profiler, RecordsLatenessAndCycleTimeOfEveryCycle) {
    auto seg = StatusSegment::create(unique_subsystem("lat"), 1, one_rtpu());
    TaskSlot slot = seg.claim(id("l", 0, 100));
    TaskProfiler p(slot);
    for (int i = 0; i < 7; ++i) {
        // Released 5 ms ago: a lateness of at least 5 ms (how much more depends on the machine).
        p.cycle_begin(ipc::now_ns() - 5'000'000);
        burn_cpu(200'000);
        p.cycle_end();
    }
    p.cycle_begin();  // no release instant (aperiodic): cycle time only
    p.cycle_end();
    const TaskStatus t = seg.snapshot()[0];
    EXPECT_EQ(t.cycle, 8u);
    EXPECT_EQ(t.cycle_time.total(), 8u) << "every cycle, the first after a reset too";
    EXPECT_EQ(t.lateness.total(), 7u) << "only cycles with a release instant";
    EXPECT_GE(*t.lateness.percentile_ns(0), 5'000'000u);
    EXPECT_GE(*t.cycle_time.percentile_ns(1'000'000), 200'000u) << "wall time >= the CPU time burnt";
    seg.reset_all();
    p.cycle_begin(ipc::now_ns());
    p.cycle_end();
    const TaskStatus after = seg.snapshot()[0];
    EXPECT_EQ(after.cycle_time.total(), 1u) << "a reset empties the histograms";
    EXPECT_EQ(after.lateness.total(), 1u);
}

// ---------------------------------------------- profiling windows per reader (16.4)

TEST(Window, DerivesTheDifferenceSinceTheBaseline) {
    RawSlot base = raw_with(100, 2, 99 * 1000, 500, 9000);
    base.generation = 4;
    base.warn_epoch = 1;
    base.warnings = 3;
    base.warning = "first";
    base.lateness.counts[time_bucket(2000)] = 90;
    base.cycle_time.counts[time_bucket(5000)] = 100;
    RawSlot now = raw_with(300, 5, 299 * 1000 + 200 * 10, 500, 9000);
    now.generation = 4;
    now.ref_f = 100;
    now.warn_epoch = 1;
    now.warnings = 3;
    now.warning = "first";
    now.lateness.counts[time_bucket(2000)] = 250;
    now.lateness.counts[time_bucket(80'000)] = 10;
    now.cycle_time.counts[time_bucket(5000)] = 300;
    const RtpuEpoch e = make_epoch(7, 1, 0, 1, Accounting::nanoseconds);
    // The window began at 1 s, the epoch at 0; now is 3 s.
    const TaskStatus t = derive_window(now, &base, 1'000'000'000, e, 3'000'000'000);
    EXPECT_TRUE(t.windowed);
    EXPECT_EQ(t.cycle, 200u);
    EXPECT_EQ(t.miss, 3u);
    EXPECT_EQ(t.accounted, 200u);
    EXPECT_DOUBLE_EQ(t.ptime, 2.0);
    EXPECT_DOUBLE_EQ(t.mez_f, 100.0);
    EXPECT_NEAR(t.avg_c, 1010e-9, 1e-15);  // (200 * 1000 + 200 * 10) ns over 200 cycles
    EXPECT_NEAR(t.max_c, 9000e-9, 1e-15) << "min/max stay the epoch's";
    EXPECT_EQ(t.warn, 0u);
    EXPECT_EQ(t.warning, "") << "no warning in this window";
    EXPECT_EQ(t.lateness.total(), 170u);
    EXPECT_EQ(t.lateness.counts[time_bucket(2000)], 160u);
    EXPECT_EQ(t.lateness.percentile_ns(990'000), time_bucket_high(time_bucket(80'000)));
    EXPECT_EQ(t.cycle_time.total(), 200u);

    // Not a window of this task, or across a reset: the counts since the reset.
    EXPECT_FALSE(derive_window(now, nullptr, 1'000'000'000, e, 3'000'000'000).windowed);
    RawSlot other = base;
    other.generation = 6;  // the slot was released and claimed by another task
    EXPECT_EQ(derive_window(now, &other, 1'000'000'000, e, 3'000'000'000).cycle, 300u);
    RawSlot old_epoch = base;
    old_epoch.epoch_seen = 6;
    EXPECT_EQ(derive_window(now, &old_epoch, 1'000'000'000, e, 3'000'000'000).cycle, 300u);
    const TaskStatus pending = derive_window(now, &base, 1'000'000'000, make_epoch(8, 2, 0, 1, Accounting::nanoseconds),
                                             3'000'000'000);
    EXPECT_FALSE(pending.windowed);
    EXPECT_TRUE(pending.reset_pending) << "the task has not seen `status reset` yet: zeros, not a window";
    EXPECT_EQ(pending.cycle, 0u);
}

TEST(Window, OneReaderRestartingItsWindowNeverLowersAnothersCounts) {
    const std::string sub = unique_subsystem("window");
    auto seg = StatusSegment::create(sub, 2, one_rtpu());
    TaskSlot slot = seg.claim(id("w", 0, 100));
    TaskProfiler p(slot);
    auto cycles = [&](int n) {
        for (int i = 0; i < n; ++i) {
            p.cycle_begin(ipc::now_ns());
            p.cycle_end();
        }
    };
    StatusReader chimtop = StatusReader::attach(sub);
    StatusReader prompt = StatusReader::attach(sub);
    StatusWindow chimtop_window, prompt_window;  // never restarted: since the reset
    cycles(10);
    EXPECT_EQ(chimtop_window.snapshot(chimtop)[0].cycle, 10u);
    // The prompt's `status`: shows its window and restarts it, for itself only.
    EXPECT_EQ(prompt_window.take(prompt)[0].cycle, 10u);
    cycles(5);
    EXPECT_EQ(prompt_window.snapshot(prompt)[0].cycle, 5u);
    EXPECT_EQ(prompt_window.snapshot(prompt)[0].cycle_time.total(), 5u);
    EXPECT_EQ(prompt_window.snapshot(prompt)[0].lateness.total(), 5u);
    const TaskStatus seen = chimtop_window.snapshot(chimtop)[0];
    EXPECT_EQ(seen.cycle, 15u) << "the other reader's counts did not fall";
    EXPECT_EQ(seen.cycle_time.total(), 15u);
    EXPECT_EQ(seen.lateness.total(), 15u);
    // chimtop's `z`: its own window only.
    chimtop_window.restart(chimtop);
    cycles(2);
    EXPECT_EQ(chimtop_window.snapshot(chimtop)[0].cycle, 2u);
    EXPECT_EQ(prompt_window.snapshot(prompt)[0].cycle, 7u);
    EXPECT_EQ(StatusWindow{}.snapshot(chimtop)[0].cycle, 17u);
    // `status reset`, the thesis's reset for everyone: every window shows since the reset.
    prompt.reset_all();
    cycles(3);
    EXPECT_EQ(chimtop_window.snapshot(chimtop)[0].cycle, 3u);
    EXPECT_EQ(prompt_window.snapshot(prompt)[0].cycle, 3u);
    EXPECT_FALSE(prompt_window.snapshot(prompt)[0].windowed);
}

TEST(Window, RtpuNamesAndCpusFromTheOptions) {
    const std::string sub = unique_subsystem("names");
    StatusOptions o;
    o.rtpus = 3;
    o.rtpu_names = {"ctrl", "robot"};
    o.rtpu_cpus = {1, 0};
    auto seg = StatusSegment::create(sub, 2, o);
    const TaskSlot a = seg.claim(id("pid", 1));
    EXPECT_EQ(a.rtpu(), 1);
    StatusReader r = StatusReader::attach(sub);
    EXPECT_EQ(r.rtpu_epoch(0).name, "ctrl");
    EXPECT_EQ(r.rtpu_epoch(0).cpu, 1);
    EXPECT_EQ(r.rtpu_epoch(1).name, "robot");
    EXPECT_EQ(r.rtpu_epoch(2).name, "");
    EXPECT_EQ(r.rtpu_epoch(2).cpu, -1);
    EXPECT_EQ(r.snapshot()[0].rtpu_name, "robot");
}

// A watcher (chimtop as a member of the watch group, issue 16.7): the same
// seqlocked reads and its own window, but no reset or accounting change: they
// would change what every reader sees, and its mapping is read-only.
TEST(Window, AWatcherReadsAndKeepsAWindowButResetsNothing) {
    const std::string sub = unique_subsystem("watch");
    auto seg = StatusSegment::create(sub, 2, one_rtpu());
    TaskSlot slot = seg.claim(id("w", 0, 100));
    TaskProfiler p(slot);
    for (int i = 0; i < 4; ++i) {
        p.cycle_begin(ipc::now_ns());
        p.cycle_end();
    }
    StatusReader watcher = StatusReader::watch(sub);
    EXPECT_TRUE(watcher.read_only());
    StatusWindow window;
    EXPECT_EQ(window.take(watcher)[0].cycle, 4u);
    const std::string denied = "status segment /chimera." + sub + ".status: permission denied: a reset changes what "
                               "every reader sees, and this reader only watches (read-only); permission denied: "
                               "/dev/shm/chimera." + sub + ".status is ";
    try {
        watcher.reset_all();
        ADD_FAILURE() << "a watcher reset every reader's counts";
    } catch (const StatusError& e) {
        EXPECT_EQ(std::string(e.what()).substr(0, denied.size()), denied);
    }
    EXPECT_THROW(watcher.reset_rtpu(0), StatusError);
    EXPECT_THROW(watcher.set_accounting(0, Accounting::half_tick, 1'000'000), StatusError);
    EXPECT_EQ(StatusWindow{}.snapshot(watcher)[0].cycle, 4u) << "nothing was reset";
}

// --------------------------------------------------------------- the segment

TEST(StatusSegmentTest, ClaimFillsIdentityAndRejectsBadInput) {
    const std::string sub = unique_subsystem("claim");
    StatusOptions o;
    o.rtpus = 2;
    auto seg = StatusSegment::create(sub, 2, o);
    TaskSlot a = seg.claim({"pid", 1, 1, TaskType::periodic, 100.0, 5, "q_ref,q_mez", "tau"});
    a.set_policy("SCHED_FIFO 80");
    a.set_state(TaskState::on);
    auto s = seg.snapshot();
    ASSERT_EQ(s.size(), 1u);
    EXPECT_EQ(s[0].rmod, "pid");
    EXPECT_EQ(s[0].rtpu, 1);
    EXPECT_EQ(s[0].type, 'P');
    EXPECT_EQ(s[0].crit, 5);
    EXPECT_DOUBLE_EQ(s[0].ref_f, 100.0);
    EXPECT_EQ(s[0].policy, "SCHED_FIFO 80");
    EXPECT_EQ(s[0].state, TaskState::on);
    EXPECT_EQ(s[0].inputs, "q_ref,q_mez");
    EXPECT_EQ(s[0].outputs, "tau");
    EXPECT_THROW(seg.claim(id("x", 2)), StatusError);  // RTPU out of range
    TaskSlot b = seg.claim(id("b", 0));
    try {
        seg.claim(id("c", 0));
        FAIL() << "third claim in a 2-slot segment";
    } catch (const StatusError& e) {
        EXPECT_NE(std::string(e.what()).find("all 2 task slots are in use"), std::string::npos)
            << e.what();
    }
    seg.release(b);
    EXPECT_FALSE(b.valid());
    EXPECT_EQ(seg.snapshot().size(), 1u);
    EXPECT_NO_THROW(seg.claim(id("c", 0)));
}

TEST(StatusSegmentTest, ReaderAttachesByNameAndSeesTheSubsystemGo) {
    const std::string sub = unique_subsystem("attach");
    EXPECT_FALSE(StatusReader::try_attach(sub).has_value());
    std::optional<StatusReader> reader;
    {
        auto seg = StatusSegment::create(sub, 4);
        EXPECT_THROW(StatusSegment::create(sub, 4), StatusError);  // creator alive
        reader = StatusReader::try_attach(sub);
        ASSERT_TRUE(reader.has_value());
        EXPECT_TRUE(reader->alive());
        EXPECT_EQ(reader->subsystem(), sub);
        EXPECT_EQ(reader->max_tasks(), 4u);
    }
    EXPECT_FALSE(reader->alive());
    EXPECT_FALSE(StatusReader::try_attach(sub).has_value());
    auto again = StatusSegment::create(sub, 4);  // restart under the same name
    auto r2 = StatusReader::try_attach(sub);
    ASSERT_TRUE(r2.has_value());
    EXPECT_NE(r2->created_ns(), reader->created_ns());
}

TEST(StatusSegmentTest, StaleSegmentOfADeadCreatorIsReplaced) {
    const std::string sub = unique_subsystem("stale");
    const pid_t child = fork();
    if (child == 0) {
        auto seg = StatusSegment::create(sub, 1);
        _exit(0);  // dies without destroying it
    }
    int st = 0;
    waitpid(child, &st, 0);
    ASSERT_TRUE(StatusReader::try_attach(sub).has_value());
    EXPECT_NO_THROW(StatusSegment::create(sub, 1));
}

TEST(WarningsAndErrors, FirstWarningKeptUntilReset) {
    auto seg = StatusSegment::create(unique_subsystem("warn"), 1, one_rtpu());
    TaskSlot t = seg.claim(id("w", 0));
    t.warning("first");
    t.warning("second");
    t.warning("third");
    auto s = seg.snapshot();
    EXPECT_EQ(s[0].warn, 3u);
    EXPECT_EQ(s[0].warning, "first");
    seg.reset_all();  // the status command displayed it
    s = seg.snapshot();
    EXPECT_EQ(s[0].warn, 0u);
    EXPECT_EQ(s[0].warning, "");
    t.warning("fourth");
    s = seg.snapshot();
    EXPECT_EQ(s[0].warn, 1u);
    EXPECT_EQ(s[0].warning, "fourth");

    t.error("cycle: division by zero");
    EXPECT_EQ(seg.snapshot()[0].error, "cycle: division by zero");
    seg.reset_all();
    EXPECT_EQ(seg.snapshot()[0].error, "cycle: division by zero");  // while in ERROR
    t.clear_error();
    EXPECT_EQ(seg.snapshot()[0].error, "");
    t.warning(std::string(500, 'x'));  // truncated, never overflowing
    EXPECT_EQ(seg.snapshot()[0].warning.size(), kMessageMax - 1);
}

// ------------------------------------------------------- the profiler itself

TEST(Profiler, CountsCyclesAndDropsTheFirstAfterAReset) {
    auto seg = StatusSegment::create(unique_subsystem("count"), 1, one_rtpu());
    TaskSlot slot = seg.claim(id("busy", 0, 100));
    std::thread th([&] {
        TaskProfiler p(slot);
        EXPECT_NE(p.clock(), CpuClock::none);
        p.cycle_begin();
        burn_cpu(40'000'000);  // the first cycle: long, must not reach maxC
        p.cycle_end();
        for (int i = 0; i < 5; ++i) {
            p.cycle_begin();
            burn_cpu(2'000'000);
            p.cycle_end();
        }
        p.missed(2);
    });
    th.join();
    auto s = seg.snapshot();
    ASSERT_EQ(s.size(), 1u);
    EXPECT_EQ(s[0].cycle, 6u);
    EXPECT_EQ(s[0].accounted, 5u);
    EXPECT_EQ(s[0].miss, 2u);
    // Each cycle burns 2 ms of its thread's CPU time: at least that is counted
    // (the CPU-time clock of the profiler may add the switches around it, many
    // on a loaded machine: bounds far from the 40 ms first cycle, not equalities).
    EXPECT_GE(s[0].min_c, 0.0019);
    EXPECT_LT(s[0].max_c, 0.020) << "the 40 ms first cycle was not dropped";
    EXPECT_GE(s[0].avg_c, 0.0019);
    EXPECT_GE(s[0].tot_c, 5 * 0.0019);
    EXPECT_LT(s[0].tot_c, 0.040) << "the first cycle is not in totC";
    EXPECT_NE(s[0].tid, 0);

    seg.reset_all();
    s = seg.snapshot();
    EXPECT_TRUE(s[0].reset_pending);
    EXPECT_EQ(s[0].cycle, 0u);
}

TEST(Profiler, ResetHonouredAtTheNextCycleAndFirstCycleDropped) {
    auto seg = StatusSegment::create(unique_subsystem("reset"), 1, one_rtpu());
    TaskSlot slot = seg.claim(id("r", 0));
    TaskProfiler p(slot);  // this thread is the task
    for (int i = 0; i < 3; ++i) {
        p.cycle_begin();
        p.cycle_end();
    }
    // The straddling cycle is long and the next short, far apart: the CPU-time
    // clock may add the switches around a cycle (CI saw 1 ms counted as 3.3 ms
    // on a loaded machine), so maxC tells them apart by a bound, not equality.
    p.cycle_begin();
    burn_cpu(40'000'000);
    seg.reset_all();  // mid-cycle: this cycle straddles the reset
    p.cycle_end();
    auto s = seg.snapshot();
    EXPECT_FALSE(s[0].reset_pending);
    EXPECT_EQ(s[0].cycle, 1u);
    EXPECT_EQ(s[0].accounted, 0u);
    EXPECT_EQ(s[0].tot_c, 0.0);
    EXPECT_GE(s[0].last_c, 0.039);
    p.cycle_begin();
    burn_cpu(1'000'000);
    p.cycle_end();
    s = seg.snapshot();
    EXPECT_EQ(s[0].cycle, 2u);
    EXPECT_EQ(s[0].accounted, 1u);
    EXPECT_GE(s[0].max_c, 0.00099);
    EXPECT_LT(s[0].max_c, 0.020) << "the 40 ms straddling cycle was accounted";

    // A task turned on restarts profiling on its RTPU (§6.7), but warnings
    // are "since the last status command" and stay.
    slot.warning("kept");
    const auto before = seg.snapshot()[0];
    p.start();
    const auto after = seg.snapshot()[0];
    EXPECT_TRUE(after.reset_pending);
    EXPECT_EQ(after.cycle, 0u);
    EXPECT_LE(after.ptime, before.ptime);
    EXPECT_EQ(after.warn, 1u);
    EXPECT_EQ(after.warning, "kept");
}

TEST(Profiler, HalfTickAccountingQuantisesEachCycle) {
    StatusOptions o;
    o.rtpus = 1;
    o.accounting = Accounting::half_tick;
    o.tick_ns = 1'000'000;
    auto seg = StatusSegment::create(unique_subsystem("half"), 1, o);
    TaskSlot slot = seg.claim(id("h", 0));
    TaskProfiler p(slot, /*allow_perf=*/false);  // burn_cpu's clock: the quantising is the subject
    for (int i = 0; i < 4; ++i) {
        p.cycle_begin();
        burn_cpu(1'300'000);  // 1.3 ms: one whole tick + a partial one = 3 half-ticks
        p.cycle_end();
    }
    auto s = seg.snapshot();
    EXPECT_EQ(s[0].accounting, Accounting::half_tick);
    EXPECT_DOUBLE_EQ(s[0].tick, 0.001);
    // 1.3 ms of CPU plus the clock reads: whatever the exact value, each cycle is
    // a whole number of half-ticks, 1.5 ms unless preempted past 2 ms.
    EXPECT_DOUBLE_EQ(std::fmod(s[0].min_c * 2000.0, 1.0), 0.0);
    EXPECT_DOUBLE_EQ(s[0].min_c, 0.0015);
    EXPECT_DOUBLE_EQ(s[0].tot_c, 3 * 0.0015);
}

TEST(Profiler, ReaderSwitchesAnRtpuToHalfTickAccounting) {
    const std::string sub = unique_subsystem("readerhalf");
    StatusOptions o;
    o.rtpus = 2;
    auto seg = StatusSegment::create(sub, 2, o);
    TaskSlot on0 = seg.claim(id("a", 0));
    TaskSlot on1 = seg.claim(id("b", 1));
    // burn_cpu's clock (the perf clock counts a vCPU's stolen time): the
    // accounting is the subject, and 0.1 ms must stay under 1 ms.
    TaskProfiler p0(on0, /*allow_perf=*/false), p1(on1, /*allow_perf=*/false);
    auto reader = StatusReader::attach(sub);
    EXPECT_THROW(reader.set_accounting(0, Accounting::half_tick, 0), StatusError);
    EXPECT_THROW(reader.set_accounting(2, Accounting::half_tick, 1'000'000), StatusError);
    reader.set_accounting(0, Accounting::half_tick, 2'000'000);  // a 2 ms tick on RTPU 0 only
    for (int i = 0; i < 3; ++i) {
        p0.cycle_begin();
        burn_cpu(100'000);
        p0.cycle_end();
        p1.cycle_begin();
        burn_cpu(100'000);
        p1.cycle_end();
    }
    auto s = seg.snapshot();
    ASSERT_EQ(s.size(), 2u);
    EXPECT_EQ(s[0].accounting, Accounting::half_tick);
    EXPECT_DOUBLE_EQ(s[0].tick, 0.002);
    EXPECT_DOUBLE_EQ(s[0].max_c, 0.001);  // 0.1 ms is one partial tick: one half-tick
    EXPECT_EQ(s[1].accounting, Accounting::nanoseconds);
    EXPECT_LT(s[1].max_c, 0.001);
    reader.set_accounting(0, Accounting::nanoseconds, 0);
    p0.cycle_begin();
    p0.cycle_end();
    EXPECT_EQ(seg.snapshot()[0].accounting, Accounting::nanoseconds);
}

TEST(Profiler, HistogramFeedsTheExecutionProfile) {
    auto seg = StatusSegment::create(unique_subsystem("hist"), 1, one_rtpu());
    TaskSlot slot = seg.claim(id("h", 0));
    // The thread's CPU-time clock, the one burn_cpu burns, so each cycle lands
    // in a known bucket: the perf clock counts a vCPU's stolen time too (CI's
    // asan stage saw a 3.3 ms burn land in the 5-6 ms bucket).
    TaskProfiler p(slot, /*allow_perf=*/false);
    p.set_histogram(1'000'000);  // 1 ms buckets
    for (int i = 0; i < 11; ++i) {
        p.cycle_begin();
        burn_cpu(i % 5 == 4 ? 3'300'000 : 300'000);
        p.cycle_end();
    }
    const auto h = seg.snapshot()[0].histogram;
    EXPECT_EQ(h.bucket_width_ns, 1'000'000u);
    EXPECT_EQ(h.total(), 10u);  // the first cycle dropped
    EXPECT_EQ(h.counts[0], 8u);
    EXPECT_EQ(h.counts[3], 2u);
    EXPECT_EQ(h.effective_ns(0.8), 1'000'000u);
    EXPECT_EQ(h.effective_ns(1.0), 4'000'000u);
}

TEST(Profiler, FallbackClockIsStatedInTheStatus) {
    auto seg = StatusSegment::create(unique_subsystem("fallback"), 1, one_rtpu());
    TaskSlot slot = seg.claim(id("f", 0));
    TaskProfiler p(slot, /*allow_perf=*/false);
    EXPECT_EQ(p.clock(), CpuClock::thread_cputime);
    for (int i = 0; i < 3; ++i) {
        p.cycle_begin();
        burn_cpu(1'000'000);
        p.cycle_end();
    }
    auto s = seg.snapshot()[0];
    EXPECT_EQ(s.cpu_clock, CpuClock::thread_cputime);
    EXPECT_STREQ(to_string(s.cpu_clock), "thread-cputime");
    EXPECT_NEAR(s.avg_c, 0.001, 0.0003);
}

// The preempted task's CPU time must not include the preemption. Both threads
// pinned to one CPU; the preempter is SCHED_FIFO (needs RT privilege).
TEST(Profiler, PreemptionByAHigherPriorityTaskIsNotCharged) {
    auto seg = StatusSegment::create(unique_subsystem("preempt"), 1, one_rtpu());
    TaskSlot slot = seg.claim(id("victim", 0));
    const int cpu = 1 % static_cast<int>(std::thread::hardware_concurrency());
    std::atomic<bool> go{false}, stop{false};
    std::atomic<bool> rt_ok{true};
    std::thread preempter([&] {
        pin_to(cpu);
        sched_param sp{};
        sp.sched_priority = 50;
        if (pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp) != 0) {
            rt_ok = false;
            return;
        }
        while (!go) std::this_thread::sleep_for(std::chrono::microseconds(200));
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
        const std::int64_t until = ipc::now_ns() + 30'000'000;  // hog the CPU 30 ms
        while (ipc::now_ns() < until) {
        }
        while (!stop) std::this_thread::sleep_for(std::chrono::milliseconds(1));
    });
    std::int64_t wall = 0;
    std::uint64_t cpu_ns = 0;
    std::thread victim([&] {
        pin_to(cpu);
        TaskProfiler p(slot);
        p.cycle_begin();
        p.cycle_end();  // the dropped first cycle
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
        if (!rt_ok) return;
        const std::int64_t t0 = ipc::now_ns();
        p.cycle_begin();
        go = true;
        burn_cpu(20'000'000);
        p.cycle_end();
        wall = ipc::now_ns() - t0;
        cpu_ns = p.last_cycle_ns();
    });
    victim.join();
    stop = true;
    preempter.join();
    if (!rt_ok) GTEST_SKIP() << "no SCHED_FIFO privilege: cannot preempt";
    EXPECT_GE(wall, 45'000'000) << "the preempter did not run during the cycle";
    EXPECT_GE(cpu_ns, 20'000'000u);
    // Charged, the 30 ms preemption would make it 50 ms; the bound leaves room
    // for a vCPU's stolen time, which this clock counts (CI saw 2.3 ms in 1 ms).
    EXPECT_LT(cpu_ns, 40'000'000u) << "the 30 ms preemption was charged";
    auto s = seg.snapshot()[0];
    EXPECT_EQ(s.switched, 1u);
    EXPECT_GE(s.max_c, 0.0199);
    EXPECT_LT(s.max_c, 0.040);
}

// A cycle that blocks part-way (sleeps) is charged only the CPU time it ran,
// accumulated across the switch-out and back in (§6.7's q_c[k] += l).
TEST(Profiler, BlockingInsideACycleIsNotCharged) {
    for (const bool perf : {true, false}) {
        auto seg = StatusSegment::create(unique_subsystem(perf ? "blockp" : "blockc"), 1, one_rtpu());
        TaskSlot slot = seg.claim(id("sleeper", 0));
        TaskProfiler p(slot, perf);
        p.cycle_begin();
        p.cycle_end();  // dropped
        p.cycle_begin();
        burn_cpu(2'000'000);
        std::this_thread::sleep_for(std::chrono::milliseconds(15));
        burn_cpu(2'000'000);
        p.cycle_end();
        const auto s = seg.snapshot()[0];
        SCOPED_TRACE(to_string(p.clock()));
        // The burns are 4 ms of CLOCK_THREAD_CPUTIME_ID; the profiler reads its
        // own clock (perf's task clock), which a fresh-clone ASan run found
        // 36 us short of it (3.964 ms): 5 % of slack, far from the 15 ms sleep.
        EXPECT_GE(s.max_c, 0.0038);
        // Charged, the sleep would make it 19 ms; room for stolen time below that.
        EXPECT_LT(s.max_c, 0.015) << "the 15 ms sleep was charged";
        if (p.clock() == CpuClock::perf_switch) {
            EXPECT_GE(s.switched, 1u);
        }
    }
}

// missed() is called from the deadline-failure signal handler, in the task
// thread, possibly while that thread is inside its own publication: no miss
// may be lost and readers must keep seeing consistent profiles.
namespace {
TaskProfiler* g_signal_profiler = nullptr;
std::atomic<std::uint64_t> g_signals_handled{0};
void miss_from_signal(int) {
    g_signal_profiler->missed(1);
    g_signals_handled.fetch_add(1, std::memory_order_relaxed);
}
}  // namespace

TEST(Profiler, MissesReportedFromASignalHandlerMidPublicationAreKept) {
    auto seg = StatusSegment::create(unique_subsystem("sigmiss"), 1, one_rtpu());
    TaskSlot slot = seg.claim(id("sig", 0));
    struct sigaction sa {};
    sa.sa_handler = miss_from_signal;
    sigemptyset(&sa.sa_mask);
    struct sigaction old {};
    ASSERT_EQ(sigaction(SIGUSR1, &sa, &old), 0);
    g_signals_handled = 0;
    std::atomic<bool> stop{false}, ready{false};
    std::atomic<std::uint64_t> cycles{0};
    std::thread task([&] {
        TaskProfiler p(slot);
        p.set_histogram(100);
        g_signal_profiler = &p;
        ready = true;
        while (!stop) {
            p.cycle_begin();
            p.cycle_end();
            cycles.fetch_add(1, std::memory_order_relaxed);
        }
        // Signals still in flight land before the thread ends.
        sigset_t pending;
        do {
            sigpending(&pending);
        } while (sigismember(&pending, SIGUSR1));
        g_signal_profiler = nullptr;
    });
    while (!ready) std::this_thread::yield();
    // A snapshot that says it is consistent must be (the profile's
    // invariants hold); one that says it is not is a reader the writer, which
    // publishes without a pause, kept out for the seqlock's 200 ms (seen
    // twice in 334 under ASan on 2 CPUs): counted, and bounded so that the
    // invariants are checked on most snapshots.
    std::uint64_t bad = 0, starved = 0, taken = 0, last_miss = 0, regressions = 0;
    for (int i = 0; i < 1000; ++i) {
        pthread_kill(task.native_handle(), SIGUSR1);
        if (i % 3 == 0) {
            const auto s = seg.snapshot()[0];
            ++taken;
            std::uint64_t sum = 0;
            for (auto c : s.histogram.counts) sum += c;
            if (!s.consistent) ++starved;
            else if ((s.cycle > 0 && s.accounted != s.cycle - 1) || sum != s.accounted) ++bad;
            if (s.miss < last_miss) ++regressions;
            last_miss = s.miss;
        }
        // Let a few cycles run between signals (and signals land in them).
        const std::uint64_t c0 = cycles.load();
        while (cycles.load() < c0 + 3) {
        }
    }
    stop = true;
    task.join();
    sigaction(SIGUSR1, &old, nullptr);
    const auto s = seg.snapshot()[0];
    EXPECT_GT(g_signals_handled.load(), 0u);
    EXPECT_EQ(s.miss, g_signals_handled.load()) << "a miss reported mid-publication was lost";
    EXPECT_EQ(bad, 0u) << "consistent snapshots that break the profile's invariants";
    EXPECT_LE(starved * 10, taken) << starved << " of " << taken << " snapshots found no consistent moment";
    EXPECT_EQ(regressions, 0u);
}

// Zero system calls per unpreempted cycle: counted by the kernel itself with a
// per-thread perf counter on the raw_syscalls:sys_enter tracepoint.
using chimera::test::open_syscall_counter;
const auto read_counter = chimera::test::read_syscall_counter;

TEST(Profiler, NoSystemCallUnlessTheCycleWasSwitchedOut) {
    auto seg = StatusSegment::create(unique_subsystem("sys"), 2, one_rtpu());
    TaskSlot slot = seg.claim(id("s", 0));
    TaskSlot slot2 = seg.claim(id("s2", 0));
    TaskProfiler p(slot);
    TaskProfiler fallback(slot2, false);
    const int fd = open_syscall_counter();
    if (fd < 0) {
        // tests/prof/in_tracefs_namespace.sh provides the tracepoint; there
        // this must not pass silently.
        if (std::getenv("CHIMERA_REQUIRE_SYSCALL_COUNTER"))
            FAIL() << "raw_syscalls:sys_enter counter could not be opened";
        GTEST_SKIP() << "raw_syscalls:sys_enter not available (mount tracefs as root, or run "
                        "the prof_syscalls test)";
    }
    constexpr int kCycles = 20000;
    // Calibrate: the read() of the counter itself is counted once.
    const std::uint64_t c0 = read_counter(fd);
    const std::uint64_t c1 = read_counter(fd);
    const std::uint64_t per_read = c1 - c0;
    const std::uint64_t sw0 = seg.snapshot()[0].switched;
    const std::uint64_t a = read_counter(fd);
    for (int i = 0; i < kCycles; ++i) {
        p.cycle_begin();
        p.cycle_end();
    }
    const std::uint64_t b = read_counter(fd);
    const std::uint64_t switched = seg.snapshot()[0].switched - sw0;
    const std::uint64_t syscalls = b - a - per_read;
    EXPECT_EQ(syscalls, switched) << "perf-page profiling: one read() per switched cycle, else none";
    EXPECT_LT(switched, static_cast<std::uint64_t>(kCycles / 10));

    // The fallback clock makes two per cycle: proves the counter sees them.
    const std::uint64_t f0 = read_counter(fd);
    for (int i = 0; i < 100; ++i) {
        fallback.cycle_begin();
        fallback.cycle_end();
    }
    const std::uint64_t f1 = read_counter(fd);
    EXPECT_EQ(f1 - f0 - per_read, 200u);
    close(fd);
}

// Readers in another process never see a torn profile: in every snapshot the
// histogram sums to the accounted cycles and accounted == cycles - 1, while
// the writer runs cycles as fast as it can and the reader resets it.
TEST(Consistency, MultiProcessSnapshotsUnderConcurrentUpdates) {
    const std::string sub = unique_subsystem("seq");
    const chimera::test::SegmentGuard cleanup("chimera." + sub + ".");  // the killed-at-exit writer's attach
    auto seg = StatusSegment::create(sub, 1, one_rtpu());
    TaskSlot slot = seg.claim(id("w", 0));
    // The writer runs until the reader has checked enough snapshots (a count,
    // not a time: under AddressSanitizer 1.3 s gave only 250).
    auto* stop = chimera::test::shared_anon<std::atomic<bool>>();
    const pid_t child = fork();
    if (child == 0) {
        // The writer process: the real writer API on the parent's segment.
        try {
            auto mine = StatusSegment::attach(sub);
            TaskProfiler p(slot);  // same mapping layout; slot handle from before fork
            p.set_histogram(50);
            const std::int64_t end = ipc::now_ns() + 60'000'000'000;  // a reader that died
            while (!stop->load() && ipc::now_ns() < end) {
                for (int i = 0; i < 1000; ++i) {
                    p.cycle_begin();
                    p.cycle_end();
                }
                p.missed(1);
            }
        } catch (...) {
            _exit(2);
        }
        _exit(0);
    }
    auto reader = StatusReader::attach(sub);
    std::uint64_t checked = 0, bad = 0, max_cycles = 0, torn = 0;
    const std::int64_t least = ipc::now_ns() + 1'300'000'000, most = ipc::now_ns() + 30'000'000'000;
    int n = 0;
    while (ipc::now_ns() < most && (ipc::now_ns() < least || checked <= 1000 || max_cycles <= 1000)) {
        auto raw = reader.raw(0);
        ASSERT_TRUE(raw.has_value());
        if (!raw->consistent) {
            ++torn;  // writer preempted in its window longer than the reader waits
        } else if (raw->cycles > 0) {
            ++checked;
            std::uint64_t sum = 0;
            for (auto c : raw->histogram.counts) sum += c;
            if (raw->accounted != raw->cycles - 1 || sum != raw->accounted ||
                (raw->accounted > 0 && raw->q_min > raw->q_max))
                ++bad;
            max_cycles = std::max(max_cycles, raw->cycles);
        }
        if (++n % 5000 == 0) reader.reset_all();
    }
    stop->store(true);
    int st = 0;
    waitpid(child, &st, 0);
    ASSERT_TRUE(WIFEXITED(st) && WEXITSTATUS(st) == 0);
    EXPECT_GT(checked, 1000u);
    EXPECT_GT(max_cycles, 1000u);
    EXPECT_EQ(bad, 0u);
    EXPECT_LT(torn, checked / 100 + 1);
}
