// Global error handling (thesis §8.2): handler chains per thread, matched per
// code / module / scope; continue, abort, jump to mark; the default handler.
// invoke() answers an abort by recording it in the thread's fixed abort slot
// and returning false (nothing thrown, nothing allocated: issue #14.7).
#include "alloc_counter.hpp"

#include "chimera/err.hpp"

#include <gtest/gtest.h>

#include <string>
#include <thread>
#include <vector>

namespace err = chimera::err;
using err::Outcome;

namespace {

// Captures what the default handler prints.
struct Capture {
    std::vector<std::string> lines;
    Capture() {
        err::set_printer([this](std::string_view l) { lines.emplace_back(l); });
    }
    ~Capture() { err::set_printer(nullptr); }
};

// Every test starts and ends with no abort pending on its thread.
class Err : public ::testing::Test {
protected:
    void SetUp() override { err::clear_pending(); }
    void TearDown() override {
        EXPECT_EQ(err::pending(), nullptr) << "a test left an abort pending";
        err::clear_pending();
    }
};

}  // namespace

TEST_F(Err, DefaultHandlerPrintsAndAborts) {
    Capture cap;
    err::set_debug(false);
    EXPECT_FALSE(err::invoke(42, "pid", "gain out of range", "pid.cpp", 17));
    const err::Abort* a = err::pending();
    ASSERT_NE(a, nullptr);
    EXPECT_EQ(a->action, Outcome::Action::Abort);
    EXPECT_EQ(a->code, 42);
    EXPECT_STREQ(a->module, "pid");
    EXPECT_STREQ(a->message, "gain out of range");
    EXPECT_STREQ(a->file, "pid.cpp");
    EXPECT_EQ(a->line, 17);
    const err::Error e = a->error();
    EXPECT_EQ(e.message, "gain out of range");
    EXPECT_STREQ(e.file, "pid.cpp");
    err::clear_pending();
    ASSERT_EQ(cap.lines.size(), 1u);
    EXPECT_EQ(cap.lines[0], "ERROR> pid: gain out of range (code 42)");
}

TEST_F(Err, DebugModeAddsFileAndLine) {
    Capture cap;
    err::set_debug(true);
    EXPECT_FALSE(err::invoke(7, "traj", "bad segment", "traj.cpp", 99));
    err::set_debug(false);
    err::clear_pending();
    ASSERT_EQ(cap.lines.size(), 1u);
    EXPECT_EQ(cap.lines[0], "ERROR> traj: bad segment (code 7) [traj.cpp:99]");
}

TEST_F(Err, ContinueReturnsToTheNextLine) {
    int handled = 0;
    err::HandlerScope scope([&](const err::Error& e) {
        ++handled;
        EXPECT_EQ(e.code, 3);
        return Outcome::resume();
    });
    EXPECT_TRUE(err::invoke(3, "m", "recoverable"));
    EXPECT_EQ(handled, 1);
    EXPECT_EQ(err::pending(), nullptr);
}

TEST_F(Err, NewestMatchingHandlerWinsAndFiltersApply) {
    std::vector<std::string> calls;
    err::HandlerScope any([&](const err::Error&) {
        calls.push_back("any");
        return Outcome::resume();
    });
    err::HandlerScope by_code(err::Match{5, ""}, [&](const err::Error&) {
        calls.push_back("code5");
        return Outcome::resume();
    });
    err::HandlerScope by_module(err::Match{std::nullopt, "robot"}, [&](const err::Error&) {
        calls.push_back("robot");
        return Outcome::resume();
    });
    EXPECT_TRUE(err::invoke(5, "robot", "x"));  // module handler is newest and matches
    EXPECT_TRUE(err::invoke(5, "pid", "x"));    // module filter fails -> code 5 handler
    EXPECT_TRUE(err::invoke(6, "pid", "x"));    // neither filter -> catch-all
    EXPECT_EQ(calls, (std::vector<std::string>{"robot", "code5", "any"}));
}

TEST_F(Err, ScopeEndsTheHandler) {
    Capture cap;
    const std::size_t before = err::chain_size();
    {
        err::HandlerScope s([](const err::Error&) { return Outcome::resume(); });
        EXPECT_EQ(err::chain_size(), before + 1);
        EXPECT_TRUE(err::invoke(1, "m", "inside"));
    }
    EXPECT_EQ(err::chain_size(), before);
    EXPECT_FALSE(err::invoke(1, "m", "outside"));
    err::clear_pending();
    EXPECT_EQ(cap.lines.size(), 1u);
}

