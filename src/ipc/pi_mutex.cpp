#include "chimera/ipc/pi_mutex.hpp"

#include <cstdio>
#include <cstdlib>

namespace chimera::ipc {

PiMutex::PiMutex() noexcept {
    pthread_mutexattr_t attr;
    pthread_mutexattr_init(&attr);
    // Every Linux since 2.6.18 has PI futexes; glibc refuses the protocol only
    // where the kernel lacks them, and then no real-time guarantee holds.
    if (pthread_mutexattr_setprotocol(&attr, PTHREAD_PRIO_INHERIT) != 0 ||
        pthread_mutex_init(&mutex_, &attr) != 0) {
        std::fputs("chimera: priority-inheritance mutexes are not available\n", stderr);
        std::abort();
    }
    pthread_mutexattr_destroy(&attr);
}

PiMutex::~PiMutex() { pthread_mutex_destroy(&mutex_); }

// A PI mutex fails only on misuse (EDEADLK would need an error-checking
// type; EOWNERDEAD a robust one), so the result is not an error path.
void PiMutex::lock() noexcept { pthread_mutex_lock(&mutex_); }
bool PiMutex::try_lock() noexcept { return pthread_mutex_trylock(&mutex_) == 0; }
void PiMutex::unlock() noexcept { pthread_mutex_unlock(&mutex_); }

}  // namespace chimera::ipc
