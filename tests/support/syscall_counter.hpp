// syscall_counter.hpp — counts the calling thread's system calls with a
// per-thread perf counter on the raw_syscalls:sys_enter tracepoint, for the
// "no system call on the real-time path" tests. Needs tracefs mounted
// (tests/prof/in_tracefs_namespace.sh mounts it in a private namespace).
#pragma once

#include <linux/perf_event.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <cstdint>
#include <cstring>
#include <fstream>

namespace chimera::test {

/// A counter of this thread's system calls from now on; -1 when the
/// tracepoint is not available (no tracefs, no permission).
inline int open_syscall_counter() {
    std::ifstream f("/sys/kernel/tracing/events/raw_syscalls/sys_enter/id");
    if (!f) f.open("/sys/kernel/debug/tracing/events/raw_syscalls/sys_enter/id");
    long id = -1;
    if (!(f >> id)) return -1;
    perf_event_attr a;
    std::memset(&a, 0, sizeof a);
    a.size = sizeof a;
    a.type = PERF_TYPE_TRACEPOINT;
    a.config = static_cast<std::uint64_t>(id);
    return static_cast<int>(syscall(SYS_perf_event_open, &a, 0, -1, -1, PERF_FLAG_FD_CLOEXEC));
}

/// The count so far (itself one system call, after the value is taken).
inline std::uint64_t read_syscall_counter(int fd) {
    std::uint64_t v = 0;
    if (read(fd, &v, sizeof v) != sizeof v) return ~0ull;
    return v;
}

}  // namespace chimera::test
