// The Linux backends of the MUF scheduler and timing failures (thesis §6.2.3,
// §6.3; docs/architecture.md §9, §10) on the real kernel: failures in the
// failing thread, aborts that leave no lock held, handlers held off in critical
// sections, an overload where only the non-critical task misses, the
// dispatcher's priority order against the analysis, SCHED_DEADLINE admission.
// Times are generous (tens of milliseconds) and only events are counted: the
// machine is shared and noisy.
#include <gtest/gtest.h>

#include <pwd.h>
#include <sched.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <sys/sysinfo.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <functional>
#include <map>
#include <memory>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "chimera/ipc/futex.hpp"
#include "chimera/ipc/lock.hpp"
#include "chimera/muf.hpp"
#include "cpu_loss.hpp"
#include "cpu_partition.hpp"
#include "rt_internal.hpp"
#include "sanitizer.hpp"
#include "syscall_counter.hpp"

using namespace chimera::muf;
using namespace std::chrono_literals;
using chimera::test::cpu_time_of_thread;
using chimera::test::CpuPartition;

namespace {

constexpr std::int64_t ms = 1'000'000;

int gettid_now() { return static_cast<int>(syscall(SYS_gettid)); }

std::int64_t thread_cpu_ns() {
    timespec ts;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
    return static_cast<std::int64_t>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec;
}

// Busy for `ns` of this thread's CPU time (robust to preemption).
void burn_cpu(std::int64_t ns) {
    const std::int64_t end = thread_cpu_ns() + ns;
    while (thread_cpu_ns() < end) {
    }
}

// Busy for `ns` of wall-clock time.
void burn_wall(std::int64_t ns) {
    const std::int64_t end = clock_ns() + ns;
    while (clock_ns() < end) {
    }
}

int rt_cpu() { return get_nprocs() - 1; }

// What a failure handler saw; the handler is a plain function, as in the thesis.
struct Probe {
    std::atomic<int> count[4]{};
    std::atomic<int> task_tid{0};
    std::atomic<int> wrong_thread{0};
    std::atomic<int> crit_in_handler{-1};
    std::atomic<int> lock_held_in_handler{0};
    chimera::ipc::LockWord* lock = nullptr;
    FailureAction action = FailureAction::resume;
    Failure act_on = Failure::deadline;
    int set_crit_to = 0;  // 0: leave the criticality alone
};

FailureAction probe_handler(Failure kind, void* user) {
    auto* p = static_cast<Probe*>(user);
    p->count[static_cast<int>(kind)].fetch_add(1);
    if (gettid_now() != p->task_tid.load()) p->wrong_thread.fetch_add(1);
    p->crit_in_handler.store(criticality());
    if (p->lock && p->lock->owner.load() != 0) p->lock_held_in_handler.fetch_add(1);
    if (p->set_crit_to > 0) set_criticality(p->set_crit_to);
    return kind == p->act_on ? p->action : FailureAction::resume;
}

// A task thread running the loop of rt.hpp's header comment.
class Runner {
public:
    Runner(RtpuScheduler& sch, const RtTaskParams& params, std::function<void()> cycle,
           Probe* probe = nullptr, int handler_crit = 0)
        : sch_(sch), cycle_(std::move(cycle)), probe_(probe), handler_crit_(handler_crit) {
        h_ = sch_.add_task(params);
    }
    ~Runner() { stop(); }

    // Starts the thread; false (with error()) when attach was refused.
    bool start() {
        thread_ = std::thread([this] { run(); });
        while (state_.load() == 0) std::this_thread::sleep_for(1ms);
        if (state_.load() < 0) {
            thread_.join();
            return false;
        }
        return true;
    }
    void stop() {
        if (!thread_.joinable()) return;
        sch_.remove_task(h_);
        thread_.join();
    }
    TaskHandle handle() const { return h_; }
    int tid() const { return tid_.load(); }
    const std::string& error() const { return error_; }
    int skipped() const { return skipped_.load(); }
    int started_cycles() const { return started_.load(); }
    // Jobs released to the cycle mark: started, or dropped there (aborted at
    // their deadline before they began, when the release came that late).
    int released_jobs() const { return released_.load(); }

private:
    void run() {
        try {
            sch_.attach_current_thread(h_);
        } catch (const SchedError& e) {
            error_ = e.what();
            state_.store(-1);
            return;
        }
        tid_.store(gettid_now());
        if (probe_) {
            probe_->task_tid.store(gettid_now());
            set_dfhandler(probe_handler, handler_crit_, probe_);
        }
        state_.store(1);
        sigset_t normal_mask;
        pthread_sigmask(SIG_SETMASK, nullptr, &normal_mask);
        for (;;) {
            const Wake w = sch_.wait_release(h_);
            if (w == Wake::detached) break;
            if (w != Wake::release) {
                skipped_.fetch_add(1);
                continue;
            }
            released_.fetch_add(1);
            // As the runtime does (src/sbs/task_loop.cpp): no mask saved, which
            // would be a system call per cycle; restored after a jump instead.
            if (sigsetjmp(*sch_.cycle_mark(h_), 0) == 0) {
                sch_.arm_abort(h_);
                started_.fetch_add(1);
                cycle_();
            } else {
                pthread_sigmask(SIG_SETMASK, &normal_mask, nullptr);
            }
            sch_.cycle_complete(h_);
        }
        sch_.detach_current_thread(h_);
    }

    RtpuScheduler& sch_;
    std::function<void()> cycle_;
    Probe* probe_;
    int handler_crit_;
    TaskHandle h_ = -1;
    std::thread thread_;
    std::atomic<int> state_{0};
    std::atomic<int> tid_{0};
    std::atomic<int> skipped_{0};
    std::atomic<int> started_{0};
    std::atomic<int> released_{0};
    std::string error_;
};

RtpuOptions options(Backend backend, Policy policy = Policy::muf) {
    RtpuOptions o;
    o.name = "test";
    o.cpu = rt_cpu();
    o.backend = backend;
    o.policy = policy;
    o.quiet = true;
    return o;
}

RtTaskParams task(const char* name, std::int64_t period, std::int64_t wcet, std::int64_t deadline = 0) {
    RtTaskParams p;
    p.name = name;
    p.period_ns = period;
    p.wcet_ns = wcet;
    p.deadline_ns = deadline;
    return p;
}

// Waits until `pred` holds, at most `limit`.
bool eventually(const std::function<bool()>& pred, std::chrono::milliseconds limit = 3000ms) {
    const auto end = std::chrono::steady_clock::now() + limit;
    while (std::chrono::steady_clock::now() < end) {
        if (pred()) return true;
        std::this_thread::sleep_for(2ms);
    }
    return pred();
}

int fifo_priority_of(int tid) {
    sched_param sp{};
    if (sched_getparam(tid, &sp) != 0) return -1;
    return sched_getscheduler(tid) == SCHED_FIFO ? sp.sched_priority : 0;
}

}  // namespace

// ------------------------------------------------------------------ pure parts

TEST(MufRank, GivesStrictlyDecreasingPrioritiesInUrgencyOrder) {
    detail::RankEntry e[3];
    e[0] = {.urgency = 5, .since_ns = 0, .handle = 0, .current_prio = 0, .new_prio = 0};
    e[1] = {.urgency = 9, .since_ns = 0, .handle = 1, .current_prio = 0, .new_prio = 0};
    e[2] = {.urgency = 7, .since_ns = 0, .handle = 2, .current_prio = 0, .new_prio = 0};
    detail::rank_priorities(e, 10, 80);
    EXPECT_EQ(e[0].handle, 1);
    EXPECT_EQ(e[0].new_prio, 79);
    EXPECT_EQ(e[1].handle, 2);
    EXPECT_EQ(e[1].new_prio, 78);
    EXPECT_EQ(e[2].handle, 0);
    EXPECT_EQ(e[2].new_prio, 77);
}

TEST(MufRank, ChangesOnlyTheTasksThatMove) {
    // A at 79 and C at 77 are in order; B, released between them, takes 78.
    detail::RankEntry e[3];
    e[0] = {.urgency = 9, .since_ns = 0, .handle = 0, .current_prio = 79, .new_prio = 0};
    e[1] = {.urgency = 3, .since_ns = 0, .handle = 2, .current_prio = 77, .new_prio = 0};
    e[2] = {.urgency = 6, .since_ns = 0, .handle = 1, .current_prio = 12, .new_prio = 0};
    detail::rank_priorities(e, 10, 80);
    EXPECT_EQ(e[0].new_prio, 79);
    EXPECT_EQ(e[1].handle, 1);
    EXPECT_EQ(e[1].new_prio, 78);
    EXPECT_EQ(e[2].new_prio, 77);
    // Already in order: nothing moves, even with gaps.
    detail::RankEntry f[2];
    f[0] = {.urgency = 9, .since_ns = 0, .handle = 0, .current_prio = 40, .new_prio = 0};
    f[1] = {.urgency = 3, .since_ns = 0, .handle = 1, .current_prio = 20, .new_prio = 0};
    detail::rank_priorities(f, 10, 80);
    EXPECT_EQ(f[0].new_prio, 40);
    EXPECT_EQ(f[1].new_prio, 20);
}

TEST(MufRank, EqualUrgencyIsFirstComeFirstServedAndTheBandIsKept) {
    detail::RankEntry e[3];
    e[0] = {.urgency = 4, .since_ns = 300, .handle = 0, .current_prio = 11, .new_prio = 0};
    e[1] = {.urgency = 4, .since_ns = 100, .handle = 1, .current_prio = 10, .new_prio = 0};
    e[2] = {.urgency = 4, .since_ns = 200, .handle = 2, .current_prio = 10, .new_prio = 0};
    detail::rank_priorities(e, 10, 13);
    EXPECT_EQ(e[0].handle, 1);
    EXPECT_EQ(e[1].handle, 2);
    EXPECT_EQ(e[2].handle, 0);
    // Three tasks in the band [10, 13): exactly 12, 11, 10.
    EXPECT_EQ(e[0].new_prio, 12);
    EXPECT_EQ(e[1].new_prio, 11);
    EXPECT_EQ(e[2].new_prio, 10);
}