TEST_F(Err, HandlerCanAbort) {
    err::HandlerScope s([](const err::Error&) { return Outcome::abort(); });
    EXPECT_FALSE(err::invoke(1, "m", "no"));
    ASSERT_NE(err::pending(), nullptr);
    EXPECT_STREQ(err::pending()->message, "no");
    err::clear_pending();
}

// A caller that goes on after an abort instead of returning: the first error
// stays the recorded cause and later invokes return false at once, without
// running a handler.
TEST_F(Err, WhileAnAbortIsPendingTheFirstErrorStands) {
    int handled = 0;
    err::HandlerScope s([&](const err::Error&) {
        ++handled;
        return Outcome::abort();
    });
    EXPECT_FALSE(err::invoke(1, "m", "first"));
    EXPECT_FALSE(err::invoke(2, "m", "second"));
    EXPECT_EQ(handled, 1);
    EXPECT_STREQ(err::pending()->message, "first");
    err::clear_pending();
    EXPECT_FALSE(err::invoke(3, "m", "third"));  // cleared: handled again
    EXPECT_EQ(handled, 2);
    err::clear_pending();
}

TEST_F(Err, JumpToMarkReturnsToTheMark) {
    err::HandlerScope s([](const err::Error&) { return Outcome::jump(2); });
    int reached = 0;
    bool destroyed = false;
    struct Guard {
        bool* flag;
        ~Guard() { *flag = true; }
    };
    const err::MarkExit exit = err::mark(2, [&] {
        Guard g{&destroyed};
        if (!err::invoke(9, "m", "restart the cycle")) return;
        reached = 1;
    });
    EXPECT_EQ(exit, err::MarkExit::jumped);
    EXPECT_EQ(reached, 0);
    EXPECT_TRUE(destroyed);  // unlike longjmp, destructors ran
    EXPECT_EQ(err::pending(), nullptr);  // the mark took the jump
    EXPECT_EQ(err::mark(2, [] {}), err::MarkExit::completed);
}

TEST_F(Err, JumpGoesToTheMarkWithThatIdThroughOthers) {
    err::HandlerScope s([](const err::Error&) { return Outcome::jump(1); });
    int inner_done = 0;
    err::MarkExit inner = err::MarkExit::completed;
    const err::MarkExit outer = err::mark(1, [&] {
        inner = err::mark(2, [&] {
            if (!err::invoke(1, "m", "x")) return;
            inner_done = 1;
        });
        if (inner == err::MarkExit::aborting) return;  // not ours: pass it on
        inner_done = 2;
    });
    EXPECT_EQ(inner, err::MarkExit::aborting);
    EXPECT_EQ(outer, err::MarkExit::jumped);
    EXPECT_EQ(inner_done, 0);
}

TEST_F(Err, JumpToAnUnsetMarkAborts) {
    err::HandlerScope s([](const err::Error&) { return Outcome::jump(77); });
    EXPECT_FALSE(err::invoke(1, "m", "x"));
    const err::Abort* a = err::pending();
    ASSERT_NE(a, nullptr);
    EXPECT_EQ(a->action, Outcome::Action::Abort);
    EXPECT_STREQ(a->message, "x (handler asked to jump to mark 77, which is not set: aborting)");
    err::clear_pending();
}

// The default handler runs for the inner error; the outer one aborts too, even
// though the handler answers continue: the inner error is the recorded cause.
TEST_F(Err, ErrorInsideAHandlerGoesToTheDefaultAndAborts) {
    Capture cap;
    bool inner_returned = true;
    err::HandlerScope s([&](const err::Error&) {
        inner_returned = err::invoke(2, "h", "nested");  // the default handler aborts this one
        return Outcome::resume();
    });
    EXPECT_FALSE(err::invoke(1, "m", "outer"));
    EXPECT_FALSE(inner_returned);
    ASSERT_NE(err::pending(), nullptr);
    EXPECT_STREQ(err::pending()->message, "nested");
    err::clear_pending();
    ASSERT_EQ(cap.lines.size(), 1u);
    EXPECT_EQ(cap.lines[0], "ERROR> h: nested (code 2)");
}

TEST_F(Err, ChainsAndAbortSlotsArePerThread) {
    err::HandlerScope s([](const err::Error&) { return Outcome::resume(); });
    Capture cap;
    bool aborted_in_other = false;
    std::thread t([&] {
        aborted_in_other = !err::invoke(1, "other", "no handler here") && err::pending() != nullptr;
    });
    t.join();
    EXPECT_TRUE(aborted_in_other);
    EXPECT_EQ(err::pending(), nullptr);  // that thread's abort is not this one's
    EXPECT_TRUE(err::invoke(1, "mine", "handled"));
}

