// Global error handling (thesis §8.2): handler chains per thread, matched per
// code / module / scope; continue, abort, jump to mark; the default handler.
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

}  // namespace

TEST(Err, DefaultHandlerPrintsAndAborts) {
    Capture cap;
    err::set_debug(false);
    try {
        err::invoke(42, "pid", "gain out of range", "pid.cpp", 17);
        FAIL() << "invoke returned";
    } catch (const err::Aborted& a) {
        EXPECT_EQ(a.code(), 42);
        EXPECT_EQ(a.module(), "pid");
        EXPECT_EQ(a.message(), "gain out of range");
    }
    ASSERT_EQ(cap.lines.size(), 1u);
    EXPECT_EQ(cap.lines[0], "ERROR> pid: gain out of range (code 42)");
}

TEST(Err, DebugModeAddsFileAndLine) {
    Capture cap;
    err::set_debug(true);
    EXPECT_THROW(err::invoke(7, "traj", "bad segment", "traj.cpp", 99), err::Aborted);
    err::set_debug(false);
    ASSERT_EQ(cap.lines.size(), 1u);
    EXPECT_EQ(cap.lines[0], "ERROR> traj: bad segment (code 7) [traj.cpp:99]");
}

TEST(Err, ContinueReturnsToTheNextLine) {
    int handled = 0;
    err::HandlerScope scope([&](const err::Error& e) {
        ++handled;
        EXPECT_EQ(e.code, 3);
        return Outcome::resume();
    });
    int after = 0;
    err::invoke(3, "m", "recoverable");
    after = 1;  // reached only because the handler continued
    EXPECT_EQ(handled, 1);
    EXPECT_EQ(after, 1);
}

TEST(Err, NewestMatchingHandlerWinsAndFiltersApply) {
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
    err::invoke(5, "robot", "x");  // module handler is newest and matches
    err::invoke(5, "pid", "x");    // module filter fails -> code 5 handler
    err::invoke(6, "pid", "x");    // neither filter -> catch-all
    EXPECT_EQ(calls, (std::vector<std::string>{"robot", "code5", "any"}));
}

TEST(Err, ScopeEndsTheHandler) {
    Capture cap;
    const std::size_t before = err::chain_size();
    {
        err::HandlerScope s([](const err::Error&) { return Outcome::resume(); });
        EXPECT_EQ(err::chain_size(), before + 1);
        EXPECT_NO_THROW(err::invoke(1, "m", "inside"));
    }
    EXPECT_EQ(err::chain_size(), before);
    EXPECT_THROW(err::invoke(1, "m", "outside"), err::Aborted);
    EXPECT_EQ(cap.lines.size(), 1u);
}

TEST(Err, HandlerCanAbort) {
    err::HandlerScope s([](const err::Error&) { return Outcome::abort(); });
    EXPECT_THROW(err::invoke(1, "m", "no"), err::Aborted);
}

TEST(Err, JumpToMarkUnwindsToTheMark) {
    err::HandlerScope s([](const err::Error&) { return Outcome::jump(2); });
    int reached = 0;
    bool destroyed = false;
    struct Guard {
        bool* flag;
        ~Guard() { *flag = true; }
    };
    const bool completed = err::mark(2, [&] {
        Guard g{&destroyed};
        err::invoke(9, "m", "restart the cycle");
        reached = 1;
    });
    EXPECT_FALSE(completed);
    EXPECT_EQ(reached, 0);
    EXPECT_TRUE(destroyed);  // unlike longjmp, destructors ran
    EXPECT_TRUE(err::mark(2, [] {}));
}

TEST(Err, JumpGoesToTheMarkWithThatIdThroughOthers) {
    err::HandlerScope s([](const err::Error&) { return Outcome::jump(1); });
    int inner_done = 0;
    const bool outer = err::mark(1, [&] {
        const bool inner = err::mark(2, [&] { err::invoke(1, "m", "x"); });
        inner_done = inner ? 1 : 2;  // never reached: the jump passes through mark 2
    });
    EXPECT_FALSE(outer);
    EXPECT_EQ(inner_done, 0);
}

TEST(Err, JumpToAnUnsetMarkAborts) {
    err::HandlerScope s([](const err::Error&) { return Outcome::jump(77); });
    try {
        err::invoke(1, "m", "x");
        FAIL();
    } catch (const err::MarkJump&) {
        FAIL() << "jumped to a mark that does not exist";
    } catch (const err::Aborted& a) {
        EXPECT_NE(a.message().find("mark 77"), std::string::npos);
    }
}

TEST(Err, ErrorInsideAHandlerGoesToTheDefault) {
    Capture cap;
    err::HandlerScope s([](const err::Error&) {
        err::invoke(2, "h", "nested");  // the default handler aborts this one
        return Outcome::resume();
    });
    EXPECT_THROW(err::invoke(1, "m", "outer"), err::Aborted);
    ASSERT_EQ(cap.lines.size(), 1u);
    EXPECT_NE(cap.lines[0].find("nested"), std::string::npos);
}

TEST(Err, ChainsArePerThread) {
    err::HandlerScope s([](const err::Error&) { return Outcome::resume(); });
    Capture cap;
    bool aborted_in_other = false;
    std::thread t([&] {
        try {
            err::invoke(1, "other", "no handler here");
        } catch (const err::Aborted&) {
            aborted_in_other = true;
        }
    });
    t.join();
    EXPECT_TRUE(aborted_in_other);
    EXPECT_NO_THROW(err::invoke(1, "mine", "handled"));
}

TEST(Err, MacroRecordsTheCallersLocation) {
    std::string file;
    int line = 0;
    err::HandlerScope s([&](const err::Error& e) {
        file = e.file ? e.file : "";
        line = e.line;
        return Outcome::resume();
    });
    const int here = __LINE__ + 1;
    CHIMERA_ERR(1, "m", "where");
    EXPECT_NE(file.find("test_err.cpp"), std::string::npos);
    EXPECT_EQ(line, here);
}
