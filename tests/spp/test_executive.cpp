// The executive (chimexec, §7.4.2) and the task's SPP object (§7.4.1):
// commands of one task in issue order, each run to completion, the
// highest-priority pending command next between tasks, XFER in order with
// CALL, WAKEUP per task, argument checks, a full command buffer, finish, and
// routines that throw. Orders are made deterministic by holding the executive
// in a gate while commands queue, then opening it.
#include <gtest/gtest.h>

#include <bit>
#include <cerrno>
#include <cstring>
#include <thread>

#include "executive_fixture.hpp"

using namespace spp_test;
namespace spp = chimera::spp;
using Entries = std::vector<std::int64_t>;

using SppExecutive = ExecutiveTest;

TEST_F(SppExecutive, OneTasksCommandsRunInTheOrderItIssuedThem) {
    start();
    spp::Spp& s = task(1);
    const spp::Handle rec = s.translate("record");
    Entries expected;
    for (std::int64_t k = 0; k < 200; ++k) {
        // A non-monotonic pattern, so a buffer that reordered would show.
        const std::int64_t t = (k * 37) % 200;
        ASSERT_EQ(s.call(rec, tag(t)), 0);
        expected.push_back(t);
        if (k % 50 == 49) {
            ASSERT_EQ(s.wait(), 0);
        }
    }
    ASSERT_EQ(s.wait(), 0);
    EXPECT_EQ(journal.entries(), expected);
}

TEST_F(SppExecutive, BetweenTasksTheHighestPriorityPendingCommandGoesNextTiesInIssueOrder) {
    start();
    spp::Spp& holder = task(50);
    spp::Spp& low = task(5);
    spp::Spp& mid = task(10);
    spp::Spp& p = task(20);
    spp::Spp& q = task(20);
    hold_executive(holder, 1);
    // Issued in this order while the executive is held (first-come-first-served
    // would run them exactly so).
    record_all(low, {100});
    record_all(p, {200});
    record_all(mid, {300});
    record_all(q, {400});
    record_all(p, {201});
    record_all(low, {101});
    record_all(q, {401});
    record_all(mid, {301});
    gates[0].open();
    for (spp::Spp* s : {&holder, &p, &q, &mid, &low}) ASSERT_EQ(s->wait(), 0);
    // p and q tie at 20: their commands alternate by issue order.
    EXPECT_EQ(journal.entries(), (Entries{1, 200, 400, 201, 401, 300, 301, 100, 101}));
}

TEST_F(SppExecutive, ACommandRunsToCompletionAndAHigherPriorityOneGoesNextNotAfterTheWholeBuffer) {
    start();
    spp::Spp& low = task(1);
    spp::Spp& high = task(99);
    ASSERT_EQ(low.call(low.translate("bracket"), tag_gate(7, 1)), 0);
    gates[1].await_entered();
    record_all(low, {8, 9});
    record_all(high, {50, 51});
    gates[1].open();
    ASSERT_EQ(high.wait(), 0);
    ASSERT_EQ(low.wait(), 0);
    // bracket's end (-7) before anything of high's: not preempted; high's two
    // before low's 8 and 9: the executive picks again after every command.
    EXPECT_EQ(journal.entries(), (Entries{7, -7, 50, 51, 8, 9}));
}

// --- XFER --------------------------------------------------------------------------

TEST_F(SppExecutive, XferMovesTheRightBytesInIssueOrderWithTheCalls) {
    start();
    spp::Spp& s = task(1);
    const spp::Handle x = s.translate("x"), scale_fn = s.translate("scale"), add_fn = s.translate("add_to");
    const double in[kXDoubles] = {1, 2, 3, 4, 5, 6, 7, 8};
    double before[kXDoubles] = {}, after[kXDoubles] = {}, tail[2] = {};
    ASSERT_EQ(s.write(x, in, sizeof in), 0);
    ASSERT_EQ(s.read(x, before, sizeof before), 0);  // before the CALL: the written values
    ASSERT_EQ(s.call(scale_fn, spp::Args{}.add(x).add(2.0)), 0);
    ASSERT_EQ(s.read(x, after, sizeof after), 0);  // after it: scaled
    ASSERT_EQ(s.call(add_fn, spp::Args{}.add(x).add(7).add(0.5)), 0);
    ASSERT_EQ(s.read(x, tail, sizeof tail, 6 * sizeof(double)), 0);  // x[6], x[7]
    ASSERT_EQ(s.wait(), 0);
    for (std::size_t k = 0; k < kXDoubles; ++k) {
        EXPECT_EQ(before[k], in[k]) << k;
        EXPECT_EQ(after[k], 2 * in[k]) << k;
    }
    EXPECT_EQ(tail[0], 14.0);
    EXPECT_EQ(tail[1], 16.5);
}

