// chimera/ipc/seqlock.hpp — the sequence-counter protocol of the status
// segment (its task slots and RTPU blocks) and of the SVAR table's watchers.
//
// One writer per counter (the task, the header-lock holder for RTPU blocks,
// the table-lock holder for the SVAR table): odd while writing. Readers copy, then re-check; they never block
// the writer. Data fields are relaxed atomics (strings are copied with
// memcpy inside the window, the usual seqlock idiom), ordered by the fences.
#pragma once

#include <atomic>
#include <cstdint>

#include <sched.h>

#include "chimera/ipc/clock.hpp"

#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#endif

namespace chimera::ipc::seqlock {

inline void cpu_relax() noexcept {
#if defined(__x86_64__) || defined(__i386__)
    _mm_pause();
#endif
}

inline void write_begin(std::atomic<std::uint32_t>& seq) noexcept {
    seq.store(seq.load(std::memory_order_relaxed) + 1, std::memory_order_relaxed);
    std::atomic_thread_fence(std::memory_order_release);
}

inline void write_end(std::atomic<std::uint32_t>& seq) noexcept {
    seq.store(seq.load(std::memory_order_relaxed) + 1, std::memory_order_release);
}

/// Runs `copy` until it saw a stable, even counter. A writer preempted in its
/// window makes the reader wait (it yields after a while: readers are not
/// real-time); a writer that died in its window leaves the counter odd, so
/// after `timeout_ns` the last copy is kept and false returned: a reader never
/// hangs on a dead task.
template <typename Copy>
bool read_consistent(const std::atomic<std::uint32_t>& seq, Copy&& copy,
                     std::int64_t timeout_ns = 200'000'000) noexcept(noexcept(copy())) {
    std::int64_t deadline = 0;
    for (unsigned i = 0;; ++i) {
        const std::uint32_t before = seq.load(std::memory_order_acquire);
        if ((before & 1u) == 0) {
            copy();
            std::atomic_thread_fence(std::memory_order_acquire);
            if (seq.load(std::memory_order_relaxed) == before) return true;
        }
        if (i < 256) {
            cpu_relax();
            continue;
        }
        const std::int64_t now = now_ns();
        if (deadline == 0) deadline = now + timeout_ns;
        if (now >= deadline) break;
        sched_yield();
    }
    copy();
    return false;
}

}  // namespace chimera::ipc::seqlock