TEST_F(Err, MacroRecordsTheCallersLocation) {
    std::string file;
    int line = 0;
    err::HandlerScope s([&](const err::Error& e) {
        file = e.file ? e.file : "";
        line = e.line;
        return Outcome::resume();
    });
    const int here = __LINE__ + 1;
    EXPECT_TRUE(CHIMERA_ERR(1, "m", "where"));
    EXPECT_NE(file.find("test_err.cpp"), std::string::npos);
    EXPECT_EQ(line, here);
}

// Too long for the slot: cut to 1023 bytes, the last ones kCutMark.
TEST_F(Err, ALongMessageIsCutWithAMark) {
    err::HandlerScope s([](const err::Error&) { return Outcome::abort(); });
    const std::string text(3000, 'x');
    EXPECT_FALSE(err::invoke(1, std::string(100, 'm'), text, "f.cpp", 1));
    const err::Abort* a = err::pending();
    ASSERT_NE(a, nullptr);
    const std::string message = a->message;
    ASSERT_EQ(message.size(), err::Abort::kMessageSize - 1);
    EXPECT_EQ(message, std::string(err::Abort::kMessageSize - 1 - err::kCutMark.size(), 'x') + std::string(err::kCutMark));
    EXPECT_EQ(std::string(a->module), std::string(err::Abort::kModuleSize - 1 - err::kCutMark.size(), 'm') +
                                          std::string(err::kCutMark));
    err::clear_pending();
}

TEST_F(Err, FormatToCutsTheWholeLineWithAMark) {
    const err::Error e{12, "pid", "gain out of range", "pid.cpp", 17};
    char line[128];
    ASSERT_EQ(err::format_to(line, sizeof line, e, true), err::format(e, true).size());
    EXPECT_EQ(std::string(line), err::format(e, true));
    char small[20];
    EXPECT_EQ(err::format_to(small, sizeof small, e, true), sizeof small - 1);
    EXPECT_EQ(std::string(small), "ERROR> pid: ga[...]");
}

// The abort path itself — the handler search, the abort record, the jump to a
// mark — allocates nothing once the chain and the marks exist.
TEST_F(Err, AbortAndJumpAllocateNothing) {
    err::HandlerScope s(err::Match{5, ""}, [](const err::Error&) { return Outcome::jump(3); });
    err::HandlerScope a(err::Match{6, ""}, [](const err::Error&) { return Outcome::abort(); });
    (void)err::mark(3, [] {});  // the mark stack's one reservation
    const std::string text(2000, 'y');
    err::MarkExit exit = err::MarkExit::completed;
    const long allocations = chimera::test::allocations_in(
        [&] {
            if (!err::invoke(6, "m", text)) err::clear_pending();
            exit = err::mark(3, [&] { (void)err::invoke(5, "m", "jump"); });
        },
        chimera::test::AllocScope::this_thread);
    EXPECT_EQ(allocations, 0);
    EXPECT_EQ(exit, err::MarkExit::jumped);
}

// On a thread with a thread printer (a task thread), the default handler hands
// its line there — cut to fit a fixed buffer — and neither allocates nor takes
// the process printer's lock.
TEST_F(Err, TheThreadPrinterTakesTheDefaultHandlersLineWithoutAllocating) {
    Capture cap;
    err::set_debug(false);
    struct Seen {
        std::string line;  // reserved below: the printer itself must not allocate either
        int calls = 0;
    } seen;
    seen.line.reserve(4096);
    err::set_thread_printer(
        [](void* c, std::string_view line) noexcept {
            auto& s = *static_cast<Seen*>(c);
            s.line.assign(line);
            ++s.calls;
        },
        &seen);
    const long allocations = chimera::test::allocations_in(
        [] {
            if (!err::invoke(8, "robot", "joint 2 lost")) err::clear_pending();
        },
        chimera::test::AllocScope::this_thread);
    err::set_thread_printer(nullptr, nullptr);
    EXPECT_EQ(allocations, 0);
    EXPECT_EQ(seen.calls, 1);
    EXPECT_EQ(seen.line, "ERROR> robot: joint 2 lost (code 8)");
    EXPECT_TRUE(cap.lines.empty());  // not through the process's printer
}
