// spp.hpp: "call/write/read/wait/release are noexcept, allocate nothing".
// Counted by interposing the malloc family (operator new ends there too) for
// the whole process while a window is open, so the executive running the
// commands is counted as well as the task issuing them.
#include <gtest/gtest.h>

#include <cerrno>
#include <cstddef>
#include <thread>

#include "alloc_counter.hpp"
#include "executive_fixture.hpp"

using namespace spp_test;
namespace spp = chimera::spp;

namespace {

using chimera::test::allocations_in;

// The promise is part of the interface: a change that dropped noexcept from
// one of these would fail to compile here.
static_assert(noexcept(std::declval<spp::Spp&>().call(spp::Handle{}, spp::Args{})));
static_assert(noexcept(std::declval<spp::Spp&>().write(spp::Handle{}, nullptr, 0, 0)));
static_assert(noexcept(std::declval<spp::Spp&>().read(spp::Handle{}, nullptr, 0, 0)));
static_assert(noexcept(std::declval<spp::Spp&>().wait()));
static_assert(noexcept(std::declval<spp::Spp&>().release()));

}  // namespace

using SppHotPath = ExecutiveTest;

TEST_F(SppHotPath, TheCounterSeesAnAllocation) {
    // The window works: otherwise every zero below would prove nothing.
    int* volatile p = nullptr;  // volatile: the compiler may not elide the pair
    EXPECT_GE(allocations_in([&] { p = new int(1); }), 1);
    delete p;
    std::thread t;
    EXPECT_GE(allocations_in([&] { t = std::thread([] {}); }), 1);
    t.join();
}

TEST_F(SppHotPath, CallWriteReadWaitAndReleaseAllocateNothingInTheTaskOrTheExecutive) {
    start(/*queue=*/8);
    spp::Spp& s = task(1);
    const spp::Handle x = s.translate("x"), scale_fn = s.translate("scale"), rec = s.translate("record"),
                      hold_fn = s.translate("hold");
    double in[kXDoubles] = {1, 2, 3, 4, 5, 6, 7, 8}, out[kXDoubles] = {};
    // Warm-up: the first wait of a thread may set up library state.
    ASSERT_EQ(s.call(rec, tag(0)), 0);
    ASSERT_EQ(s.wait(), 0);
    s.lock();
    const long n = allocations_in([&] {
        for (int cycle = 0; cycle < 200; ++cycle) {
            if (s.write(x, in, sizeof in) != 0 || s.call(scale_fn, spp::Args{}.add(x).add(0.5)) != 0 ||
                s.read(x, out, sizeof out) != 0 || s.call(rec, tag(cycle)) != 0 || s.wait() != 0)
                ADD_FAILURE() << "cycle " << cycle;
        }
        // The refusals too.
        if (s.call(x) != -EINVAL || s.read(x, out, sizeof out + 1) != -EINVAL) ADD_FAILURE() << "refusals";
        if (s.call(rec, spp::Args{}.add(1).add(2).add(3).add(4).add(5).add(6).add(7)) != -EINVAL)
            ADD_FAILURE() << "too many args";
        // A full buffer (QUEUE 8): the hold, running, and 7 more.
        if (s.call(hold_fn, tag_gate(-2, 1)) != 0) ADD_FAILURE() << "hold";
        gates[1].await_entered();
        for (int k = 0; k < 7; ++k)
            if (s.call(rec, tag(-1)) != 0) ADD_FAILURE() << "record " << k;
        if (s.call(rec, tag(-1)) != -ENOSPC || s.write(x, in, sizeof in) != -ENOSPC) ADD_FAILURE() << "full buffer";
        gates[1].open();
        if (s.wait() != 0) ADD_FAILURE() << "wait on a full buffer";
        if (s.release() != 0) ADD_FAILURE() << "release";
        if (s.wait() != 0) ADD_FAILURE() << "wait after release";
    });
    EXPECT_EQ(n, 0);
    EXPECT_EQ(out[7], 4.0);
    EXPECT_EQ(journal.size(), 1 + 200 + 1 + 7);
}