// wait_release's reference form: the task's own word is the one futex it
// sleeps on (process-private). A change of the word made by another thread
// ends the wait as a command; a removal reaches the sleeping thread through
// the same word, long before its next release (a 10 s period here).
TEST(MufRt, TheTasksOwnWordEndsTheWaitForACommandAndForARemoval) {
    RtpuScheduler sch(options(Backend::other));
    const TaskHandle h = sch.add_task(task("own_word", 10'000 * ms, 0));
    std::atomic<std::uint32_t> word{0};
    std::atomic<int> commands{0}, waiting{0};
    std::atomic<bool> detached{false};
    std::thread t([&] {
        sch.attach_current_thread(h);
        for (;;) {
            const std::uint32_t seen = word.load();
            waiting.fetch_add(1);
            const Wake w = sch.wait_release(h, word, seen);
            if (w == Wake::detached) break;
            if (w == Wake::command) commands.fetch_add(1);
            if (w == Wake::release) sch.cycle_complete(h);
        }
        detached.store(true);
        sch.detach_current_thread(h);
    });
    ASSERT_TRUE(eventually([&] { return waiting.load() >= 1; }));
    std::this_thread::sleep_for(50ms);  // asleep in the futex, most likely
    const int before = commands.load();
    word.fetch_add(1);
    chimera::ipc::futex_wake_all(word, chimera::ipc::FutexScope::process);
    EXPECT_TRUE(eventually([&] { return commands.load() > before; })) << "a command did not end the wait";
    ASSERT_TRUE(eventually([&] { return waiting.load() >= 2; }));
    std::this_thread::sleep_for(50ms);
    sch.remove_task(h);
    EXPECT_TRUE(eventually([&] { return detached.load(); })) << "the removal did not reach the sleeping thread";
    t.join();
}

TEST(MufRank, TheOrderHoldsWhereItMattersAndOnlyThere) {
    // Sorted most urgent first. P: a pending job, W: a task waiting for its
    // release (ranked by the job that release begins).
    const auto entry = [](std::uint64_t urgency, int handle, int prio, bool pending) {
        detail::RankEntry e{.urgency = urgency, .since_ns = 0, .handle = handle, .current_prio = prio, .new_prio = prio};
        e.pending = pending;
        return e;
    };
    // Pending jobs in urgency order, a waiting task above the less urgent one.
    detail::RankEntry ok[3] = {entry(9, 0, 70, true), entry(6, 1, 60, false), entry(3, 2, 50, true)};
    EXPECT_TRUE(detail::ranking_holds(ok, 10, 80));
    // A waiting task may stand above a more urgent pending job: released, it
    // runs first and ranks itself down before its job begins.
    detail::RankEntry high[2] = {entry(9, 0, 60, true), entry(6, 1, 70, false)};
    EXPECT_TRUE(detail::ranking_holds(high, 10, 80));
    // ... but not below a less urgent one: released, it would wait behind it.
    detail::RankEntry low[2] = {entry(9, 0, 50, false), entry(6, 1, 60, true)};
    EXPECT_FALSE(detail::ranking_holds(low, 10, 80));
    detail::RankEntry tie[2] = {entry(9, 0, 60, false), entry(6, 1, 60, true)};
    EXPECT_FALSE(detail::ranking_holds(tie, 10, 80));  // FIFO among equals: behind it
    // Two pending jobs out of order.
    detail::RankEntry swapped[2] = {entry(9, 0, 50, true), entry(6, 1, 60, true)};
    EXPECT_FALSE(detail::ranking_holds(swapped, 10, 80));
    // Waiting tasks among themselves are free.
    detail::RankEntry waiting[2] = {entry(9, 0, 50, false), entry(6, 1, 60, false)};
    EXPECT_TRUE(detail::ranking_holds(waiting, 10, 80));
    // Not placed yet (0), or outside the band.
    detail::RankEntry unplaced[1] = {entry(9, 0, 0, false)};
    EXPECT_FALSE(detail::ranking_holds(unplaced, 10, 80));
    detail::RankEntry outside[1] = {entry(9, 0, 80, true)};
    EXPECT_FALSE(detail::ranking_holds(outside, 10, 80));
}

TEST(MufRank, StandingUrgencyOrdersCriticalityThenAbsoluteDeadlineThenUserPriority) {
    const UrgencyEncoding enc;
    // Earlier deadline more urgent, whatever the user priority.
    EXPECT_GT(detail::standing_urgency(enc, 1, 1000, 0), detail::standing_urgency(enc, 1, 1001, 63));
    // Equal deadlines: the user priority.
    EXPECT_GT(detail::standing_urgency(enc, 1, 1000, 5), detail::standing_urgency(enc, 1, 1000, 4));
    // Criticality first, whatever the deadline; no deadline least urgent.
    EXPECT_GT(detail::standing_urgency(enc, 2, -1, 0), detail::standing_urgency(enc, 1, 0, 63));
    EXPECT_GT(detail::standing_urgency(enc, 1, std::int64_t{1} << 40, 0), detail::standing_urgency(enc, 1, -1, 63));
    // Far deadlines stay apart: 2^40 ticks (12.7 days of µs) is within the field.
    EXPECT_GT(detail::standing_urgency(enc, 1, std::int64_t{1} << 40, 0),
              detail::standing_urgency(enc, 1, (std::int64_t{1} << 40) + 1, 0));
}

TEST(MufRt, BackendNamesAndBadParameters) {
    EXPECT_EQ(parse_backend("FIFO"), Backend::fifo);
    EXPECT_EQ(parse_backend("deadline"), Backend::deadline);
    EXPECT_EQ(parse_backend("other"), Backend::other);
    EXPECT_FALSE(parse_backend("rr"));
    EXPECT_EQ(to_string(Failure::maxexec), "MAXEXEC");

    RtpuOptions bad = options(Backend::other);
    bad.fifo_low = 50;
    bad.fifo_high = 40;
    EXPECT_THROW(RtpuScheduler{bad}, SchedError);
    bad = options(Backend::other);
    bad.cpu = 4096;
    try {
        RtpuScheduler s(bad);
        FAIL() << "CPU 4096 accepted";
    } catch (const SchedError& e) {
        EXPECT_NE(std::string(e.what()).find("CPU 4096"), std::string::npos) << e.what();
    }

    RtpuScheduler sch(options(Backend::other));
    try {
        sch.add_task(task("late", 10 * ms, 1 * ms, 20 * ms));
        FAIL() << "deadline beyond period accepted";
    } catch (const SchedError& e) {
        EXPECT_NE(std::string(e.what()).find("task 'late'"), std::string::npos) << e.what();
    }
    RtTaskParams p = task("min", 10 * ms, 1 * ms);
    p.minexec_ns = 11 * ms;
    EXPECT_THROW(sch.add_task(p), SchedError);
    EXPECT_THROW(sch.add_task(task("zero", 0, 1)), SchedError);
    EXPECT_THROW(sch.remove_task(7), SchedError);
}

// ------------------------------------------------------------------ failures

class MufFailures : public ::testing::TestWithParam<Backend> {};

TEST_P(MufFailures, DeadlineRunsTheHandlerInTheTaskThread) {
    RtpuScheduler sch(options(GetParam()));
    Probe probe;
    // 30 ms of wall time against a 10 ms deadline in a 50 ms period.
    RtTaskParams p = task("late", 50 * ms, 40 * ms, 10 * ms);
    p.maxexec_check = false;
    Runner r(sch, p, [] { std::this_thread::sleep_for(30ms); }, &probe);
    ASSERT_TRUE(r.start()) << r.error();
    ASSERT_TRUE(eventually([&] { return probe.count[1].load() >= 3; }));
    r.stop();
    const RtTaskStatus st = sch.status(r.handle());
    EXPECT_EQ(probe.wrong_thread.load(), 0);
    EXPECT_EQ(probe.count[2].load(), 0);
    // One handler call per late job, for every deadline that passed while it
    // ran (more than one where a job overran a whole period: a loaded machine).
    EXPECT_GE(st.deadline_failures, static_cast<std::uint64_t>(probe.count[1].load()));
    // Every job but the one cut short by stop() completed; none was aborted.
    EXPECT_GE(st.cycles, 2u);
    EXPECT_EQ(st.aborted, 0u);
}

// A job that ends after its deadline is reported at its end, by the task
// itself, even when the watchdog never looks: one task with an implicit
// deadline ranks statically (the dispatcher is off the release path) and the
// watchdog's longest sleep is far beyond the test. Every job sleeps past the
// period, so every job is one DEADLINE failure, handled in the task's thread,
// and none is aborted (the cycle is over when it is seen).
TEST_P(MufFailures, DeadlineOfAJobThatEndsLateIsReportedAtItsEnd) {
    RtpuOptions o = options(GetParam());
    o.watchdog_ns = 3'600'000 * ms;
    RtpuScheduler sch(o);
    Probe probe;
    probe.action = FailureAction::abort_cycle;
    RtTaskParams p = task("late", 20 * ms, 15 * ms);
    p.maxexec_check = false;
    Runner r(sch, p, [] { std::this_thread::sleep_for(25ms); }, &probe);
    ASSERT_TRUE(r.start()) << r.error();
    ASSERT_TRUE(eventually([&] { return sch.status(r.handle()).cycles >= 4; }))
        << sch.status(r.handle()).cycles << " cycles, " << sch.status(r.handle()).missed << " missed, "
        << sch.status(r.handle()).deadline_failures << " DEADLINE, " << r.started_cycles() << " started";
    r.stop();
    const RtTaskStatus st = sch.status(r.handle());
    EXPECT_EQ(probe.wrong_thread.load(), 0);
    // One report per late job, counting every deadline that passed while it
    // ran (more than one where a job overran a whole period: a loaded machine).
    EXPECT_GE(st.deadline_failures, static_cast<std::uint64_t>(probe.count[1].load()));
    // Every job was reported at its end, and counted as a cycle: the one
    // during which stop() removed the task too (within one: the count of
    // handler runs and of cycles are read a moment apart). A job that overran
    // the next release's deadline too (a slow guest's 25 ms sleep taking 45)
    // makes that release skipped: one more report, and a miss, but no cycle.
    const auto reports = static_cast<std::uint64_t>(probe.count[1].load());
    const std::uint64_t skipped = st.missed - std::min(st.missed, st.cycles);
    EXPECT_GE(reports, 3u);
    EXPECT_GE(reports + 1, st.cycles) << reports << " reports, " << st.cycles << " cycles";
    EXPECT_LE(reports, st.cycles + skipped + 1)
        << reports << " reports, " << st.cycles << " cycles, " << skipped << " releases skipped";
    // A miss per failure: the job during which stop() removed the task is
    // accounted as any other, and the releases the last job overran are
    // counted as the task leaves.
    EXPECT_EQ(st.deadline_failures, st.missed) << st.cycles << " cycles";
    EXPECT_EQ(st.aborted, 0u);
}

TEST_P(MufFailures, MaxexecRunsTheHandlerInTheTaskThread) {
    RtpuScheduler sch(options(GetParam()));
    Probe probe;
    // 12 ms of CPU time against a 4 ms budget in a 50 ms period (CPU-time
    // timers fire at the kernel's tick: up to 4 ms late at HZ=250).
    Runner r(sch, task("greedy", 50 * ms, 4 * ms), [] { burn_cpu(12 * ms); }, &probe);
    ASSERT_TRUE(r.start()) << r.error();
    ASSERT_TRUE(eventually([&] { return probe.count[2].load() >= 3; }));
    r.stop();
    EXPECT_EQ(probe.wrong_thread.load(), 0);
    EXPECT_EQ(sch.status(r.handle()).maxexec_failures, static_cast<std::uint64_t>(probe.count[2].load()));
    // One budget per cycle: never more failures than cycles started.
    EXPECT_LE(probe.count[2].load(), r.started_cycles());
}

TEST_P(MufFailures, MinexecSkipsTheCycleAndRunsTheHandler) {
    RtpuScheduler sch(options(GetParam()));
    Probe probe;
    // MINEXEC = the whole deadline: less is always left once the task wakes.
    RtTaskParams p = task("never", 20 * ms, 1 * ms);
    p.minexec_ns = 20 * ms;
    Runner r(sch, p, [] {}, &probe);
    ASSERT_TRUE(r.start()) << r.error();
    ASSERT_TRUE(eventually([&] { return probe.count[3].load() >= 3; }));
    r.stop();
    const RtTaskStatus st = sch.status(r.handle());
    EXPECT_EQ(probe.wrong_thread.load(), 0);
    EXPECT_EQ(r.started_cycles(), 0);
    EXPECT_EQ(st.cycles, 0u);
    EXPECT_EQ(st.minexec_failures, static_cast<std::uint64_t>(probe.count[3].load()));
    EXPECT_GE(st.missed, st.minexec_failures);
    EXPECT_GE(r.skipped(), probe.count[3].load());
}

TEST_P(MufFailures, AbortInsideACriticalSectionWaitsForLeaveAndFreesTheLock) {
    RtpuScheduler sch(options(GetParam()));
    Probe probe;
    chimera::ipc::LockWord table_lock;
    probe.lock = &table_lock;
    probe.action = FailureAction::abort_cycle;
    probe.act_on = Failure::deadline;
    std::atomic<int> sections_done{0}, after_leave{0}, locked_ok{0}, unlock_failed{0};
    // Cycles that entered the section with their deadline still ahead and yet
    // got past leave_critical: none may (the abort waits for leave, then jumps).
    std::atomic<int> early_and_completed{0};
    RtTaskParams p = task("aborted", 60 * ms, 50 * ms, 10 * ms);
    p.maxexec_check = false;
    // The deadline passes while the table lock is held: the handler waits for
    // leave_critical, then aborts; the code after leave never runs.
    Runner r(
        sch, p,
        [&] {
            const bool early = clock_ns() < sch.job_release_ns(r.handle()) + p.deadline_ns;
            enter_critical();
            if (chimera::ipc::holds(chimera::ipc::lock(table_lock))) locked_ok.fetch_add(1);
            // 25 ms past the deadline: the watchdog's signal (at the deadline,
            // plus its wake-up) lands inside the section even in the guest on
            // a loaded host, where 10 ms was once not enough.
            burn_wall(35 * ms);
            if (!chimera::ipc::unlock(table_lock)) unlock_failed.fetch_add(1);
            sections_done.fetch_add(1);
            leave_critical();
            after_leave.fetch_add(1);
            if (early) early_and_completed.fetch_add(1);
        },
        &probe);
    ASSERT_TRUE(r.start()) << r.error();
    ASSERT_TRUE(eventually([&] { return sch.status(r.handle()).aborted >= 3; }));
    r.stop();
    const RtTaskStatus st = sch.status(r.handle());
    EXPECT_EQ(probe.wrong_thread.load(), 0);
    EXPECT_EQ(probe.lock_held_in_handler.load(), 0);   // held off until the section ended
    EXPECT_EQ(table_lock.owner.load(), 0u);             // no lock left held
    EXPECT_EQ(locked_ok.load(), sections_done.load());
    EXPECT_EQ(unlock_failed.load(), 0);
    EXPECT_GE(st.aborted, 3u);
    EXPECT_GE(sch.watchdog_signals(), st.aborted);  // a job that never ends is the watchdog's
    // A cycle that got past leave_critical completed; the others were aborted
    // there (or, released after their deadline on a loaded host, dropped
    // before they began), and the next cycles ran after each abort.
    EXPECT_EQ(static_cast<std::uint64_t>(after_leave.load()), st.cycles);
    EXPECT_EQ(st.cycles + st.aborted, static_cast<std::uint64_t>(r.released_jobs()));
    EXPECT_LE(r.started_cycles(), r.released_jobs());
    EXPECT_GE(st.missed, st.aborted);
    // Under SCHED_FIFO a cycle that reached the section with its deadline
    // ahead was aborted at leave. Only one woken after its deadline (a loaded
    // host, TCG in the PREEMPT_RT guest) may complete: the watchdog saw no job
    // running in time. Best effort (other) gives the watchdog no such edge.
    if (GetParam() == Backend::fifo) {
        EXPECT_EQ(early_and_completed.load(), 0);
    }
}

TEST_P(MufFailures, AbortOutsideASectionJumpsToTheMark) {
    RtpuScheduler sch(options(GetParam()));
    Probe probe;
    probe.action = FailureAction::abort_cycle;
    probe.act_on = Failure::maxexec;
    std::atomic<int> finished{0};
    Runner r(sch, task("runaway", 40 * ms, 3 * ms),
             [&] {
                 burn_cpu(15 * ms);
                 finished.fetch_add(1);
             },
             &probe);
    ASSERT_TRUE(r.start()) << r.error();
    ASSERT_TRUE(eventually([&] { return sch.status(r.handle()).aborted >= 3; }));
    r.stop();
    const RtTaskStatus st = sch.status(r.handle());
    EXPECT_EQ(probe.wrong_thread.load(), 0);
    EXPECT_EQ(st.aborted, st.maxexec_failures);
    EXPECT_EQ(static_cast<std::uint64_t>(finished.load()) + st.aborted,
              static_cast<std::uint64_t>(r.started_cycles()));
    // The kernel checks CPU-time timers at its tick, on the thread then
    // running: a SCHED_FIFO task that burns 12 ms past its budget is caught
    // every time; under SCHED_OTHER on a loaded machine it may not be current
    // at a tick before the cycle ends.
    if (GetParam() == Backend::fifo) {
        EXPECT_EQ(finished.load(), 0);
    }
}

TEST_P(MufFailures, SkipNextSkipsOneRelease) {
    RtpuScheduler sch(options(GetParam()));
    Probe probe;
    probe.action = FailureAction::skip_next;
    probe.act_on = Failure::deadline;
    RtTaskParams p = task("skipper", 30 * ms, 20 * ms, 5 * ms);
    p.maxexec_check = false;
    Runner r(sch, p, [] { std::this_thread::sleep_for(10ms); }, &probe);
    ASSERT_TRUE(r.start()) << r.error();
    ASSERT_TRUE(eventually([&] { return probe.count[1].load() >= 4; }));
    r.stop();
    // Every cycle misses its deadline and asks to skip the next release, so
    // cycles and skipped releases alternate. A handler run only after the
    // next job began (best effort on a loaded machine: 4 runs in 10 at load
    // 10; SCHED_FIFO too in the guest whose emulated CPU the host starves)
    // makes two misses share one skip, which is still a skip.
    EXPECT_GE(r.skipped(), 1);
    EXPECT_LE(r.skipped(), probe.count[1].load());
}

TEST_P(MufFailures, HandlerRunsAtItsCriticalityAndMaySetANewOne) {
    RtpuScheduler sch(options(GetParam()));
    Probe restore, keep;
    RtTaskParams p = task("soft", 40 * ms, 2 * ms);
    p.crit = 5;
    Runner a(sch, p, [] { burn_cpu(12 * ms); }, &restore, /*handler_crit=*/6);
    ASSERT_TRUE(a.start()) << a.error();
    ASSERT_TRUE(eventually([&] { return restore.count[2].load() >= 2; }));
    EXPECT_EQ(restore.crit_in_handler.load(), 6);  // the handler priority
    EXPECT_EQ(sch.status(a.handle()).crit, 5);     // restored afterwards
    a.stop();

    // Listing 2: MAXEXEC lowers the task to 3, and it stays there.
    keep.set_crit_to = 3;
    p.name = "lowered";
    Runner b(sch, p, [] { burn_cpu(12 * ms); }, &keep, /*handler_crit=*/5);
    ASSERT_TRUE(b.start()) << b.error();
    ASSERT_TRUE(eventually([&] { return keep.count[2].load() >= 1; }));
    EXPECT_EQ(sch.status(b.handle()).crit, 3);
    b.stop();
}

// The job during which its task is removed is accounted as any other: the
// deadlines the watchdog reported while it ran are misses too (they were
// failures without misses, the difference growing with each period the last
// job overran), and so are the releases it overran.
TEST_P(MufFailures, AJobDuringWhichItsTaskIsRemovedIsAccountedAsAnyOther) {
    RtpuScheduler sch(options(GetParam()));
    RtTaskParams p = task("removed", 20 * ms, 15 * ms);
    p.maxexec_check = false;
    Runner r(sch, p, [] { std::this_thread::sleep_for(50ms); });  // overruns two deadlines
    ASSERT_TRUE(r.start()) << r.error();
    ASSERT_TRUE(eventually([&] { return sch.status(r.handle()).deadline_failures >= 1; }));
    r.stop();  // during the first job, whose deadline the watchdog reported
    const RtTaskStatus st = sch.status(r.handle());
    EXPECT_GE(st.deadline_failures, 1u);
    EXPECT_EQ(st.deadline_failures, st.missed) << st.cycles << " cycles";
}

INSTANTIATE_TEST_SUITE_P(Backends, MufFailures, ::testing::Values(Backend::fifo, Backend::other),
                         [](const auto& info) { return std::string(to_string(info.param)); });

// ------------------------------------------------------------------ thesis task API

namespace {

struct SoftTask {
    std::atomic<int> deadline{0}, maxexec{0};
    std::int64_t next = 0;
    std::int64_t period = 0;
    std::int64_t effective = 0;
};

FailureAction soft_handler(Failure kind, void* user) {
    auto* t = static_cast<SoftTask*>(user);
    switch (kind) {
        case Failure::deadline:  // missed: back to 5, continue with the next cycle's time
            t->deadline.fetch_add(1);
            set_criticality(5);
            t->next += t->period;
            set_deadline(t->next, 0, t->effective, t->period);
            break;
        case Failure::maxexec:  // E used up: lower to 3 and go on in left-over time
            t->maxexec.fetch_add(1);
            set_criticality(3);
            break;
        case Failure::minexec: break;
    }
    return FailureAction::resume;
}

}  // namespace

TEST(MufTaskApi, SoftRealTimeTaskOfListing2) {
    RtpuScheduler sch(options(Backend::fifo));
    RtTaskParams p = task("soft", 40 * ms, 30 * ms);
    p.effective_ns = 5 * ms;
    const TaskHandle h = sch.add_task(p);
    SoftTask soft;
    soft.period = 40 * ms;
    soft.effective = 5 * ms;
    std::atomic<int> crit_after_maxexec{-1};
    std::atomic<std::int64_t> measured{0};
    std::thread th([&] {
        sch.attach_current_thread(h);
        set_dfhandler(soft_handler, 5, &soft);
        soft.next = clock_ns();
        for (int i = 0; i < 4; ++i) {
            soft.next += soft.period;
            set_criticality(5);
            pause(soft.next, 0, soft.effective, soft.period);
            const std::int64_t start = execstart();
            // More than E by three ticks: the kernel checks CPU-time timers at
            // its tick (4 ms at HZ=250), so MAXEXEC comes up to a tick late.
            burn_cpu(17 * ms);
            measured.store(execend() - start);
            crit_after_maxexec.store(criticality());
        }
        sch.detach_current_thread(h);
    });
    th.join();
    EXPECT_EQ(soft.maxexec.load(), 4);
    EXPECT_EQ(crit_after_maxexec.load(), 3);
    EXPECT_GE(measured.load(), 17 * ms);  // execend - execstart is the CPU time used
    EXPECT_EQ(sch.status(h).maxexec_failures, 4u);
}

TEST(MufTaskApi, ExecleftCountsDownAndSetDeadlineRaisesMinexec) {
    RtpuScheduler sch(options(Backend::other));
    const TaskHandle h = sch.add_task(task("api", 100 * ms, 50 * ms));
    std::atomic<std::int64_t> left_before{0}, left_after{0};
    std::atomic<int> minexec{0};
    std::thread th([&] {
        sch.attach_current_thread(h);
        set_dfhandler(
            [](Failure kind, void* u) {
                if (kind == Failure::minexec) static_cast<std::atomic<int>*>(u)->fetch_add(1);
                return FailureAction::resume;
            },
            0, &minexec);
        set_deadline(clock_ns(), 0, 40 * ms, 100 * ms);
        left_before.store(execleft());
        burn_cpu(10 * ms);
        left_after.store(execleft());
        // 5 ms of minimum work before a deadline 1 ms away: MINEXEC at once.
        set_deadline(clock_ns(), 5 * ms, 40 * ms, 1 * ms);
        sch.detach_current_thread(h);
    });
    th.join();
    EXPECT_GT(left_before.load(), 35 * ms);
    EXPECT_LE(left_before.load(), 40 * ms);
    EXPECT_LE(left_after.load(), 30 * ms);
    EXPECT_EQ(minexec.load(), 1);
    EXPECT_EQ(sch.status(h).minexec_failures, 1u);
}

// ------------------------------------------------------------------ fifo backend

// The ranking keeps placed priorities where it can (fewer changes), but a task
// just attached is not placed: a lone task, and the most urgent of a set, go to
// the top of the band, never left at fifo_low below every other real-time
// thread of the machine (threaded IRQs run at 50 on PREEMPT_RT). A 1 kHz chain
// of one combined task ran at SCHED_FIFO 10 for good before.
TEST(MufFifo, TheMostUrgentTaskIsPlacedAtTheTopOfTheBand) {
    for (const bool harmonic : {true, false}) {
        SCOPED_TRACE(harmonic ? "static ranking" : "dynamic ranking");
        RtpuScheduler sch(options(Backend::fifo));
        if (!sch.privileged()) GTEST_SKIP() << "SCHED_FIFO refused on this machine";
        // Each job notes the priority it runs at (under dynamic ranking a task
        // waits for its release at the dispatcher's, fifo_high, to rank itself).
        std::array<std::atomic<int>, 2> running_at{};
        const auto note = [](std::atomic<int>& at) { return [&at] { at.store(fifo_priority_of(0)); }; };
        std::vector<std::unique_ptr<Runner>> runners;
        runners.push_back(std::make_unique<Runner>(sch, task("lone", 10 * ms, 0), note(running_at[0])));
        ASSERT_TRUE(runners[0]->start()) << runners[0]->error();
        ASSERT_TRUE(eventually([&] { return sch.status(runners[0]->handle()).cycles >= 2; }));
        EXPECT_EQ(running_at[0].load(), sch.options().fifo_high - 1);
        // A second, less urgent (longer period; non-harmonic: dynamic ranking).
        runners.push_back(std::make_unique<Runner>(sch, task("second", harmonic ? 20 * ms : 15 * ms, 0),
                                                   note(running_at[1])));
        ASSERT_TRUE(runners[1]->start()) << runners[1]->error();
        const std::uint64_t lone_now = sch.status(runners[0]->handle()).cycles;
        ASSERT_TRUE(eventually([&] {
            return sch.status(runners[1]->handle()).cycles >= 2 && sch.status(runners[0]->handle()).cycles >= lone_now + 2;
        }));
        EXPECT_EQ(sch.static_ranking(), harmonic);
        EXPECT_EQ(running_at[0].load(), sch.options().fifo_high - 1);
        EXPECT_GT(running_at[1].load(), sch.options().fifo_low);
        EXPECT_LT(running_at[1].load(), sch.options().fifo_high);
        // Fixed ranks: the second below the first. Dynamic ranking orders only
        // the jobs pending together, so a job running alone is at the top
        // (the order of pending jobs: DispatcherPrioritiesFollowTheUrgencyOrder).
        if (harmonic) {
            EXPECT_LT(running_at[1].load(), running_at[0].load());
        }
        runners.clear();
    }
}

TEST(MufFifo, DispatcherPrioritiesFollowTheUrgencyOrder) {
    for (Policy policy : {Policy::muf, Policy::rm, Policy::edf}) {
        SCOPED_TRACE(std::string(to_string(policy)));
        RtpuOptions o = options(Backend::fifo, policy);
        RtpuScheduler sch(o);
        if (!sch.privileged()) GTEST_SKIP() << "SCHED_FIFO refused on this machine";
        // Released together; each cycle blocks on a gate, so every job stays
        // pending and all compete at once. Periods, deadlines, explicit
        // criticality and user priority are chosen so RM, EDF and MUF differ.
        struct Spec {
            const char* name;
            std::int64_t period, deadline;
            std::optional<int> crit, uprio;
        };
        const Spec specs[] = {
            {"p10d9", 100 * ms, 90 * ms, std::nullopt, 1},
            {"p20d3", 200 * ms, 30 * ms, std::nullopt, 2},
            {"p30d6", 300 * ms, 60 * ms, 3, 3},
            {"p40d6", 400 * ms, 60 * ms, std::nullopt, 4},
            {"p50d6", 500 * ms, 60 * ms, std::nullopt, 5},
        };
        std::atomic<bool> gate{false};
        std::atomic<int> inside{0};
        const std::int64_t start = clock_ns() + 30 * ms;
        std::vector<std::unique_ptr<Runner>> runners;
        for (const Spec& s : specs) {
            RtTaskParams p = task(s.name, s.period, 1 * ms, s.deadline);
            p.crit = s.crit;
            p.uprio = s.uprio;
            p.first_release_ns = start;
            p.maxexec_check = false;
            runners.push_back(std::make_unique<Runner>(sch, p, [&] {
                inside.fetch_add(1);
                while (!gate.load()) std::this_thread::sleep_for(1ms);
            }));
        }
        for (auto& r : runners) ASSERT_TRUE(r->start()) << r->error();
        ASSERT_TRUE(eventually([&] { return inside.load() == 5; }));
        // Expected order: the urgency of Figure 6.2 from the analysis.
        const Assignment as = sch.assignment();
        std::vector<std::pair<std::uint64_t, std::size_t>> order;
        for (std::size_t i = 0; i < runners.size(); ++i) {
            const std::optional<std::int64_t> ticks =
                as.uses_deadline ? std::optional<std::int64_t>(specs[i].deadline / o.tick_ns)
                                 : std::nullopt;
            order.emplace_back(urgency(o.encoding, as.crit[i], ticks, as.uprio[i]), i);
        }
        std::sort(order.begin(), order.end(), std::greater<>());
        std::vector<int> prios;
        for (const auto& [u, i] : order) {
            prios.push_back(fifo_priority_of(runners[i]->tid()));
            EXPECT_EQ(sch.status(runners[i]->handle()).priority, prios.back());
        }
        for (std::size_t k = 0; k < prios.size(); ++k) {
            EXPECT_GE(prios[k], o.fifo_low);
            EXPECT_LT(prios[k], o.fifo_high);
            if (k > 0) {
                EXPECT_LT(prios[k], prios[k - 1]) << "rank " << k;
            }
        }
        EXPECT_NE(sch.policy_of(runners[0]->handle()).find("SCHED_FIFO"), std::string::npos);
        EXPECT_NE(sch.policy_of(runners[0]->handle()).find("CPU " + std::to_string(o.cpu)),
                  std::string::npos);
        gate.store(true);
        for (auto& r : runners) r->stop();
    }
}

TEST(MufFifo, SetPeriodTakesEffectAtTheNextRelease) {
    RtpuScheduler sch(options(Backend::fifo));
    std::atomic<int> cycles{0};
    Runner r(sch, task("rate", 40 * ms, 1 * ms), [&] { cycles.fetch_add(1); });
    ASSERT_TRUE(r.start()) << r.error();
    auto releases = [&] {
        const RtTaskStatus st = sch.status(r.handle());
        return static_cast<std::int64_t>(st.cycles + st.missed);
    };
    std::this_thread::sleep_for(50ms);
    std::int64_t before = releases();
    std::this_thread::sleep_for(400ms);
    const std::int64_t slow = releases() - before;  // about 10
    sch.set_period(r.handle(), 10 * ms);
    std::this_thread::sleep_for(60ms);
    before = releases();
    std::this_thread::sleep_for(400ms);
    const std::int64_t fast = releases() - before;  // about 40
    r.stop();
    // Releases follow the absolute timeline, so the counts are exact to the
    // window's edges; a wide margin keeps a noisy machine out of it.
    EXPECT_GE(slow, 8);
    EXPECT_LE(slow, 12);
    EXPECT_GE(fast, 34);
    EXPECT_LE(fast, 42);
}

// ------------------------------------------------------------------ deadline backend

// SCHED_DEADLINE is admitted to a thread pinned to one CPU only where that CPU
// is a root domain of its own: the RTPU's task gets its CPU through an exclusive
// cpuset partition (made here where the system offers one: the PREEMPT_RT
// guest), and is refused, naming what to do, where the CPU is not one.
RtpuOptions partition_options(const CpuPartition& part) {
    RtpuOptions o = options(Backend::deadline);
    o.cpu = part.cpu();
    return o;
}

TEST(MufDeadline, RefusesAReservationOnACpuThatIsNotAPartition) {
    RtpuScheduler sch(options(Backend::deadline));
    if (!sch.privileged()) GTEST_SKIP() << "no real-time privilege";
    if (get_nprocs() < 2) GTEST_SKIP() << "one CPU: it is the whole root domain";
    Runner crit_task(sch, task("reserved", 50 * ms, 5 * ms), [] {});
    ASSERT_FALSE(crit_task.start()) << sch.policy_of(crit_task.handle());
    const std::string& e = crit_task.error();
    EXPECT_NE(e.find("task 'reserved'"), std::string::npos) << e;
    EXPECT_NE(e.find("needs CPU " + std::to_string(rt_cpu()) + " to be an exclusive cpuset partition"),
              std::string::npos)
        << e;
    EXPECT_NE(e.find("this process may run on CPUs "), std::string::npos) << e;
    EXPECT_NE(e.find("BACKEND fifo"), std::string::npos) << e;
}

TEST(MufDeadline, AdmitsAFeasibleCriticalSetOnItsPartitionAndSignalsOverrunAsMaxexec) {
    CpuPartition part;
    if (!part.made()) GTEST_SKIP() << part.reason();
    RtpuScheduler sch(partition_options(part));
    Probe probe;
    Runner crit_task(sch, task("reserved", 50 * ms, 5 * ms), [] { burn_cpu(15 * ms); }, &probe);
    // 0.95 on top of 0.1: outside the critical set, so on SCHED_FIFO.
    Runner other(sch, task("light", 100 * ms, 95 * ms), [] { burn_cpu(ms / 2); });
    ASSERT_TRUE(crit_task.start()) << crit_task.error();
    const std::string policy = sch.policy_of(crit_task.handle());
    ASSERT_TRUE(other.start()) << other.error();
    EXPECT_NE(policy.find("SCHED_DEADLINE 5000000/50000000"), std::string::npos) << policy;
    EXPECT_NE(policy.find("CPU " + std::to_string(part.cpu()) + ", a root domain of its own"), std::string::npos)
        << policy;
    ASSERT_TRUE(eventually([&] { return probe.count[2].load() >= 2; }));
    EXPECT_EQ(probe.wrong_thread.load(), 0);
    EXPECT_EQ(sch.status(crit_task.handle()).priority, 0);
    EXPECT_NE(sch.policy_of(other.handle()).find("SCHED_FIFO"), std::string::npos)
        << sch.policy_of(other.handle());
    // Its first release is the next instant of its 100 ms timeline: under
    // emulation (the PREEMPT_RT guest) that can come after the two overruns.
    EXPECT_TRUE(eventually([&] { return sch.status(other.handle()).cycles >= 1; }));
    crit_task.stop();
    other.stop();
}

// The reserved task stays on its RTPU's CPU, and every deadline it misses is a
// miss in its status: no job ends late uncounted.
TEST(MufDeadline, AReservedTaskStaysOnItsCpuAndCountsEachLateJobAsAMiss) {
    CpuPartition part;
    if (!part.made()) GTEST_SKIP() << part.reason();
    RtpuScheduler sch(partition_options(part));
    std::atomic<int> wrong_cpu{0}, jobs{0};
    // 3 ms of CPU against a 2 ms budget every 20 ms: each job is throttled to
    // the next period and ends after its deadline.
    Runner late(sch, task("late", 20 * ms, 2 * ms), [&] {
        burn_cpu(3 * ms);
        if (sched_getcpu() != part.cpu()) wrong_cpu.fetch_add(1);
        jobs.fetch_add(1);
    });
    ASSERT_TRUE(late.start()) << late.error();
    ASSERT_TRUE(eventually([&] { return jobs.load() >= 10; }));
    late.stop();
    const RtTaskStatus st = sch.status(late.handle());
    EXPECT_EQ(wrong_cpu.load(), 0);
    EXPECT_GE(st.deadline_failures, 5u);
    // Equal: the job during which stop() removed the task is accounted too,
    // with the releases it overran (a starved guest once stretched it over
    // two deadlines, both failures, neither a miss).
    EXPECT_EQ(st.deadline_failures, st.missed) << st.cycles << " cycles";
}

TEST(MufDeadline, RefusesAnInfeasibleSetNamingItsUtilisation) {
    // The RTPU's critical set fits its CPU (0.97), but the kernel admits 0.95
    // of a CPU: the reservation is refused.
    CpuPartition part;
    if (!part.made()) GTEST_SKIP() << part.reason();
    RtpuScheduler sch(partition_options(part));
    Runner heavy(sch, task("heavy", 100 * ms, 97 * ms), [] { std::this_thread::sleep_for(1ms); });
    ASSERT_FALSE(heavy.start()) << "the kernel admitted a reservation of 0.97";
    const std::string& refusal = heavy.error();
    EXPECT_NE(refusal.find("admission refused"), std::string::npos) << refusal;
    EXPECT_NE(refusal.find("utilisation is 0.970"), std::string::npos) << refusal;
    EXPECT_NE(refusal.find("of CPU " + std::to_string(part.cpu())), std::string::npos) << refusal;
    EXPECT_NE(refusal.find("task 'heavy'"), std::string::npos) << refusal;
}

// ------------------------------------------------------------------ no privilege

TEST(MufFifo, WithoutPrivilegeWarnsRunsBestEffortAndStillDetectsFailures) {
    // A child process that gave up root (and any real-time allowance).
    const pid_t child = fork();
    ASSERT_GE(child, 0);
    if (child == 0) {
        rlimit none{0, 0};
        setrlimit(RLIMIT_RTPRIO, &none);
        if (getuid() == 0 && setresuid(65534, 65534, 65534) != 0) _exit(10);
        RtpuScheduler sch(options(Backend::fifo));
        if (sch.privileged()) _exit(11);
        Probe probe;
        RtTaskParams p = task("plain", 20 * ms, 10 * ms, 5 * ms);
        p.maxexec_check = false;
        Runner r(sch, p, [] { std::this_thread::sleep_for(8ms); }, &probe);
        if (!r.start()) _exit(12);
        if (!eventually([&] { return probe.count[1].load() >= 2; })) _exit(13);
        const std::string pol = sch.policy_of(r.handle());
        if (pol.find("SCHED_OTHER") == std::string::npos || pol.find("no privilege") == std::string::npos)
            _exit(14);
        if (probe.wrong_thread.load() != 0) _exit(15);
        r.stop();
        _exit(0);
    }
    int status = 0;
    ASSERT_EQ(waitpid(child, &status, 0), child);
    ASSERT_TRUE(WIFEXITED(status));
    EXPECT_EQ(WEXITSTATUS(status), 0)
        << "10 setresuid, 11 still privileged, 12 attach, 13 no DEADLINE, 14 policy text, 15 thread";
}

// --- Static ranking: one wake-up per release, no dispatcher on the release path

TEST(MufStatic, HarmonicImplicitDeadlinesRankStaticallyAndTasksReleaseThemselves) {
    RtpuScheduler sch(options(Backend::fifo));
    if (!sch.privileged()) GTEST_SKIP() << "SCHED_FIFO refused on this machine";
    std::atomic<int> n5{0}, n10{0}, n20{0};
    Runner a(sch, task("p20", 20 * ms, 0), [&] { n20.fetch_add(1); });
    Runner b(sch, task("p5", 5 * ms, 0), [&] { n5.fetch_add(1); });
    Runner c(sch, task("p10", 10 * ms, 0), [&] { n10.fetch_add(1); });
    ASSERT_TRUE(a.start() && b.start() && c.start());
    EXPECT_TRUE(sch.static_ranking());
    ASSERT_TRUE(eventually([&] { return n20.load() >= 3; }));
    // Fixed priorities in deadline order: the shortest period highest.
    const int p5 = fifo_priority_of(b.tid()), p10 = fifo_priority_of(c.tid()), p20 = fifo_priority_of(a.tid());
    EXPECT_GT(p5, p10);
    EXPECT_GT(p10, p20);
    // Steady state: the tasks go on releasing themselves while the dispatcher
    // neither runs nor changes a priority.
    const std::uint64_t rescheds = sch.reschedules(), changes = sch.priority_changes();
    const int before = n5.load();
    ASSERT_TRUE(eventually([&] { return n5.load() >= before + 20; }));
    EXPECT_EQ(sch.reschedules(), rescheds);
    EXPECT_EQ(sch.priority_changes(), changes);
    EXPECT_EQ(fifo_priority_of(b.tid()), p5);
    EXPECT_EQ(sch.status(b.handle()).priority, p5);
}

TEST(MufStatic, NonHarmonicOrConstrainedDeadlinesStayWithTheDispatcher) {
    {
        RtpuScheduler sch(options(Backend::fifo));
        if (!sch.privileged()) GTEST_SKIP() << "SCHED_FIFO refused on this machine";
        Runner a(sch, task("p10", 10 * ms, 0), [] {});
        Runner b(sch, task("p15", 15 * ms, 0), [] {});
        ASSERT_TRUE(a.start() && b.start());
        EXPECT_FALSE(sch.static_ranking());
    }
    {
        RtpuScheduler sch(options(Backend::fifo));
        Runner a(sch, task("p10", 10 * ms, 0), [] {});
        Runner b(sch, task("p20d8", 20 * ms, 0, 8 * ms), [] {});
        ASSERT_TRUE(a.start() && b.start());
        EXPECT_FALSE(sch.static_ranking());
        // RM ranks statically whatever the periods.
    }
    RtpuScheduler rm(options(Backend::fifo, Policy::rm));
    Runner a(rm, task("p10", 10 * ms, 0), [] {});
    Runner b(rm, task("p15", 15 * ms, 0), [] {});
    ASSERT_TRUE(a.start() && b.start());
    EXPECT_TRUE(rm.static_ranking());
}

// System calls of a task thread per cycle in steady state, counted by the
// kernel (raw_syscalls tracepoint): the wait for the release, plus one for
// the CPU budget of a task with a WCET; DEADLINE costs none (the task checks
// it at the job's end, the watchdog finds a job that never ends). Needs tracefs (registered as
// muf_rt_syscalls under tests/prof/in_tracefs_namespace.sh).
TEST(MufStatic, SystemCallsPerCycle) {
    if (chimera::test::open_syscall_counter() < 0) {
        if (std::getenv("CHIMERA_REQUIRE_SYSCALL_COUNTER"))
            FAIL() << "the raw_syscalls tracepoint cannot be opened (tracefs not mounted?)";
        GTEST_SKIP() << "no raw_syscalls tracepoint: tracefs not mounted (see in_tracefs_namespace.sh)";
    }
    // The release path reads the clock once per cycle. Where the vDSO cannot
    // serve CLOCK_MONOTONIC (a clocksource it cannot read, as under qemu's
    // emulation in the PREEMPT_RT guest), that read is a system call too.
    std::uint64_t clock_calls = 0;
    {
        const int fd = chimera::test::open_syscall_counter();
        const std::uint64_t before = chimera::test::read_syscall_counter(fd);
        for (int i = 0; i < 10; ++i) (void)clock_ns();
        clock_calls = chimera::test::read_syscall_counter(fd) - before - 1;
        ::close(fd);
    }
    const std::uint64_t clock_read = clock_calls >= 10 ? 1 : 0;
    if (clock_read) std::printf("CLOCK_MONOTONIC is a system call here (no vDSO clocksource): one more per cycle\n");
    for (const std::int64_t wcet : {std::int64_t{0}, 2 * ms}) {
        SCOPED_TRACE(wcet == 0 ? "no WCET" : "WCET 2 ms");
        RtpuScheduler sch(options(Backend::fifo));
        constexpr int kFrom = 20, kCycles = 100;
        std::atomic<int> n{0};
        int fd = -1;
        std::uint64_t first = 0, last = 0;
        RtTaskParams p = task("t", 2 * ms, wcet);
        Runner r(sch, p, [&] {
            const int k = n.fetch_add(1);
            if (k == kFrom) {
                fd = chimera::test::open_syscall_counter();
                first = chimera::test::read_syscall_counter(fd);
            } else if (k == kFrom + kCycles) {
                last = chimera::test::read_syscall_counter(fd);
            }
        });
        ASSERT_TRUE(r.start());
        ASSERT_TRUE(eventually([&] { return n.load() > kFrom + kCycles; }));
        r.stop();
        ::close(fd);
        ASSERT_GT(last, first);
        // One read of the counter is inside the window.
        const std::uint64_t calls = last - first - 1;
        // The wait, and for a WCET the budget timer armed at the release; the clock
        // is read twice (at the release and at the job's end, for DEADLINE).
        const std::uint64_t per_cycle = (wcet == 0 ? 1 : 2) + 2 * clock_read;
        EXPECT_LE(calls, per_cycle * kCycles) << calls << " system calls in " << kCycles << " cycles";
        EXPECT_GE(calls, kCycles) << "the wait alone is one per cycle: the counter missed calls";
    }
}

// Dynamic ranking (issue #14 item 3): a task is released at the priority it
// already has and makes no priority change where the MUF order holds, so a
// task thread's system calls per cycle are the wait alone; where the order
// does change, the only calls beyond the waits are the priority changes,
// counted in priority_changes(). Counted by the kernel per task thread from
// the test's thread, between two instants of the release timeline when every
// task sleeps. Needs tracefs (muf_rt_syscalls, under in_tracefs_namespace.sh).
namespace {

struct DynamicTask {
    const char* name;
    std::int64_t period, deadline, burn;
};
struct DynamicCount {
    std::vector<std::uint64_t> calls, cycles;
    std::uint64_t changes = 0, missed = 0;
    bool dynamic = false;
    bool on_time = true;  ///< both samples within a tenth of the quiet time of their instant
    /// The stall detector: the latest a job ended after the end the simulator
    /// gives it (from its release): what the machine took from the tasks.
    std::int64_t worst_late_ns = 0;
};

// How long after its release each job of one hyperperiod ends in the
// simulated schedule, per task, in job order: the set as the runtime assigns
// it (no WCET given), each job running its burn, in ticks of 1 us.
std::vector<std::vector<std::int64_t>> simulated_end_delays(const std::vector<DynamicTask>& tasks,
                                                            std::int64_t hyper) {
    constexpr std::int64_t us = 1000;
    std::vector<TaskSpec> specs;
    for (const DynamicTask& t : tasks) {
        TaskSpec spec;
        spec.name = t.name;
        spec.period = static_cast<double>(t.period / us);
        spec.deadline = static_cast<double>(t.deadline / us);
        specs.push_back(spec);
    }
    const Assignment a = assign(specs, Policy::muf);
    std::vector<SimTask> sim;
    for (std::size_t i = 0; i < tasks.size(); ++i)
        sim.push_back({.name = tasks[i].name, .period = tasks[i].period / us, .wcet = tasks[i].burn / us,
                       .deadline = tasks[i].deadline / us, .crit = a.crit[i], .uprio = a.uprio[i]});
    SimOptions so;
    so.late = LateJob::finish;
    so.use_deadline = a.uses_deadline;
    so.until = hyper / us;
    std::vector<std::vector<std::int64_t>> delays(tasks.size());
    for (const SimJob& j : simulate(sim, so).jobs) delays[j.task].push_back((j.finish - j.release) * us);
    return delays;
}

// A job of a counted set: burns, then tells the stall detector how late it
// ended. Wall-clock burn: CLOCK_MONOTONIC is read in the vDSO, where a
// thread's CPU clock is a system call; the one read beyond the burn's is
// counted by the tests where the clock is a call.
struct CountedJob {
    RtpuScheduler& sch;
    const std::vector<std::unique_ptr<Runner>>& runners;
    std::atomic<std::int64_t>& worst_late;
    const std::vector<std::int64_t>& end_delays;  // simulated_end_delays() of its task
    std::size_t task;
    std::int64_t burn, period, epoch;
    std::int64_t last_release = -1;

    void operator()() {
        if (burn > 0) burn_wall(burn);
        const std::int64_t release = sch.job_release_ns(runners[task]->handle());
        const auto job = static_cast<std::size_t>((release - epoch) / period) % end_delays.size();
        // Releases skipped (the task woke a period or more late) are as late as the time they cover.
        const std::int64_t skipped = last_release < 0 ? 0 : release - last_release - period;
        last_release = release;
        const std::int64_t late = std::max(clock_ns() - release - end_delays[job], skipped);
        if (late > worst_late.load(std::memory_order_relaxed)) worst_late.store(late, std::memory_order_relaxed);
    }
};

// Runs `tasks` from an epoch, and counts from `from` to `to` hyperperiods
// after it, at `quiet` into the hyperperiod (no task running then).
DynamicCount count_dynamic_cycles(const std::vector<DynamicTask>& tasks, std::int64_t hyper, std::int64_t quiet,
                                  int from, int to) {
    RtpuOptions o = options(Backend::fifo);
    o.epoch_ns = clock_ns() + 30 * ms;
    RtpuScheduler sch(o);
    std::vector<std::unique_ptr<Runner>> runners;
    const auto end_delays = simulated_end_delays(tasks, hyper);
    std::atomic<std::int64_t> worst_late{0};
    for (const DynamicTask& t : tasks) {
        RtTaskParams p = task(t.name, t.period, 0, t.deadline);
        const std::size_t i = runners.size();
        runners.push_back(std::make_unique<Runner>(
            sch, p, CountedJob{sch, runners, worst_late, end_delays[i], i, t.burn, t.period, o.epoch_ns}));
    }
    for (auto& r : runners)
        if (!r->start()) throw std::runtime_error(r->error());
    DynamicCount c;
    c.dynamic = !sch.static_ranking();
    std::vector<int> fds;
    for (auto& r : runners) fds.push_back(chimera::test::open_syscall_counter(r->tid()));
    // Sampled from above the band on the tasks' CPU (nothing of theirs runs
    // at those instants), so that the samples fall when meant; one that came
    // late may have fallen inside a cycle, and the run is not counted clean.
    cpu_set_t cpus, one;
    sched_getaffinity(0, sizeof cpus, &cpus);
    CPU_ZERO(&one);
    CPU_SET(static_cast<unsigned>(o.cpu), &one);
    sched_setaffinity(0, sizeof one, &one);
    sched_param above{};
    above.sched_priority = o.fifo_high + 5;
    sched_setscheduler(0, SCHED_FIFO, &above);
    const auto at = [&](int k) {
        const std::int64_t when = o.epoch_ns + k * hyper + quiet;
        std::this_thread::sleep_until(std::chrono::steady_clock::time_point(std::chrono::nanoseconds(when)));
        if (clock_ns() - when > quiet / 10) c.on_time = false;
    };
    // Misses and lateness are counted in the window too: the counts asserted
    // are, and the start (threads made, memory locked) is when a loaded
    // machine stalls most.
    std::vector<std::uint64_t> calls0, cycles0, missed0;
    at(from);
    for (std::size_t i = 0; i < runners.size(); ++i) {
        calls0.push_back(chimera::test::read_syscall_counter(fds[i]));
        cycles0.push_back(sch.status(runners[i]->handle()).cycles);
        missed0.push_back(sch.status(runners[i]->handle()).missed);
    }
    worst_late.store(0);  // no task runs now: this thread is above them on their CPU
    const std::uint64_t changes0 = sch.priority_changes();
    at(to);
    c.worst_late_ns = worst_late.load();
    for (std::size_t i = 0; i < runners.size(); ++i) {
        c.calls.push_back(chimera::test::read_syscall_counter(fds[i]) - calls0[i]);
        c.cycles.push_back(sch.status(runners[i]->handle()).cycles - cycles0[i]);
        c.missed += sch.status(runners[i]->handle()).missed - missed0[i];
    }
    c.changes = sch.priority_changes() - changes0;
    sched_param normal{};
    sched_setscheduler(0, SCHED_OTHER, &normal);
    sched_setaffinity(0, sizeof cpus, &cpus);
    for (int fd : fds) ::close(fd);
    for (auto& r : runners) r->stop();
    return c;
}

// Whether CLOCK_MONOTONIC is a system call here (no vDSO clocksource, as under
// qemu's emulation): then the release path's two clock reads count too.
std::uint64_t clock_read_is_a_system_call() {
    const int fd = chimera::test::open_syscall_counter();
    const std::uint64_t before = chimera::test::read_syscall_counter(fd);
    for (int i = 0; i < 10; ++i) (void)clock_ns();
    const std::uint64_t calls = chimera::test::read_syscall_counter(fd) - before - 1;
    ::close(fd);
    return calls >= 10 ? 1 : 0;
}

bool dynamic_counter_preconditions() {
    if (chimera::test::kSanitizer) {
        // The counts are structural and held by the plain build (suite stage);
        // a sanitizer's slower release path made every run of the 2 ms set
        // miss (asan stage, 5 of 5 runs flagged, 2026-12-02).
        std::printf("sanitizer build: the dynamic sets' 0.2-1.2 ms jobs do not fit its release path\n");
        return false;
    }
    if (chimera::test::open_syscall_counter() < 0) {
        if (std::getenv("CHIMERA_REQUIRE_SYSCALL_COUNTER"))
            ADD_FAILURE() << "the raw_syscalls tracepoint cannot be opened (tracefs not mounted?)";
        else
            std::printf("no raw_syscalls tracepoint: tracefs not mounted (see in_tracefs_namespace.sh)\n");
        return false;
    }
    if (!RtpuScheduler(options(Backend::fifo)).privileged()) {
        std::printf("SCHED_FIFO refused on this machine: no dispatched tasks to count\n");
        return false;
    }
    return true;
}

std::string describe(const DynamicCount& c, const std::vector<DynamicTask>& tasks) {
    std::string line = std::string(c.on_time ? "" : "(a sample came late) ") + "priority changes " +
                       std::to_string(c.changes) + ", missed " + std::to_string(c.missed) + ", a job " +
                       std::to_string(c.worst_late_ns / 1000) + " us late;";
    for (std::size_t i = 0; i < tasks.size(); ++i)
        line += std::string(" ") + tasks[i].name + " " + std::to_string(c.calls[i]) + " calls/" +
                std::to_string(c.cycles[i]) + " cycles";
    return line;
}

// Runs of the set (hyperperiods of 6 ms, counted from `from` to `to`) until
// one is `clean`; a run that is not is run again, up to five times, only when
// the test's stall detector says it was disturbed, and it prints so: a sample
// came late, or a job ended more than a tenth of the shortest period after
// the end the simulator gives it (the machine held the CPU:
// measured on a 2-vCPU Firecracker VM whose kernel does not preempt in kernel
// mode, a bare SCHED_FIFO sleeper there wakes up to 10 ms late at load 7).
// Jobs pending together in another order then rightly change priorities and
// miss. Stops at once on a set that does not rank dynamically.
template <typename Clean>
DynamicCount count_until_clean(const std::vector<DynamicTask>& tasks, int from, int to, Clean clean) {
    std::int64_t shortest = tasks.front().period;
    for (const DynamicTask& t : tasks) shortest = std::min(shortest, t.period);
    DynamicCount c;
    for (int attempt = 1; attempt <= 5; ++attempt) {
        c = count_dynamic_cycles(tasks, 6 * ms, 5 * ms, from, to);
        if (!c.dynamic) break;
        const bool disturbed = !c.on_time || c.worst_late_ns > shortest / 10;
        std::printf("run %d: %s%s\n", attempt, describe(c, tasks).c_str(),
                    disturbed ? " (disturbed: the machine held the CPU)" : "");
        if (clean(c) || !disturbed) break;
    }
    return c;
}

}  // namespace

TEST(MufDynamic, OneSystemCallPerCycleWhereTheRankingHolds) {
    if (!dynamic_counter_preconditions()) GTEST_SKIP() << "preconditions (printed above)";
    const std::uint64_t clock_read = clock_read_is_a_system_call();
    // A deadline shorter than its period (a) and a period that divides no
    // other (c): dynamic ranking. Light jobs: whenever two are pending the
    // more urgent was ranked above, and a waiting task is never below a less
    // urgent pending one, so no release changes a priority.
    const std::vector<DynamicTask> tasks = {
        {"a2d1", 2 * ms, 1 * ms, 0}, {"b2", 2 * ms, 0, 0}, {"c3", 3 * ms, 0, 0}};
    constexpr int from = 10, to = 60;  // hyperperiods of 6 ms: 300 ms, 350 cycles
    const DynamicCount c = count_until_clean(tasks, from, to, [&](const DynamicCount& r) {
        bool clean = r.on_time && r.changes == 0 && r.missed == 0;
        for (std::size_t i = 0; i < tasks.size(); ++i)
            clean = clean && r.calls[i] == r.cycles[i] * (1 + 3 * clock_read);
        return clean;
    });
    ASSERT_TRUE(c.dynamic) << "the set must rank dynamically";
    EXPECT_EQ(c.changes, 0u);
    for (std::size_t i = 0; i < tasks.size(); ++i) {
        SCOPED_TRACE(tasks[i].name);
        const std::uint64_t per_hyper = static_cast<std::uint64_t>(6 * ms / tasks[i].period);
        EXPECT_EQ(c.cycles[i], per_hyper * (to - from));
        // Exactly the wait, once per cycle (where the clock reads are calls,
        // the release path's two and the stall detector's one too).
        EXPECT_EQ(c.calls[i], c.cycles[i] * (1 + 3 * clock_read));
    }
}

TEST(MufDynamic, WhereTheRankingChangesTheOnlyOtherCallsAreTheCountedPriorityChanges) {
    if (!dynamic_counter_preconditions()) GTEST_SKIP() << "preconditions (printed above)";
    const std::uint64_t clock_read = clock_read_is_a_system_call();
    // In each 6 ms: at 0 both are released and b (deadline 2) goes first; a's
    // job of 3 (deadline 6) runs from 3 to 4.2 ms, when b's of 4 has the same
    // deadline and comes second (first come, first served): the order flips
    // twice, one priority change each (rank_priorities moves one task where a
    // single one can move). Quiet at 5 ms.
    const std::vector<DynamicTask> tasks = {{"a3", 3 * ms, 0, 12 * ms / 10}, {"b2", 2 * ms, 0, 2 * ms / 10}};
    constexpr int from = 10, to = 60;
    const DynamicCount c = count_until_clean(tasks, from, to, [&](const DynamicCount& r) {
        const std::uint64_t calls = r.calls[0] + r.calls[1];
        const std::uint64_t cycles = r.cycles[0] + r.cycles[1];
        return r.on_time && r.missed == 0 && r.changes == 2u * (to - from) &&
               calls == cycles * (1 + 3 * clock_read) + r.changes;
    });
    ASSERT_TRUE(c.dynamic) << "the set must rank dynamically";
    EXPECT_EQ(c.cycles[0], 2u * (to - from));
    EXPECT_EQ(c.cycles[1], 3u * (to - from));
    EXPECT_EQ(c.changes, 2u * (to - from)) << "two flips of the order per 6 ms, one change each";
    // Every call beyond the waits is a priority change the scheduler counted.
    EXPECT_EQ(c.calls[0] + c.calls[1], (c.cycles[0] + c.cycles[1]) * (1 + 3 * clock_read) + c.changes);
}

// Memory locked once a scheduler has real-time privilege (docs/muf.md; not in a
// sanitizer build, which says so), and no page fault in a task's steady-state
// cycles: counted by the kernel per thread.
TEST(MufStatic, MemoryIsLockedAndCyclesDoNotPageFault) {
    RtpuScheduler sch(options(Backend::fifo));
    if (!sch.privileged()) GTEST_SKIP() << "SCHED_FIFO refused: the runtime locks memory only with privilege";
    if (chimera::test::kSanitizer) {
        EXPECT_EQ(chimera::muf::detail::lock_memory(), "memory not locked (sanitizer build)");
    } else if (std::getenv("CHIMERA_NO_MLOCK") == nullptr) {
        std::ifstream status("/proc/self/status");
        std::string line;
        long locked_kb = -1;
        while (std::getline(status, line))
            if (line.rfind("VmLck:", 0) == 0) locked_kb = std::stol(line.substr(6));
        EXPECT_GT(locked_kb, 0) << "mlockall was not called";
    }
    constexpr int kFrom = 20, kCycles = 100;
    std::atomic<int> n{0};
    long faults_before = -1, faults_after = -1;
    Runner r(sch, task("t", 2 * ms, 0), [&] {
        const int k = n.fetch_add(1);
        if (k != kFrom && k != kFrom + kCycles) return;
        rusage u{};
        getrusage(RUSAGE_THREAD, &u);
        (k == kFrom ? faults_before : faults_after) = u.ru_minflt + u.ru_majflt;
    });
    ASSERT_TRUE(r.start());
    ASSERT_TRUE(eventually([&] { return n.load() > kFrom + kCycles; }));
    r.stop();
    EXPECT_EQ(faults_after - faults_before, 0) << "page faults in " << kCycles << " steady-state cycles";
}

// §6.2.4 on real threads: three tasks of one rate on one RTPU, spawned robot
// first, are ordered by their data flow — trajectory, then PID, then robot —
// in every period, so a new reference reaches the robot in the period it is made.
TEST(MufStatic, DataFlowOrdersTasksOfOneRateInEveryPeriod) {
    RtpuScheduler sch(options(Backend::fifo));
    if (!sch.privileged()) GTEST_SKIP() << "SCHED_FIFO refused: the order is set by FIFO priorities";
    constexpr int kLog = 3 * 100;
    // Each job logs its release instant: a release a loaded machine made a
    // task miss shifts no other period's order (a fixed stride of 3 would).
    struct Entry {
        std::atomic<std::int64_t> release{0};
        std::atomic<int> id{0};
    };
    std::array<Entry, kLog> log{};
    std::array<std::atomic<TaskHandle>, 4> handles{};
    std::atomic<int> next{0};
    auto runner = [&](const char* name, int id, std::vector<std::string> in, std::vector<std::string> out) {
        RtTaskParams p = task(name, 5 * ms, 0);
        p.inputs = std::move(in);
        p.outputs = std::move(out);
        auto r = std::make_unique<Runner>(sch, p, [&, id] {
            const int k = next.fetch_add(1);
            if (k >= kLog) return;
            log[static_cast<std::size_t>(k)].release.store(sch.job_release_ns(handles[static_cast<std::size_t>(id)]));
            log[static_cast<std::size_t>(k)].id.store(id);
        });
        handles[static_cast<std::size_t>(id)].store(r->handle());
        return r;
    };
    auto robot = runner("robot", 3, {"T_REF"}, {"Q_MEZ"});
    auto pid = runner("jpid", 2, {"Q_REF", "Q_MEZ"}, {"T_REF"});
    auto traj = runner("jtraj", 1, {}, {"Q_REF"});
    // All three released at the same instants: the epoch-aligned timeline.
    ASSERT_TRUE(robot->start() && pid->start() && traj->start());
    EXPECT_TRUE(sch.static_ranking());
    const Assignment as = sch.assignment();
    ASSERT_EQ(as.uprio.size(), 3u);
    EXPECT_LT(as.uprio[0], as.uprio[1]);  // robot below jpid
    EXPECT_LT(as.uprio[1], as.uprio[2]);  // jpid below jtraj
    ASSERT_TRUE(eventually([&] { return next.load() >= kLog; }));
    robot->stop();
    pid->stop();
    traj->stop();
    // The jobs of one release instant ran trajectory, PID, robot, in that
    // order (a task that missed the instant is absent from it, not late in it).
    std::map<std::int64_t, std::vector<int>> by_release;
    for (const Entry& e : log) by_release[e.release.load()].push_back(e.id.load());
    int complete = 0;
    for (const auto& [release, ids] : by_release) {
        EXPECT_TRUE(std::is_sorted(ids.begin(), ids.end()) && std::adjacent_find(ids.begin(), ids.end()) == ids.end())
            << "release " << release << ": order " << ::testing::PrintToString(ids);
        if (ids.size() == 3) ++complete;
    }
    EXPECT_GE(complete, 30);  // a loaded machine (CI at load 10) made 42 of 60 complete
}

// ------------------------------------------------------------------ Figure 6.1 on threads

// Issue #20.6: Figure 6.1's task set (tools/chimsched/examples/fig6_1.tasks,
// what `chimsched simulate` draws) on real SCHED_FIFO threads on one CPU, one
// time unit = 10 ms, for one hyperperiod (60 units): the tasks miss what the
// simulator says (RM: tau3 2, tau4 4; EDF: tau1 4, tau2 4; MUF: tau4 4 only).
// As the figure draws it, a job still running at its deadline is aborted there
// (its failure handler returns abort_cycle). The misses are events, counted;
// no time is asserted.
//
// The schedule has no slack in places: under EDF tau4 finishes exactly at its
// deadline at 15 and at 45, after 15 units of back-to-back jobs. A thread
// loses CPU time in proportion to the time it runs (the vCPU's steal time,
// the ticks, the dispatcher): measured 0.3-2 % on a 2-vCPU Firecracker VM,
// where a fixed 0.1 ms per job made tau4 miss at 15 and 45 in every run. So
// each job burns its WCET less kMarginPermille of it, and the simulator, run
// on those shortened jobs in ticks of unit/1000, must miss exactly what it
// misses on whole units: the margin changes no count (up to 4.5 % it does not).
class Figure6_1OnThreads : public ::testing::TestWithParam<Policy> {};

constexpr std::int64_t kMarginPermille = 30;
constexpr std::int64_t kTicksPerUnit = 1000;

// The figure's set in ticks of unit/1000, each job kMarginPermille shorter.
TaskSet figure6_1_burned(const TaskSet& set) {
    TaskSet fine = set;
    for (TaskSpec& t : fine.tasks) {
        t.period *= kTicksPerUnit;
        t.wcet = t.wcet * (kTicksPerUnit - kMarginPermille);
    }
    return fine;
}

struct FigureRun {
    std::vector<std::uint64_t> missed;  // per task: jobs of [0, 60) not completed
    std::int64_t attached_late_ns = 0;  // > 0: the set was attached after its first release
    std::int64_t lost_ns = 0;           // CPU time the simulator gives the jobs that the threads did not get
    std::int64_t excess_ns = 0;         // > 0: a stretch lost more than its jobs' margin
};

// CPU time the schedule gives the jobs in [0, t) (ticks).
std::int64_t busy_until(const SimResult& sim, std::int64_t t) {
    std::int64_t busy = 0;
    for (const SimSlice& s : sim.timeline) busy += std::max<std::int64_t>(0, std::min(s.end, t) - s.begin);
    return busy;
}

// The stall detector. At each sample (time from the first release, CPU time
// the task threads had), the threads' loss is the CPU time the simulated
// schedule of the burned set gives the jobs less what they had. A stretch
// between two samples that lost more than the margin of the CPU time in it
// may have made a job miss that the schedule does not.
void judge_losses(FigureRun& run, const TaskSet& burned, Policy policy, std::int64_t unit,
                  const std::vector<std::pair<std::int64_t, std::int64_t>>& samples) {
    const std::int64_t tick = unit / kTicksPerUnit;
    const SimResult sim = simulate(burned.tasks, policy, LateJob::abort, samples.back().first / tick + 1);
    std::vector<std::int64_t> busy, lost;
    for (const auto& [t, cpu] : samples) {
        busy.push_back(busy_until(sim, std::max<std::int64_t>(t, 0) / tick) * tick);
        lost.push_back(busy.back() - (cpu - samples.front().second));
    }
    run.lost_ns = lost.back();
    for (std::size_t j = 1; j < samples.size(); ++j)
        for (std::size_t i = 0; i < j; ++i)
            run.excess_ns = std::max(run.excess_ns, lost[j] - lost[i] - (busy[j] - busy[i]) * kMarginPermille / 1000);
}

// (time from `start`, CPU time the task threads had) now, once a unit, and
// half a unit after the hyperperiod (no job released before it runs on).
// Taken from another CPU than the tasks' where there is one.
std::vector<std::pair<std::int64_t, std::int64_t>> sample_task_cpu(
    const std::vector<std::unique_ptr<Runner>>& runners, int task_cpu, std::int64_t start, std::int64_t unit,
    std::int64_t hyperperiod) {
    const chimera::test::OnOtherCpus elsewhere(task_cpu);
    const auto sample = [&] {
        std::int64_t cpu = 0;
        for (auto& r : runners) cpu += cpu_time_of_thread(r->tid());
        return std::pair(clock_ns() - start, cpu);
    };
    std::vector<std::pair<std::int64_t, std::int64_t>> samples{sample()};
    for (std::int64_t k = 1; k <= hyperperiod + 1; ++k) {
        const std::int64_t at = start + std::min(k * unit, hyperperiod * unit + unit / 2);
        std::this_thread::sleep_until(std::chrono::steady_clock::time_point(std::chrono::nanoseconds(at)));
        samples.push_back(sample());
    }
    return samples;
}

struct OverloadRun {
    RtTaskStatus a, b, c;
    std::uint64_t reschedules = 0;
    std::int64_t worst_lost_ns = 0;  // the most time any 20 ms stretch gave neither the three tasks nor idle
};

// U = 0.35 + 0.35 + 0.40 = 1.10 of demand on one CPU for 620 ms. The stall
// detector (cpu_loss.hpp) samples every 5 ms from another CPU: a 20 ms
// stretch of which more than a's job margin (1 ms) went neither to the three
// threads nor to idle was the machine's (vCPU steal, a kernel that does not
// preempt), not MUF's.
OverloadRun run_overload(RtpuScheduler& sch) {
    auto make = [](const char* name, std::int64_t period, std::int64_t wcet) {
        RtTaskParams p = task(name, period, wcet);
        p.maxexec_check = false;
        return p;
    };
    const std::int64_t start = clock_ns() + 20 * ms;
    RtTaskParams pa = make("a", 20 * ms, 8 * ms), pb = make("b", 30 * ms, 12 * ms),
                 pc = make("c", 40 * ms, 16 * ms);
    pa.first_release_ns = pb.first_release_ns = pc.first_release_ns = start;
    std::vector<std::unique_ptr<Runner>> runners;
    runners.push_back(std::make_unique<Runner>(sch, pa, [] { burn_cpu(7 * ms); }));
    runners.push_back(std::make_unique<Runner>(sch, pb, [] { burn_cpu(21 * ms / 2); }));
    runners.push_back(std::make_unique<Runner>(sch, pc, [] { burn_cpu(16 * ms); }));
    const Assignment as = sch.assignment();
    EXPECT_EQ(as.crit, (std::vector<int>{crit::critical, crit::critical, crit::non_critical}));
    for (auto& r : runners) EXPECT_TRUE(r->start()) << r->error();
    std::this_thread::sleep_until(std::chrono::steady_clock::time_point(std::chrono::nanoseconds(start)));
    // Under a second of overload: the kernel's fair server lends the starved
    // SCHED_OTHER tasks time after about 0.95 s, which is not MUF's doing.
    OverloadRun run;
    run.worst_lost_ns = chimera::test::worst_cpu_loss({runners[0]->tid(), runners[1]->tid(), runners[2]->tid()},
                                                      sch.options().cpu, 620ms, 5ms, 20ms);
    run.a = sch.status(runners[0]->handle());
    run.b = sch.status(runners[1]->handle());
    run.c = sch.status(runners[2]->handle());
    run.reschedules = sch.reschedules();
    for (auto& r : runners) r->stop();
    return run;
}

TEST(MufFifo, OverloadOnlyTheNonCriticalTaskMisses) {
    OverloadRun run;
    for (int attempt = 1; attempt <= 3; ++attempt) {
        RtpuScheduler sch(options(Backend::fifo));
        if (!sch.privileged()) GTEST_SKIP() << "SCHED_FIFO refused on this machine: no overload test";
        run = run_overload(sch);
        const bool clean = run.a.missed + run.b.missed + run.a.deadline_failures + run.b.deadline_failures == 0;
        const bool disturbed = chimera::test::overload_run_disturbed(attempt, run.a.missed, run.b.missed,
                                                                     run.c.missed, run.worst_lost_ns);
        if (clean || !disturbed) break;
    }
    EXPECT_GE(run.a.cycles, 25u);
    EXPECT_GE(run.b.cycles, 16u);
    EXPECT_EQ(run.a.missed, 0u);
    EXPECT_EQ(run.b.missed, 0u);
    EXPECT_EQ(run.a.deadline_failures, 0u);
    EXPECT_EQ(run.b.deadline_failures, 0u);
    EXPECT_GT(run.c.missed + run.c.deadline_failures, 0u);
    EXPECT_GT(run.reschedules, 0u);
}

// One hyperperiod of `set` on threads under `policy`.
FigureRun figure6_1_on_threads(const TaskSet& set, Policy policy, std::int64_t unit, std::int64_t hyperperiod) {
    const RtpuOptions o = options(Backend::fifo, policy);
    RtpuScheduler sch(o);
    const std::int64_t start = clock_ns() + 100 * ms;
    const std::int64_t end = start + hyperperiod * unit;
    const TaskSet burned = figure6_1_burned(set);
    std::vector<std::unique_ptr<Probe>> probes;  // outlive the runners
    std::vector<std::unique_ptr<Runner>> runners;
    // Jobs released before the end and completed, counted by the job itself:
    // the look may come late, when jobs released at the end have completed.
    std::array<std::atomic<std::uint64_t>, 8> completed{};
    for (std::size_t i = 0; i < set.tasks.size(); ++i) {
        const TaskSpec& t = set.tasks[i];
        probes.push_back(std::make_unique<Probe>());
        probes.back()->action = FailureAction::abort_cycle;  // at its deadline a job is dropped
        RtTaskParams p = task(t.name.c_str(), static_cast<std::int64_t>(t.period) * unit,
                              static_cast<std::int64_t>(t.wcet) * unit);
        p.maxexec_check = false;  // the tasks run to their WCET by design
        p.first_release_ns = start;
        const auto burn = static_cast<std::int64_t>(burned.tasks[i].wcet) * (unit / kTicksPerUnit);
        runners.push_back(std::make_unique<Runner>(
            sch, p,
            [&, i, burn] {
                burn_cpu(burn);
                if (sch.job_release_ns(runners[i]->handle()) < end) completed[i].fetch_add(1);
            },
            probes.back().get()));
    }
    for (auto& r : runners)
        if (!r->start()) throw std::runtime_error(r->error());
    const auto samples = sample_task_cpu(runners, o.cpu, start, unit, hyperperiod);
    for (auto& r : runners) r->stop();
    FigureRun run;
    run.attached_late_ns = samples.front().first;
    judge_losses(run, burned, policy, unit, samples);
    for (std::size_t i = 0; i < set.tasks.size(); ++i)
        run.missed.push_back(static_cast<std::uint64_t>(hyperperiod / set.tasks[i].period) - completed[i].load());
    return run;
}

std::vector<std::uint64_t> simulated_misses(const TaskSet& set, Policy policy, std::int64_t until) {
    std::vector<std::uint64_t> m;
    for (const auto& s : simulate(set.tasks, policy, LateJob::abort, until).stats) m.push_back(s.missed);
    return m;
}

TEST_P(Figure6_1OnThreads, MissesWhatTheSimulatorMisses) {
    const Policy policy = GetParam();
    if (!RtpuScheduler(options(Backend::fifo, policy)).privileged())
        GTEST_SKIP() << "SCHED_FIFO refused on this machine: Figure 6.1 needs real-time threads on one CPU";
    const char* root = std::getenv("CHIMERA_SOURCE_ROOT");
    ASSERT_NE(root, nullptr) << "CHIMERA_SOURCE_ROOT is not set (meson test sets it)";
    const TaskSet set = read_task_set(std::string(root) + "/tools/chimsched/examples/fig6_1.tasks");
    constexpr std::int64_t unit = 10 * ms, hyperperiod = 60;
    const std::vector<std::uint64_t> want = simulated_misses(set, policy, hyperperiod);
    ASSERT_EQ(simulated_misses(figure6_1_burned(set), policy, hyperperiod * kTicksPerUnit), want)
        << "the jobs' margin changes what the simulator misses";
    // The CPU is shared with the other engineers' real-time tests and with the
    // hypervisor: a run in a stretch of which the task threads lost more CPU
    // time than the jobs' margin in it, or whose set was attached after its
    // first release (the test thread waited for a CPU), was disturbed
    // (measured, printed) and is run again, up to five times; any other
    // disagreement fails at once.
    FigureRun run;
    for (int attempt = 1; attempt <= 5; ++attempt) {
        if (attempt > 1) std::this_thread::sleep_for(200ms);
        run = figure6_1_on_threads(set, policy, unit, hyperperiod);
        std::string line;
        for (std::size_t i = 0; i < run.missed.size(); ++i)
            line += " " + set.tasks[i].name + " " + std::to_string(run.missed[i]) + "/" + std::to_string(want[i]);
        const bool late = run.attached_late_ns > 0;
        const bool disturbed = late || run.excess_ns > 0;
        char why[96] = "";
        if (late)
            std::snprintf(why, sizeof why, " (disturbed: the set was attached %.1f ms after its first release)",
                          run.attached_late_ns / 1e6);
        else if (disturbed)
            std::snprintf(why, sizeof why, " (disturbed: a stretch lost %.2f ms more than its jobs' margin)",
                          run.excess_ns / 1e6);
        std::printf("%s run %d, missed on threads/simulated:%s; the threads lost %.2f ms%s\n",
                    to_string(policy).data(), attempt, line.c_str(), run.lost_ns / 1e6, why);
        if (run.missed == want || !disturbed) break;
    }
    EXPECT_EQ(run.missed, want);
}

INSTANTIATE_TEST_SUITE_P(Policies, Figure6_1OnThreads, ::testing::Values(Policy::rm, Policy::edf, Policy::muf),
                         [](const auto& info) { return std::string(to_string(info.param)); });
