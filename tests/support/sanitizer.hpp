// sanitizer.hpp — which sanitizer the test program is built with (meson's
// b_sanitize; scripts/test.sh's asan and tsan stages), for the few tests that
// must behave differently under one.
#pragma once

#include <gtest/gtest.h>
#include <pthread.h>

#if defined(__has_feature)  // clang; GCC defines __SANITIZE_*__
#define CHIMERA_TEST_HAS_FEATURE(x) __has_feature(x)
#else
#define CHIMERA_TEST_HAS_FEATURE(x) 0
#endif

namespace chimera::test {

#if defined(__SANITIZE_THREAD__) || CHIMERA_TEST_HAS_FEATURE(thread_sanitizer)
inline constexpr bool kThreadSanitizer = true;
#else
inline constexpr bool kThreadSanitizer = false;
#endif
#if defined(__SANITIZE_ADDRESS__) || CHIMERA_TEST_HAS_FEATURE(address_sanitizer)
inline constexpr bool kAddressSanitizer = true;
#else
inline constexpr bool kAddressSanitizer = false;
#endif
/// Built with AddressSanitizer or ThreadSanitizer: the runtime then leaves
/// memory unlocked (src/muf/policy.cpp), and the tests that check locking know.
inline constexpr bool kSanitizer = kAddressSanitizer || kThreadSanitizer;

namespace detail {

// Under ThreadSanitizer a fork (or a helper program started) in a test not
// marked CHIMERA_NOT_UNDER_TSAN fails that test, so what TSan does not run is
// always marked, with its reason.
inline void another_process_under_tsan() {
    if (kThreadSanitizer)
        ADD_FAILURE() << "another process under ThreadSanitizer: begin this test with "
                         "CHIMERA_NOT_UNDER_TSAN(what it crosses)";
}
inline const bool fork_guard_installed = [] {
    if (kThreadSanitizer) ::pthread_atfork(another_process_under_tsan, nullptr, nullptr);
    return kThreadSanitizer;
}();

}  // namespace detail
}  // namespace chimera::test

/// First line of a test whose synchronisation crosses a process boundary
/// (fork, a helper program, a segment another process writes), with what it
/// crosses. ThreadSanitizer keeps its shadow memory per process: it sees one
/// side of every exchange, so such a test proves nothing under it, and a fork
/// after threads ran is outside what it supports. These tests run in the normal
/// and the AddressSanitizer suites; what crosses processes is held by their
/// stress and kill -9 loops, which fail on a torn or lost item.
#define CHIMERA_NOT_UNDER_TSAN(crosses)                                                          \
    do {                                                                                         \
        if (::chimera::test::kThreadSanitizer)                                                   \
            GTEST_SKIP() << "crosses processes (" crosses "): ThreadSanitizer sees one side only"; \
    } while (0)
