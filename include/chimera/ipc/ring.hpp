// chimera/ipc/ring.hpp — a bounded lock-free queue and a doorbell, for what a
// real-time thread hands to a non-real-time one (signals, error lines).
//
// Ring<T, N>: D. Vyukov's bounded multi-producer multi-consumer queue. Each
// slot carries a sequence number; a push or a pop is one compare-and-swap on
// the shared position plus one store, never a wait, never an allocation (the
// slots are in the object). A full ring refuses the push (the caller counts
// what it dropped): a producer never waits for a consumer.
//
// Doorbell: how the consumer sleeps until something is pushed. The producer
// rings (one atomic add; the futex wake, a system call, only while a consumer
// sleeps); the consumer reads the bell, finds the ring empty, and sleeps on
// the value it read, so a push between its look and its sleep is not lost.
#pragma once

#include "chimera/ipc/futex.hpp"

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <type_traits>

namespace chimera::ipc {

template <typename T, std::size_t N>
class Ring {
    static_assert(N >= 2 && (N & (N - 1)) == 0, "the capacity is a power of two");
    static_assert(std::is_trivially_copyable_v<T>, "slots are copied, never constructed");

public:
    Ring() noexcept {
        for (std::size_t i = 0; i < N; ++i) slots_[i].seq.store(i, std::memory_order_relaxed);
    }
    Ring(const Ring&) = delete;
    Ring& operator=(const Ring&) = delete;

    /// False when the ring is full (the item is not queued).
    bool push(const T& item) noexcept {
        std::size_t pos = tail_.load(std::memory_order_relaxed);
        for (;;) {
            Slot& s = slots_[pos & (N - 1)];
            const std::size_t seq = s.seq.load(std::memory_order_acquire);
            const auto diff = static_cast<std::ptrdiff_t>(seq) - static_cast<std::ptrdiff_t>(pos);
            if (diff == 0) {
                if (tail_.compare_exchange_weak(pos, pos + 1, std::memory_order_relaxed)) {
                    s.item = item;
                    s.seq.store(pos + 1, std::memory_order_release);
                    return true;
                }
            } else if (diff < 0) {
                return false;  // full
            } else {
                pos = tail_.load(std::memory_order_relaxed);
            }
        }
    }

    /// False when the ring is empty.
    bool pop(T& out) noexcept {
        std::size_t pos = head_.load(std::memory_order_relaxed);
        for (;;) {
            Slot& s = slots_[pos & (N - 1)];
            const std::size_t seq = s.seq.load(std::memory_order_acquire);
            const auto diff = static_cast<std::ptrdiff_t>(seq) - static_cast<std::ptrdiff_t>(pos + 1);
            if (diff == 0) {
                if (head_.compare_exchange_weak(pos, pos + 1, std::memory_order_relaxed)) {
                    out = s.item;
                    s.seq.store(pos + N, std::memory_order_release);
                    return true;
                }
            } else if (diff < 0) {
                return false;  // empty
            } else {
                pos = head_.load(std::memory_order_relaxed);
            }
        }
    }

private:
    struct Slot {
        std::atomic<std::size_t> seq;
        T item;
    };
    alignas(64) std::atomic<std::size_t> tail_{0};
    alignas(64) std::atomic<std::size_t> head_{0};
    Slot slots_[N];
};

class Doorbell {
public:
    /// Producer, after its push.
    void ring() noexcept {
        word_.fetch_add(1, std::memory_order_seq_cst);
        if (sleepers_.load(std::memory_order_seq_cst) != 0) futex_wake_all(word_);
    }
    /// Consumer, before it looks at the ring.
    std::uint32_t read() const noexcept { return word_.load(std::memory_order_seq_cst); }
    /// Consumer: sleeps while nothing rang since `seen` (deadline_ns < 0: no limit,
    /// else an absolute CLOCK_MONOTONIC time). False when the deadline passed.
    bool wait(std::uint32_t seen, std::int64_t deadline_ns = -1) noexcept {
        sleepers_.fetch_add(1, std::memory_order_seq_cst);
        FutexResult r = FutexResult::woken;
        if (word_.load(std::memory_order_seq_cst) == seen)
            r = deadline_ns < 0 ? futex_wait(word_, seen) : futex_wait_until(word_, seen, deadline_ns);
        sleepers_.fetch_sub(1, std::memory_order_seq_cst);
        return r != FutexResult::timed_out;
    }

private:
    std::atomic<std::uint32_t> word_{0};
    std::atomic<std::uint32_t> sleepers_{0};
};

}  // namespace chimera::ipc
