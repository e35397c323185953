// syscall_counter.hpp — counts the calling thread's system calls with a
// per-thread perf counter on the raw_syscalls:sys_enter tracepoint, for the
// "no system call on the real-time path" tests. Needs tracefs mounted
// (tests/prof/in_tracefs_namespace.sh mounts it in a private namespace).
#pragma once

#include <linux/futex.h>
#include <linux/perf_event.h>
#include <sys/ioctl.h>
#include <sys/syscall.h>
#include <sys/types.h>
#include <unistd.h>

#include <cstdint>
#include <cstring>
#include <fstream>
#include <string>

namespace chimera::test {

/// A counter of this thread's system calls from now on (or of thread `tid`
/// of this process, read from another thread: the reads are not its calls);
/// -1 when the tracepoint is not available (no tracefs, no permission).
inline int open_syscall_counter(pid_t tid = 0) {
    std::ifstream f("/sys/kernel/tracing/events/raw_syscalls/sys_enter/id");
    if (!f) f.open("/sys/kernel/debug/tracing/events/raw_syscalls/sys_enter/id");
    long id = -1;
    if (!(f >> id)) return -1;
    perf_event_attr a;
    std::memset(&a, 0, sizeof a);
    a.size = sizeof a;
    a.type = PERF_TYPE_TRACEPOINT;
    a.config = static_cast<std::uint64_t>(id);
    return static_cast<int>(syscall(SYS_perf_event_open, &a, tid, -1, -1, PERF_FLAG_FD_CLOEXEC));
}

/// The id of a tracefs event ("raw_syscalls/sys_enter"), or -1.
inline long tracepoint_id(const char* event) {
    for (const char* root : {"/sys/kernel/tracing/events/", "/sys/kernel/debug/tracing/events/"}) {
        std::ifstream f(std::string(root) + event + "/id");
        long id = -1;
        if (f >> id) return id;
    }
    return -1;
}

/// The release wait of a runtime task: FUTEX_WAIT_BITSET on its own
/// process-private command word (src/muf/rt.cpp, wait_words).
constexpr int kReleaseWaitFutexOp = FUTEX_WAIT_BITSET | FUTEX_PRIVATE_FLAG;

/// A counter of thread `tid`'s futex(2) calls that pass `filter` (a tracefs
/// filter over the tracepoint's fields: op, utime, ...) on the
/// syscalls:sys_enter_futex tracepoint; -1 when it cannot be opened.
inline int open_futex_counter(long tid, const std::string& filter) {
    const long id = tracepoint_id("syscalls/sys_enter_futex");
    if (id < 0) return -1;
    perf_event_attr a;
    std::memset(&a, 0, sizeof a);
    a.size = sizeof a;
    a.type = PERF_TYPE_TRACEPOINT;
    a.config = static_cast<std::uint64_t>(id);
    const int fd = static_cast<int>(syscall(SYS_perf_event_open, &a, static_cast<pid_t>(tid), -1, -1, PERF_FLAG_FD_CLOEXEC));
    if (fd >= 0 && ioctl(fd, PERF_EVENT_IOC_SET_FILTER, filter.c_str()) != 0) {
        close(fd);
        return -1;
    }
    return fd;
}

/// A counter of thread `tid`'s futex(2) calls other than the release wait —
/// the table lock found busy, a wake.
inline int open_other_futex_counter(long tid) {
    return open_futex_counter(tid, "op != " + std::to_string(kReleaseWaitFutexOp));
}

/// The count so far (itself one system call, after the value is taken).
inline std::uint64_t read_syscall_counter(int fd) {
    std::uint64_t v = 0;
    if (read(fd, &v, sizeof v) != sizeof v) return ~0ull;
    return v;
}

}  // namespace chimera::test
