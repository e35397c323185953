// The table lock's slow paths: spin, block in FUTEX_LOCK_PI (the holder inherits
// the waiter's priority), take over dead holders, refuse corrupt words, time out;
// hand over to a waiter through FUTEX_UNLOCK_PI.
#include "chimera/ipc/lock.hpp"

#include <fcntl.h>
#include <linux/futex.h>
#include <poll.h>
#include <pthread.h>
#include <sys/stat.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <bit>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <ctime>

#include "chimera/ipc/clock.hpp"

#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#endif

namespace chimera::ipc {

namespace detail {
[[gnu::tls_model("initial-exec")]] constinit thread_local std::uint64_t t_self_owner_id = 0;
}  // namespace detail

namespace {

// The child of fork() inherits the parent's thread-local cache: clear it.
void clear_self_in_child() noexcept { detail::t_self_owner_id = 0; }
const bool g_atfork_registered = [] {
    pthread_atfork(nullptr, nullptr, &clear_self_in_child);
    return true;
}();

std::atomic<LockEventHandler> g_handler{nullptr};
std::atomic<void*> g_context{nullptr};

inline void cpu_pause() noexcept {
#if defined(__x86_64__) || defined(__i386__)
    _mm_pause();
#elif defined(__aarch64__)
    asm volatile("yield" ::: "memory");
#else
    std::atomic_signal_fence(std::memory_order_seq_cst);
#endif
}

void report(LockEvent::Kind kind, const LockWord& lock, std::uint64_t previous,
            std::int64_t waited) noexcept {
    if (LockEventHandler h = g_handler.load(std::memory_order_acquire)) {
        const LockEvent ev{kind, &lock, owner_pid(previous), owner_tid(previous), waited};
        h(ev, g_context.load(std::memory_order_acquire));
    }
}

}  // namespace

const char* to_string(LockStatus s) noexcept {
    switch (s) {
        case LockStatus::acquired: return "acquired";
        case LockStatus::recovered: return "recovered from a dead holder";
        case LockStatus::forced: return "reset after timeout";
        case LockStatus::busy: return "busy";
        case LockStatus::timed_out: return "timed out";
        case LockStatus::already_held: return "already held by this thread";
        case LockStatus::corrupt: return "lock word corrupt (names no thread that can hold it)";
    }
    return "unknown";
}

void set_lock_event_handler(LockEventHandler handler, void* context) noexcept {
    g_context.store(context, std::memory_order_release);
    g_handler.store(handler, std::memory_order_release);
}

std::uint64_t detail::self_owner_id_slow() noexcept {
    (void)g_atfork_registered;
    const auto pid = static_cast<std::uint32_t>(getpid());
    const auto tid = static_cast<std::uint32_t>(gettid());
    const std::uint64_t id = (static_cast<std::uint64_t>(pid) << 32) | tid;
    t_self_owner_id = id;
    return id;
}

namespace {

// Whether a pidfd, polled now, says its task has exited: 1 yes, 0 no, -1 unknown.
int pidfd_says_exited(int pidfd) noexcept {
    pollfd p{pidfd, POLLIN, 0};
    const int ready = poll(&p, 1, 0);
    close(pidfd);
    return ready == 1 ? 1 : ready == 0 ? 0 : -1;
}

// A killed process is a zombie until reaped, and tgkill() still reaches it.
// 1 when thread `tid` of process `pid` has exited, 0 when it has not, -1 when
// only /proc/PID/task/TID/stat can tell. Asked without reading that stat where
// the kernel allows, because the read takes a reference to the process's
// memory: a process that dies meanwhile keeps its mappings, and the segment
// user locks they hold, until the read ends — seen as a dead user still
// counted after it was reaped.
//  - Linux 6.9 and later: a pidfd of the thread itself (PIDFD_THREAD), readable
//    once that thread has exited — but a leader's only once all its process
//    has: the kernel holds back a leader that ends before the other threads.
//  - Before: a pidfd of the process, readable once all of it has exited.
// A leader not exited by its pidfd is alive when it is its process's only
// thread (/proc/PID/task's link count is 2 + threads). With several, the
// leader — whose id names the holder — may have ended alone: -1.
int thread_exited(std::int32_t pid, std::int32_t tid) noexcept {
#ifdef SYS_pidfd_open
    constexpr unsigned kPidfdThread = O_EXCL;  // PIDFD_THREAD (linux/pidfd.h, 6.9)
    int fd = static_cast<int>(syscall(SYS_pidfd_open, tid, kPidfdThread));
    if (fd < 0) {
        if (errno == ESRCH) return 1;
        if (errno != EINVAL || pid != tid) return -1;  // EINVAL: a kernel without PIDFD_THREAD
        fd = static_cast<int>(syscall(SYS_pidfd_open, pid, 0));
        if (fd < 0) return errno == ESRCH ? 1 : -1;
    }
    if (const int exited = pidfd_says_exited(fd); exited != 0 || tid != pid) return exited;
    char path[32];
    std::snprintf(path, sizeof path, "/proc/%d/task", pid);
    struct stat st {};
    if (stat(path, &st) == 0 && st.st_nlink == 3) return 0;
#else
    (void)pid;
    (void)tid;
#endif
    return -1;
}

}  // namespace

bool owner_alive(std::uint64_t word) noexcept {
    const std::int32_t pid = owner_pid(word);
    const std::int32_t tid = owner_tid(word);
    if (pid < 0 || tid <= 0) return false;
    // A pid half of 0: a holder between clearing it and FUTEX_UNLOCK_PI; ask by TID alone.
    const long rc = pid > 0 ? syscall(SYS_tgkill, pid, tid, 0) : syscall(SYS_tkill, tid, 0);
    if (rc != 0 && errno == ESRCH) return false;
    if (pid > 0) {
        if (const int exited = thread_exited(pid, tid); exited >= 0) return exited == 0;
    }
    // tgkill succeeds on a zombie (killed, not yet reaped): look at its state.
    char path[64];
    std::snprintf(path, sizeof path, "/proc/%d/task/%d/stat", pid > 0 ? pid : tid, tid);
    const int fd = open(path, O_RDONLY | O_CLOEXEC);
    if (fd < 0) {
        if (errno == ESRCH) return false;  // gone since tgkill
        // ENOENT: gone since tgkill — or no /proc here at all (a container, a
        // chroot), where only tgkill can answer, and it said alive.
        if (errno == ENOENT) return access("/proc/self/stat", F_OK) != 0;
        return true;
    }
    char buf[512];
    const ssize_t n = read(fd, buf, sizeof buf - 1);
    const int read_error = n < 0 ? errno : 0;
    close(fd);
    // Reaped between the open and the read: the read fails with ESRCH. Gone,
    // not alive (taking that for "alive" brought a dead one back to life).
    if (read_error == ESRCH) return false;
    if (n <= 0) return true;
    buf[n] = '\0';
    // "pid (comm) S ...": the state follows the last ')'.
    const char* paren = std::strrchr(buf, ')');
    if (!paren || paren[1] == '\0' || paren[2] == '\0') return true;
    const char state = paren[2];
    return state != 'Z' && state != 'X' && state != 'x';
}

LockStatus take_over(LockWord& lock, std::uint64_t dead_owner, std::int64_t waited_ns) noexcept {
    std::uint64_t expected = dead_owner;
    if (!lock.owner.compare_exchange_strong(expected, self_owner_id(), std::memory_order_acquire,
                                            std::memory_order_relaxed))
        return owner_of(expected) == self_owner_id() ? LockStatus::already_held : LockStatus::busy;
    lock.recoveries.fetch_add(1, std::memory_order_relaxed);
    lock.acquisitions.fetch_add(1, std::memory_order_relaxed);
    report(LockEvent::Kind::recovered, lock, dead_owner, waited_ns);
    return LockStatus::recovered;
}

namespace {

// The futex half of the word: the low 32 bits, wherever the byte order puts them.
std::uint32_t* futex_half(LockWord& lock) noexcept {
    auto* p = reinterpret_cast<std::uint32_t*>(&lock.owner);
    return std::endian::native == std::endian::little ? p : p + 1;
}

// FUTEX_LOCK_PI2 (Linux 5.14) takes a CLOCK_MONOTONIC deadline; FUTEX_LOCK_PI
// only CLOCK_REALTIME, converted here for older kernels.
constexpr int kFutexLockPi2 = 13;
std::atomic<bool> g_lock_pi2{true};

// One wait in the kernel until `until_ns` (monotonic): 0 when the caller got the
// lock, else the errno.
int futex_lock_pi(LockWord& lock, std::int64_t until_ns) noexcept {
    if (g_lock_pi2.load(std::memory_order_relaxed)) {
        const timespec ts = to_timespec(until_ns);
        if (syscall(SYS_futex, futex_half(lock), kFutexLockPi2, 0, &ts, nullptr, 0) == 0) return 0;
        if (errno != ENOSYS) return errno;
        g_lock_pi2.store(false, std::memory_order_relaxed);
    }
    timespec real{};
    clock_gettime(CLOCK_REALTIME, &real);
    const timespec ts = to_timespec(until_ns - now_ns() + real.tv_sec * 1'000'000'000LL + real.tv_nsec);
    return syscall(SYS_futex, futex_half(lock), FUTEX_LOCK_PI, 0, &ts, nullptr, 0) == 0 ? 0 : errno;
}

// The kernel made the caller the owner (its TID in the futex half): writes the
// caller's pid into the other half. A pid still there is the previous holder's,
// who never released (it died; the kernel handed the lock on at its exit).
LockStatus claim(LockWord& lock, std::uint64_t me, std::int64_t waited) noexcept {
    std::uint64_t seen = lock.owner.load(std::memory_order_relaxed);
    for (;;) {
        const std::uint64_t mine = (me & ~std::uint64_t{0xffffffffu}) | (seen & 0xffffffffu & ~kFutexOwnerDied);
        if (lock.owner.compare_exchange_weak(seen, mine, std::memory_order_acquire, std::memory_order_relaxed))
            break;
    }
    lock.acquisitions.fetch_add(1, std::memory_order_relaxed);
    const std::uint64_t previous_pid = seen >> 32;
    if (previous_pid == 0 && (seen & kFutexOwnerDied) == 0) return LockStatus::acquired;
    lock.recoveries.fetch_add(1, std::memory_order_relaxed);
    report(LockEvent::Kind::recovered, lock, seen & ~std::uint64_t{0xffffffffu}, waited);
    return LockStatus::recovered;
}

LockStatus refuse_corrupt(LockWord& lock, std::uint64_t seen, std::int64_t waited) noexcept {
    lock.corruptions.fetch_add(1, std::memory_order_relaxed);
    report(LockEvent::Kind::corrupt, lock, seen, waited);
    return LockStatus::corrupt;
}

// A word no holder can have written: a pid half naming no process that has the
// thread of the TID half. A pid half of 0 is a holder between clearing it and
// FUTEX_UNLOCK_PI, or a new owner about to claim(): not suspicious. (A word
// naming no thread at all is a dead holder: the kernel answers ESRCH.)
bool implausible(std::uint64_t word) noexcept {
    if (owner_pid(word) == 0 || (word & kFutexTidMask) == 0) return false;
    return !owner_alive(word);
}

// A holder died while waiters were queued: its exit left the kernel's PI state
// without an owner, and the kernel refuses (EINVAL) the word that still names
// the dead thread until the waiter it woke takes over — which that waiter may
// never do (killed too) or only late (a busy machine). The kernel's own answer
// to this is the robust list's mark: TID 0 and FUTEX_OWNER_DIED, which lets the
// next locker attach to the ownerless state or take the word. This lock has no
// robust list, so a waiter that finds the word's thread gone marks it so; the
// pid half is kept, so the next owner knows it is a recovery (claim()).
bool mark_owner_died(LockWord& lock, std::uint64_t word) noexcept {
    // By TID alone: the kernel refuses the word for that thread, whatever its pid half says.
    if ((word & kFutexTidMask) == 0 || owner_alive(word & kFutexTidMask)) return false;
    const std::uint64_t marked = (word & ~std::uint64_t{0xffffffffu}) | kFutexOwnerDied | kFutexWaiters;
    return lock.owner.compare_exchange_strong(word, marked, std::memory_order_relaxed, std::memory_order_relaxed);
}

// A pause between looks at a word the kernel refused (see lock_slow): short
// against the time a woken waiter needs to take the lock over.
constexpr std::int64_t kRefusedNapNs = 20'000;
constexpr std::int64_t kRefusedBoundNs = 50'000'000;
void nap_ns(std::int64_t ns) noexcept {
    timespec ts = to_timespec(ns);
    while (nanosleep(&ts, &ts) != 0 && errno == EINTR) {
    }
}

// The spin phase: true with the lock taken when it came free.
bool spin(LockWord& lock, std::uint64_t me, std::uint32_t count) noexcept {
    for (std::uint32_t i = 0; i < count; ++i) {
        cpu_pause();
        std::uint64_t seen = lock.owner.load(std::memory_order_relaxed);
        if (seen == 0 && lock.owner.compare_exchange_weak(seen, me, std::memory_order_acquire,
                                                          std::memory_order_relaxed)) {
            lock.acquisitions.fetch_add(1, std::memory_order_relaxed);
            return true;
        }
    }
    return false;
}

LockStatus on_timeout(LockWord& lock, std::uint64_t me, std::uint64_t seen, const LockOptions& options,
                      std::int64_t waited, bool& retry) noexcept {
    retry = false;
    if (options.reset_on_timeout) {
        if (lock.owner.compare_exchange_strong(seen, me, std::memory_order_acquire, std::memory_order_relaxed)) {
            lock.forced.fetch_add(1, std::memory_order_relaxed);
            lock.acquisitions.fetch_add(1, std::memory_order_relaxed);
            report(LockEvent::Kind::forced, lock, seen, waited);
            return LockStatus::forced;
        }
        retry = true;
        return LockStatus::busy;
    }
    lock.timeouts.fetch_add(1, std::memory_order_relaxed);
    report(LockEvent::Kind::timed_out, lock, seen, waited);
    return LockStatus::timed_out;
}

}  // namespace

LockStatus lock_slow(LockWord& lock, const LockOptions& options) noexcept {
    const std::uint64_t me = self_owner_id();
    if (owner_of(lock.owner.load(std::memory_order_relaxed)) == me) return LockStatus::already_held;
    if (spin(lock, me, options.spin_count)) return LockStatus::acquired;

    const std::int64_t start = now_ns();
    const std::int64_t deadline = options.timeout_ns < 0 ? INT64_MAX : start + options.timeout_ns;
    const std::int64_t period = options.liveness_check_ns > 0 ? options.liveness_check_ns : 1'000'000;
    std::uint64_t suspect = 0;  // an implausible word seen at the end of the last wait
    std::uint64_t refused_word = 0;  // the word the kernel last refused, and since when
    std::int64_t refused_since = 0;
    for (;;) {
        std::uint64_t seen = lock.owner.load(std::memory_order_relaxed);
        if (seen == 0) {
            if (lock.owner.compare_exchange_strong(seen, me, std::memory_order_acquire, std::memory_order_relaxed)) {
                lock.acquisitions.fetch_add(1, std::memory_order_relaxed);
                return LockStatus::acquired;
            }
            continue;
        }
        const std::int64_t now = now_ns();
        const int rc = futex_lock_pi(lock, std::min(deadline, now + period));
        if (rc == 0) return claim(lock, me, now_ns() - start);
        const std::uint64_t after = lock.owner.load(std::memory_order_relaxed);
        switch (rc) {
            case EINTR:
            case EAGAIN:  // the holder is exiting, or the word changed under the kernel: look again
                continue;
            case ESRCH:  // the TID in the word names no live thread: its holder died
                if (owner_tid(after) == owner_tid(seen) && after != 0) {
                    const LockStatus s = take_over(lock, after, now_ns() - start);
                    if (s != LockStatus::busy) return s;
                }
                continue;
            case EDEADLK:
                return LockStatus::already_held;
            case ETIMEDOUT:
                break;
            default:  // EINVAL, EPERM, EFAULT: the kernel refuses the word
                // Also after a holder died with waiters queued (see
                // mark_owner_died), and while the waiter the kernel woke has not
                // yet run to write its TID: nap and look again; refuse a word
                // refused for kRefusedBoundNs (or until the timeout).
                if (after == 0 || mark_owner_died(lock, after)) continue;
                if (after != refused_word) {
                    refused_word = after;
                    refused_since = now_ns();
                } else if (now_ns() - refused_since >= std::max(period, kRefusedBoundNs) ||
                           now_ns() >= deadline) {
                    return refuse_corrupt(lock, after, now_ns() - start);
                }
                nap_ns(kRefusedNapNs);
                continue;
        }
        const std::int64_t waited = now_ns() - start;
        if (implausible(after)) {
            if (after == suspect) return refuse_corrupt(lock, after, waited);
            suspect = after;
        } else {
            suspect = 0;
        }
        if (now_ns() >= deadline) {
            bool retry = false;
            const LockStatus s = on_timeout(lock, me, after, options, waited, retry);
            if (!retry) return s;
        }
    }
}

bool unlock_slow(LockWord& lock, std::uint64_t self, std::uint64_t seen) noexcept {
    // The kernel has waiters (FUTEX_WAITERS): clear the pid half first, which
    // tells the next owner this hand-over is a release, then let the kernel
    // hand the lock to the highest-priority waiter.
    for (;;) {
        if (owner_of(seen) != self) return false;
        if (lock.owner.compare_exchange_weak(seen, seen & 0xffffffffu, std::memory_order_release,
                                             std::memory_order_relaxed))
            break;
    }
    return syscall(SYS_futex, futex_half(lock), FUTEX_UNLOCK_PI, 0, nullptr, nullptr, 0) == 0;
}

}  // namespace chimera::ipc