TEST_F(SppExecutive, AWriteAtAnOffsetChangesOnlyThoseBytes) {
    start();
    spp::Spp& s = task(1);
    const spp::Handle y = s.translate("y");
    unsigned char ones[64], patch[5] = {9, 8, 7, 6, 5}, out[64] = {};
    std::memset(ones, 1, sizeof ones);
    ASSERT_EQ(s.write(y, ones, sizeof ones), 0);
    ASSERT_EQ(s.write(y, patch, sizeof patch, 59), 0);  // the last 5 bytes
    ASSERT_EQ(s.read(y, out, sizeof out), 0);
    ASSERT_EQ(s.wait(), 0);
    for (std::size_t k = 0; k < 59; ++k) EXPECT_EQ(out[k], 1) << k;
    for (std::size_t k = 0; k < 5; ++k) EXPECT_EQ(out[59 + k], patch[k]) << k;
}

// spp.hpp: "`src` must stay valid until the command has run" — the bytes are
// taken when the XFER runs, not when it is issued.
TEST_F(SppExecutive, AWriteTakesTheTasksBytesWhenItRuns) {
    start();
    spp::Spp& holder = task(1);
    spp::Spp& s = task(2);
    const spp::Handle x = s.translate("x");
    double v[kXDoubles] = {1, 1, 1, 1, 1, 1, 1, 1}, out[kXDoubles] = {};
    hold_executive(holder, 0);
    ASSERT_EQ(s.write(x, v, sizeof v), 0);
    v[3] = 42;
    gates[0].open();
    ASSERT_EQ(s.read(x, out, sizeof out), 0);
    ASSERT_EQ(s.wait(), 0);
    EXPECT_EQ(out[3], 42.0);
    EXPECT_EQ(out[2], 1.0);
}

// --- arguments and handles ---------------------------------------------------------

TEST_F(SppExecutive, UpToKMaxArgsArriveIntactAndMoreAreRefused) {
    start();
    spp::Spp& s = task(1);
    const spp::Handle probe_fn = s.translate("probe_args"), rec = s.translate("record"), y = s.translate("y");
    static_assert(spp::Args::kMaxArgs == 6, "the argument list below has kMaxArgs entries");
    spp::Args six;
    six.add(1).add(std::int64_t{-2}).add(3.5).add(y).add(std::int64_t{1} << 40).add(rec);
    ASSERT_TRUE(six.valid());
    ASSERT_EQ(s.call(probe_fn, six), 0);
    std::int64_t out[1 + spp::Args::kMaxArgs] = {};
    ASSERT_EQ(s.read(kProbe, out, sizeof out), 0);
    ASSERT_EQ(s.wait(), 0);
    EXPECT_EQ(out[0], 6);
    EXPECT_EQ(out[1], 1);
    EXPECT_EQ(out[2], -2);
    EXPECT_EQ(out[3], std::bit_cast<std::int64_t>(3.5));
    const auto h4 = std::bit_cast<spp::Handle>(out[4]), h6 = std::bit_cast<spp::Handle>(out[6]);
    EXPECT_EQ(h4.kind, spp::Handle::Kind::variable);
    EXPECT_EQ(h4.index, y.index);
    EXPECT_EQ(out[5], std::int64_t{1} << 40);
    EXPECT_EQ(h6.kind, spp::Handle::Kind::routine);
    EXPECT_EQ(h6.index, rec.index);

    spp::Args seven = six;
    seven.add(7);
    EXPECT_FALSE(seven.valid());
    EXPECT_EQ(seven.size(), 7);
    const std::uint64_t ran = proc().executed();
    EXPECT_EQ(s.call(probe_fn, seven), -EINVAL);
    EXPECT_EQ(s.call(rec, spp::Args{}.add(1).add(2).add(3).add(4).add(5).add(6).add(7).add(8)), -EINVAL);
    ASSERT_EQ(s.wait(), 0);
    EXPECT_EQ(proc().executed() - ran, 1u) << "only the WAKEUP ran";
    EXPECT_EQ(journal.size(), 0);
}

