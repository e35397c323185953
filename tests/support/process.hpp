// process.hpp — plumbing for the tests that cross processes: shared memory
// inherited across fork(), a child running a body, its exit status, polling.
// Kept apart from the code under test on purpose (plain mmap and fork).
#pragma once

#include <sys/mman.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <new>
#include <thread>

namespace chimera::test {

/// Anonymous shared memory inherited across fork(): for plain test
/// plumbing that must not depend on the code under test.
template <typename T>
T* shared_anon() {
    void* p = mmap(nullptr, sizeof(T), PROT_READ | PROT_WRITE, MAP_SHARED | MAP_ANONYMOUS, -1, 0);
    if (p == MAP_FAILED) std::abort();
    return new (p) T{};
}

/// Runs `body` in a child process; returns its pid. The child exits with
/// body's return value and never returns into gtest.
template <typename F>
pid_t fork_child(F&& body) {
    const pid_t pid = fork();
    if (pid == 0) {
        int rc = 1;
        try {
            rc = body();
        } catch (...) {
            rc = 99;
        }
        _exit(rc);
    }
    return pid;
}

/// Waits for a child; returns its exit code, or 128+signal.
inline int wait_child(pid_t pid) {
    int status = 0;
    if (waitpid(pid, &status, 0) != pid) return -1;
    if (WIFEXITED(status)) return WEXITSTATUS(status);
    if (WIFSIGNALED(status)) return 128 + WTERMSIG(status);
    return -1;
}

/// Polls `cond` up to `ms` milliseconds.
template <typename F>
bool wait_for(F&& cond, int ms = 5000) {
    const auto end = std::chrono::steady_clock::now() + std::chrono::milliseconds(ms);
    while (!cond()) {
        if (std::chrono::steady_clock::now() > end) return false;
        std::this_thread::sleep_for(std::chrono::microseconds(100));
    }
    return true;
}

}  // namespace chimera::test
