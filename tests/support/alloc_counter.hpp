// alloc_counter.hpp — counts heap allocations for the "no allocation on the
// real-time path" tests. Linking tests/support's alloc_counter into a test
// program interposes malloc, calloc, realloc, aligned_alloc, memalign and
// posix_memalign (and so every operator new, which allocates through malloc);
// nothing is counted until a count is started.
//
//   EXPECT_EQ(chimera::test::allocations_in([&] { table.read(p); }), 0);
//   // a task's own thread, seen from outside:
//   chimera::test::alloc_count_start(chimera::test::AllocScope::thread, task_tid);
//   ...; EXPECT_EQ(chimera::test::alloc_count_stop(), 0);
#pragma once

namespace chimera::test {

enum class AllocScope {
    process,      ///< every thread
    this_thread,  ///< the thread that starts the count
    thread,       ///< the thread whose Linux tid is given
};

/// Starts counting from zero (one count at a time per process).
void alloc_count_start(AllocScope scope = AllocScope::process, long tid = 0) noexcept;
/// Stops counting; the allocations counted since the start.
long alloc_count_stop() noexcept;
/// The allocations counted so far (the count goes on).
long alloc_count_now() noexcept;

/// Runs `body` with counting on; how many allocations it made.
template <typename F>
long allocations_in(F&& body, AllocScope scope = AllocScope::process) {
    alloc_count_start(scope);
    body();
    return alloc_count_stop();
}

}  // namespace chimera::test