TEST_F(SppExecutive, CommandsWithTheWrongHandleOrRangeAreRefusedAndNothingRuns) {
    start();
    spp::Spp& s = task(1);
    const spp::Handle y = s.translate("y"), rec = s.translate("record");  // y: 64 bytes
    unsigned char buf[80] = {};
    const std::uint64_t ran = proc().executed();
    EXPECT_EQ(s.call(y), -EINVAL);
    EXPECT_EQ(s.call(spp::Handle{}), -EINVAL);
    EXPECT_EQ(s.call(spp::Handle{spp::Handle::Kind::routine, 999}), -EINVAL);
    EXPECT_EQ(s.write(rec, buf, 1), -EINVAL);
    EXPECT_EQ(s.read(spp::Handle{spp::Handle::Kind::variable, 999}, buf, 1), -EINVAL);
    EXPECT_EQ(s.write(y, buf, 65), -EINVAL);
    EXPECT_EQ(s.read(y, buf, 65), -EINVAL);
    EXPECT_EQ(s.write(y, buf, 8, 57), -EINVAL);
    EXPECT_EQ(s.read(y, buf, 1, 64), -EINVAL);
    EXPECT_EQ(s.read(y, buf, 2, std::numeric_limits<std::size_t>::max()), -EINVAL);
    EXPECT_EQ(s.write(y, buf, std::numeric_limits<std::size_t>::max(), 1), -EINVAL);
    ASSERT_EQ(s.wait(), 0);
    EXPECT_EQ(proc().executed() - ran, 1u) << "only the WAKEUP ran";
    // The exact limits are accepted.
    EXPECT_EQ(s.write(y, buf, 64), 0);
    EXPECT_EQ(s.write(y, buf, 8, 56), 0);
    EXPECT_EQ(s.read(y, buf, 0, 64), 0);
    ASSERT_EQ(s.wait(), 0);
    EXPECT_EQ(proc().executed() - ran, 5u);
}

// --- WAKEUP / wait -----------------------------------------------------------------

TEST_F(SppExecutive, WaitReturnsOnlyOnceEveryCommandIssuedBeforeHasRun) {
    start();
    spp::Spp& holder = task(1);
    spp::Spp& s = task(2);
    hold_executive(holder, 0);
    record_all(s, {1, 2, 3});
    int seen_at_return = -1;
    std::thread waiter([&] {
        EXPECT_EQ(s.wait(), 0);
        seen_at_return = journal.size();
    });
    gates[0].open();
    waiter.join();
    EXPECT_EQ(seen_at_return, 4);
    EXPECT_EQ(journal.entries(), (Entries{0, 1, 2, 3}));
}

TEST_F(SppExecutive, WaitWithNothingPendingReturnsAtOnce) {
    start();
    spp::Spp& s = task(1);
    EXPECT_EQ(s.wait(), 0);
    EXPECT_EQ(s.wait(), 0);
}

TEST_F(SppExecutive, AHigherPriorityTasksWaitDoesNotWaitForALowerPriorityTasksCommands) {
    start();
    spp::Spp& holder = task(1);
    spp::Spp& low = task(2);
    spp::Spp& high = task(3);
    hold_executive(holder, 10);
    ASSERT_EQ(low.call(low.translate("hold"), tag_gate(20, 1)), 0);  // would block the executive
    record_all(high, {30});
    std::thread high_task([&] { EXPECT_EQ(high.wait(), 0); });
    // Open only once high's WAKEUP is queued: holder's hold (running), low's
    // hold, high's record and WAKEUP.
    ASSERT_TRUE(eventually([&] { return proc().queued() == 4; }));
    gates[0].open();
    // Returns although low's hold is (or will be) stuck in gate 1: high's
    // WAKEUP is reached before it.
    high_task.join();
    const Entries e = journal.entries();
    ASSERT_GE(e.size(), 2u);
    EXPECT_EQ(e[0], 10);
    EXPECT_EQ(e[1], 30);
    gates[1].open();
    ASSERT_EQ(low.wait(), 0);
    EXPECT_EQ(journal.entries(), (Entries{10, 30, 20}));
}

TEST_F(SppExecutive, QueuedCountsTheCommandsNotYetCompletedOfEveryTask) {
    start();
    spp::Spp& holder = task(1);
    spp::Spp& s = task(2);
    EXPECT_EQ(proc().queued(), 0u);
    hold_executive(holder, 0);
    EXPECT_EQ(proc().queued(), 1u);  // the hold, running
    record_all(s, {1, 2, 3});
    EXPECT_EQ(proc().queued(), 4u);
    gates[0].open();
    ASSERT_EQ(s.wait(), 0);
    EXPECT_EQ(proc().queued(), 0u);  // the WAKEUP too: retired before the task is woken
    EXPECT_EQ(journal.entries(), (Entries{0, 1, 2, 3}));
}

// --- routines that throw -----------------------------------------------------------

