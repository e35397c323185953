// The table lock's slow path: spin, poll, detect dead holders, time out.
#include "chimera/ipc/lock.hpp"

#include <fcntl.h>
#include <pthread.h>
#include <sys/syscall.h>
#include <unistd.h>

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

void sleep_ns(std::int64_t ns) noexcept {
    timespec ts = to_timespec(ns);
    while (nanosleep(&ts, &ts) != 0 && errno == EINTR) {
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

bool owner_alive(std::uint64_t word) noexcept {
    const std::int32_t pid = owner_pid(word);
    const std::int32_t tid = owner_tid(word);
    if (pid <= 0 || tid <= 0) return false;
    if (syscall(SYS_tgkill, pid, tid, 0) != 0 && errno == ESRCH) return false;
    // tgkill succeeds on a zombie (killed, not yet reaped): look at its state.
    char path[64];
    std::snprintf(path, sizeof path, "/proc/%d/task/%d/stat", pid, tid);
    const int fd = open(path, O_RDONLY | O_CLOEXEC);
    if (fd < 0) return errno != ENOENT;  // without /proc, trust tgkill
    char buf[512];
    const ssize_t n = read(fd, buf, sizeof buf - 1);
    close(fd);
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
        return expected == self_owner_id() ? LockStatus::already_held : LockStatus::busy;
    lock.recoveries.fetch_add(1, std::memory_order_relaxed);
    lock.acquisitions.fetch_add(1, std::memory_order_relaxed);
    report(LockEvent::Kind::recovered, lock, dead_owner, waited_ns);
    return LockStatus::recovered;
}

LockStatus lock_slow(LockWord& lock, const LockOptions& options) noexcept {
    const std::uint64_t me = self_owner_id();
    std::uint64_t seen = lock.owner.load(std::memory_order_relaxed);
    if (seen == me) return LockStatus::already_held;

    // Phase 1: bounded spin (test-and-test-and-set) with the polling pause.
    for (std::uint32_t i = 0; i < options.spin_count; ++i) {
        cpu_pause();
        seen = lock.owner.load(std::memory_order_relaxed);
        if (seen == 0) {
            if (lock.owner.compare_exchange_weak(seen, me, std::memory_order_acquire,
                                                 std::memory_order_relaxed)) {
                lock.acquisitions.fetch_add(1, std::memory_order_relaxed);
                return LockStatus::acquired;
            }
        }
    }

    // Phase 2: poll with short sleeps; check the holder's liveness now and then.
    const std::int64_t start = now_ns();
    const std::int64_t deadline = options.timeout_ns < 0 ? INT64_MAX : start + options.timeout_ns;
    std::int64_t next_check = start;  // check at once: the holder may be long dead
    std::int64_t sleep = options.min_sleep_ns > 0 ? options.min_sleep_ns : 1000;
    for (;;) {
        seen = lock.owner.load(std::memory_order_relaxed);
        if (seen == 0) {
            if (lock.owner.compare_exchange_strong(seen, me, std::memory_order_acquire,
                                                   std::memory_order_relaxed)) {
                lock.acquisitions.fetch_add(1, std::memory_order_relaxed);
                return LockStatus::acquired;
            }
            continue;
        }
        const std::int64_t now = now_ns();
        if (now >= next_check) {
            if (!owner_alive(seen)) {
                const LockStatus s = take_over(lock, seen, now - start);
                if (s == LockStatus::recovered) return s;
                continue;  // someone else took it over first: keep polling
            }
            next_check = now + options.liveness_check_ns;
        }
        if (now >= deadline) {
            if (options.reset_on_timeout) {
                std::uint64_t expected = seen;
                if (lock.owner.compare_exchange_strong(expected, me, std::memory_order_acquire,
                                                       std::memory_order_relaxed)) {
                    lock.forced.fetch_add(1, std::memory_order_relaxed);
                    lock.acquisitions.fetch_add(1, std::memory_order_relaxed);
                    report(LockEvent::Kind::forced, lock, seen, now - start);
                    return LockStatus::forced;
                }
                continue;
            }
            lock.timeouts.fetch_add(1, std::memory_order_relaxed);
            report(LockEvent::Kind::timed_out, lock, seen, now - start);
            return LockStatus::timed_out;
        }
        std::int64_t nap = sleep;
        if (nap > deadline - now) nap = deadline - now;
        sleep_ns(nap);
        if (sleep < options.max_sleep_ns) sleep *= 2;
        if (sleep > options.max_sleep_ns) sleep = options.max_sleep_ns;
    }
}

}  // namespace chimera::ipc
