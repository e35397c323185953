// chimera/ipc/pi_mutex.hpp — a process-local mutex that inherits priority.
//
// Every lock a real-time task thread can wait on must either never block or
// lend the waiter's priority to the holder (docs/muf.md, "Locks a task thread
// can wait on"). std::mutex is a glibc PTHREAD_MUTEX_NORMAL: a SCHED_FIFO
// waiter sleeps while a medium-priority thread keeps the low-priority holder
// off the CPU (priority inversion). PiMutex is a PTHREAD_PRIO_INHERIT mutex:
// contended, glibc takes it with FUTEX_LOCK_PI and the kernel boosts the
// holder to the highest waiter's priority until it unlocks. Uncontended it is
// one compare-and-swap each way, like std::mutex.
//
// It meets BasicLockable/Lockable (std::lock_guard, std::unique_lock). It has
// no condition variable on purpose: glibc's condition variables inherit
// nothing; wait for a word with ipc::futex_wait instead.
#pragma once

#include "chimera/export.hpp"

#include <pthread.h>

namespace chimera::ipc {

class CHIMERA_API PiMutex {
public:
    PiMutex() noexcept;
    ~PiMutex();
    PiMutex(const PiMutex&) = delete;
    PiMutex& operator=(const PiMutex&) = delete;

    void lock() noexcept;
    bool try_lock() noexcept;
    void unlock() noexcept;

private:
    pthread_mutex_t mutex_;
};

}  // namespace chimera::ipc