TEST_F(SppExecutive, ARoutineThatThrowsIsCountedAsAFaultAndTheNextCommandsRun) {
    start();
    spp::Spp& s = task(1);
    const std::uint64_t ran = proc().executed();
    ASSERT_EQ(s.call(s.translate("throw_runtime_error")), 0);
    record_all(s, {1});
    ASSERT_EQ(s.call(s.translate("throw_int")), 0);
    record_all(s, {2});
    ASSERT_EQ(s.wait(), 0);
    EXPECT_EQ(journal.entries(), (Entries{1, 2}));
    EXPECT_EQ(proc().faults(), 2u);
    EXPECT_EQ(proc().executed() - ran, 5u);
}

// --- a full command buffer ---------------------------------------------------------

TEST_F(SppExecutive, AFullCommandBufferRefusesWithEnospcAndWaitMakesRoom) {
    start(/*queue=*/4);
    spp::Spp& holder = task(1);
    spp::Spp& s = task(2);
    const spp::Handle rec = s.translate("record"), y = s.translate("y");
    unsigned char buf[8] = {};
    hold_executive(holder, 0);
    record_all(s, {1, 2, 3, 4});  // QUEUE 4: full
    EXPECT_EQ(s.call(rec, tag(5)), -ENOSPC);
    EXPECT_EQ(s.write(y, buf, 8), -ENOSPC);
    EXPECT_EQ(s.read(y, buf, 8), -ENOSPC);
    std::thread waiter([&] { EXPECT_EQ(s.wait(), 0); });
    gates[0].open();
    waiter.join();
    EXPECT_EQ(journal.entries(), (Entries{0, 1, 2, 3, 4}));  // 5 was refused, not run
    record_all(s, {6});
    ASSERT_EQ(s.wait(), 0);
    EXPECT_EQ(journal.entries(), (Entries{0, 1, 2, 3, 4, 6}));
}

// --- finish ------------------------------------------------------------------------

TEST_F(SppExecutive, FinishRunsThePendingCommandsAndRefusesLaterOnes) {
    start();
    spp::Spp& holder = task(1);
    std::unique_ptr<spp::Spp> s = spp::Spp::init(proc(), 2);
    const spp::Handle rec = s->translate("record"), y = s->translate("y");
    hold_executive(holder, 0);
    record_all(*s, {1, 2, 3});
    int seen_at_return = -1;
    std::thread finisher([&] {
        s->finish();
        seen_at_return = journal.size();
    });
    gates[0].open();
    finisher.join();
    EXPECT_EQ(seen_at_return, 4);
    unsigned char buf[8] = {};
    EXPECT_EQ(s->call(rec, tag(9)), -EPIPE);
    EXPECT_EQ(s->write(y, buf, 8), -EPIPE);
    EXPECT_EQ(s->read(y, buf, 8), -EPIPE);
    EXPECT_EQ(s->wait(), -EPIPE);
    s->finish();  // twice is harmless
    s.reset();    // and so is the destructor after it
    ASSERT_EQ(holder.wait(), 0);
    EXPECT_EQ(journal.entries(), (Entries{0, 1, 2, 3}));
}

TEST_F(SppExecutive, TheDestructorFinishesAndTheFreedSlotServesANewTask) {
    start(/*queue=*/8, /*tasks=*/1);
    {
        std::unique_ptr<spp::Spp> first = spp::Spp::init(proc(), 1);
        record_all(*first, {1, 2});
    }  // finish: waits for 1 and 2
    EXPECT_EQ(journal.entries(), (Entries{1, 2}));
    std::unique_ptr<spp::Spp> second = spp::Spp::init(proc(), 7);
    record_all(*second, {3});
    ASSERT_EQ(second->wait(), 0);
    EXPECT_EQ(journal.entries(), (Entries{1, 2, 3}));
}

// --- the Processor outliving its tasks -----------------------------------------------

// A task still attached keeps pointers into the Processor: destroying it then
// would leave that task's next call (or its finish) writing freed memory. It
// is a programming error, stopped where it happens, with its name.
TEST(SppProcessorDeathTest, DestroyingItWhileATaskIsAttachedStopsTheProgramNamingIt) {
    GTEST_FLAG_SET(death_test_style, "threadsafe");
    EXPECT_DEATH(
        {
            auto proc = spp::Processor::init(make_config(), make_library());
            spp::Spp* attached = spp::Spp::init(*proc, 1).release();  // never finished
            static_cast<void>(attached);
            proc.reset();
        },
        "spp fpa0: destroyed while 1 task is still attached");
}

TEST(SppProcessor, DestroyingItAfterItsTasksFinishedIsQuiet) {
    auto proc = spp::Processor::init(make_config(), make_library());
    auto s = spp::Spp::init(*proc, 1);
    ASSERT_EQ(s->call(s->translate("record"), tag(1)), 0);
    s.reset();
    proc.reset();
}
