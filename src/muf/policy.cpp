// Scheduling classes and CPU pinning for the muf backends: SCHED_FIFO,
// SCHED_OTHER and SCHED_DEADLINE (through the raw sched_setattr system call:
// glibc 2.36 has no wrapper and no struct sched_attr).
#include <fcntl.h>
#include <pthread.h>
#include <sched.h>
#include <sys/mman.h>
#include <sys/syscall.h>
#include <sys/sysinfo.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <mutex>
#include <string>

#include "rt_internal.hpp"

namespace chimera::muf::detail {
namespace {

constexpr unsigned kSchedDeadline = 6;             // SCHED_DEADLINE
constexpr std::uint64_t kFlagDlOverrun = 0x04;     // SCHED_FLAG_DL_OVERRUN

// The kernel's struct sched_attr, version 1 (with the utilisation clamps).
struct SchedAttr {
    std::uint32_t size;
    std::uint32_t sched_policy;
    std::uint64_t sched_flags;
    std::int32_t sched_nice;
    std::uint32_t sched_priority;
    std::uint64_t sched_runtime;
    std::uint64_t sched_deadline;
    std::uint64_t sched_period;
    std::uint32_t sched_util_min;
    std::uint32_t sched_util_max;
};
static_assert(sizeof(SchedAttr) == 56, "SCHED_ATTR_SIZE_VER1");

int sys_sched_setattr(pid_t tid, const SchedAttr& attr) noexcept {
    return static_cast<int>(syscall(SYS_sched_setattr, tid, &attr, 0u));
}

int sys_sched_getattr(pid_t tid, SchedAttr& attr) noexcept {
    return static_cast<int>(
        syscall(SYS_sched_getattr, tid, &attr, static_cast<unsigned>(sizeof attr), 0u));
}

double read_long(const char* path, double fallback) noexcept {
    std::FILE* f = std::fopen(path, "r");
    if (!f) return fallback;
    long v = 0;
    const bool ok = std::fscanf(f, "%ld", &v) == 1;
    std::fclose(f);
    return ok ? static_cast<double>(v) : fallback;
}

}  // namespace

namespace {

bool built_with_sanitizer() noexcept {
#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
    return true;
#elif defined(__has_feature)
#if __has_feature(address_sanitizer) || __has_feature(thread_sanitizer) || __has_feature(memory_sanitizer)
    return true;
#else
    return false;
#endif
#else
    return false;
#endif
}

}  // namespace

std::string lock_memory() {
    static std::once_flag once;
    static std::string note;
    std::call_once(once, [] {
        // A sanitizer's shadow memory is terabytes of reserved address space:
        // locking it is impossible, and its runs are not about timing.
        if (built_with_sanitizer()) {
            note = "memory not locked (sanitizer build)";
            return;
        }
        if (const char* off = std::getenv("CHIMERA_NO_MLOCK"); off != nullptr && *off != '\0' && *off != '0') {
            note = "memory not locked (CHIMERA_NO_MLOCK is set)";
            return;
        }
        // Every page mapped now and later is resident and locked: a cycle
        // never page-faults, and thread stacks made later are faulted in when
        // they are made, not when a cycle first grows into them.
        if (mlockall(MCL_CURRENT | MCL_FUTURE) != 0)
            note = std::string("memory not locked (mlockall: ") + std::strerror(errno) +
                   "); a cycle may page-fault: raise RLIMIT_MEMLOCK (ulimit -l) or run with CAP_IPC_LOCK";
    });
    return note;
}

std::string hold_cpu_wakeup_latency() {
    static std::once_flag once;
    static std::string note;
    std::call_once(once, [] {
        if (const char* off = std::getenv("CHIMERA_NO_CPU_LATENCY"); off != nullptr && *off != '\0' && *off != '0') {
            note = "CPU idle states left alone (CHIMERA_NO_CPU_LATENCY is set)";
            return;
        }
        // A PM QoS request, as cyclictest makes: while this file stays open
        // with 0 in it, no CPU enters an idle state it cannot leave at once,
        // which on a VM or a laptop-class CPU is tens of µs on every release.
        // Held for the life of the process (the kernel drops it at exit).
        const int fd = ::open("/dev/cpu_dma_latency", O_WRONLY | O_CLOEXEC);
        const std::int32_t zero = 0;
        if (fd < 0 || ::write(fd, &zero, sizeof zero) != static_cast<ssize_t>(sizeof zero)) {
            note = std::string("CPU idle states not limited (/dev/cpu_dma_latency: ") + std::strerror(errno) +
                   "): releases may be late by the CPUs' wake-up from idle";
            if (fd >= 0) ::close(fd);
        }
    });
    return note;
}

int pin_to_cpu(int cpu) noexcept {
    cpu_set_t set;
    CPU_ZERO(&set);
    CPU_SET(cpu, &set);
    return pthread_setaffinity_np(pthread_self(), sizeof set, &set);
}

std::string process_cpus_text() {
    // The thread group leader's mask: the CPUs the process's cpuset gives it.
    std::ifstream in("/proc/self/status");
    for (std::string line; std::getline(in, line);)
        if (line.rfind("Cpus_allowed_list:", 0) == 0) {
            const std::size_t at = line.find_first_not_of(" \t", sizeof "Cpus_allowed_list:" - 1);
            return "this process may run on CPUs " + (at == std::string::npos ? std::string("?") : line.substr(at));
        }
    return "the CPUs of this process are unknown";
}

int set_fifo(pid_t tid, int prio) noexcept {
    sched_param sp{};
    sp.sched_priority = prio;
    return sched_setscheduler(tid, SCHED_FIFO, &sp) == 0 ? 0 : errno;
}

int set_other(pid_t tid) noexcept {
    sched_param sp{};
    return sched_setscheduler(tid, SCHED_OTHER, &sp) == 0 ? 0 : errno;
}

int set_deadline_policy(pid_t tid, std::int64_t runtime_ns, std::int64_t deadline_ns,
                        std::int64_t period_ns) noexcept {
    SchedAttr attr{};
    attr.size = sizeof attr;
    attr.sched_policy = kSchedDeadline;
    attr.sched_flags = kFlagDlOverrun;
    attr.sched_runtime = static_cast<std::uint64_t>(runtime_ns);
    attr.sched_deadline = static_cast<std::uint64_t>(deadline_ns);
    attr.sched_period = static_cast<std::uint64_t>(period_ns);
    return sys_sched_setattr(tid, attr) == 0 ? 0 : errno;
}

std::string describe_policy(pid_t tid) {
    SchedAttr attr{};
    if (sys_sched_getattr(tid, attr) != 0) return std::string("unknown (") + std::strerror(errno) + ")";
    std::string text;
    switch (attr.sched_policy) {
        case SCHED_FIFO: text = "SCHED_FIFO " + std::to_string(attr.sched_priority); break;
        case SCHED_RR: text = "SCHED_RR " + std::to_string(attr.sched_priority); break;
        case kSchedDeadline:
            text = "SCHED_DEADLINE " + std::to_string(attr.sched_runtime) + "/" +
                   std::to_string(attr.sched_period);
            break;
        case SCHED_OTHER: text = "SCHED_OTHER"; break;
        default: text = "policy " + std::to_string(attr.sched_policy); break;
    }
    cpu_set_t set;
    CPU_ZERO(&set);
    if (sched_getaffinity(tid, sizeof set, &set) == 0) {
        if (CPU_COUNT(&set) == 1) {
            for (int c = 0; c < CPU_SETSIZE; ++c)
                if (CPU_ISSET(c, &set)) text += " CPU " + std::to_string(c);
        } else {
            text += " (not pinned: " + std::to_string(CPU_COUNT(&set)) + " CPUs)";
        }
    }
    return text;
}

double deadline_bandwidth_per_cpu() noexcept {
    const double runtime = read_long("/proc/sys/kernel/sched_rt_runtime_us", 950000);
    const double period = read_long("/proc/sys/kernel/sched_rt_period_us", 1000000);
    if (runtime < 0 || period <= 0) return 1.0;  // -1: no limit
    return runtime / period;
}

}  // namespace chimera::muf::detail
