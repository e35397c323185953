// Express mail, SEM and MSG costs (thesis §5.3, §5.4), each next to the
// POSIX mechanisms a Linux programmer would otherwise use, measured in the
// same run with the same message sizes:
//
//   XmWriteRead        xmWrite into this RTPU's own mailbox ring + xmRead
//   MsgSendReceive     msgSend + msgReceive on one queue, one process
//   MqSendReceive      mq_send + mq_receive, one process       (baseline)
//   PipeWriteRead      write + read on one pipe, one process   (baseline)
//   SemPV              semP + semV, uncontended
//   PosixSemPV         sem_wait + sem_post (process-shared), uncontended (baseline)
//   SemPingPong        two processes, two semaphores: V(a) P(b) against P(a) V(b);
//                      every P blocks and is woken by the other process's V
//   MsgPingPong        two processes, a request and a reply queue, blocking
//                      receives: one round trip = 2 sends, 2 woken receives
//   MqPingPong         the same with two POSIX message queues (baseline)
//   PipePingPong       the same with two pipes (baseline)
//   MsgBusyPingPong    MSG round trip with both sides polling (receive with
//                      timeout 0 in a loop, no wake-up): the peer is iceoryx2's
//                      busy-waiting publish/subscribe ping-pong (measured apart,
//                      bench/results/xmail.md)
//
// Placement (second argument of the round trips): 0 = the two processes on
// two cores (CPUs 0 and 1), 1 = both on CPU 1 (every hand-off is a context
// switch), 2 = not pinned.
//
// Cross-process objects are laid over a MAP_SHARED mapping inherited by a
// forked child (the name server is a set-up path, not measured); the futex
// words and locks are the shared ones a named object uses. Argument: bytes
// per message (1 = a token, the baseline for SemPingPong). Ping-pong times
// are one round trip, wall clock; the rest are best read as CPU time on a
// machine shared with other work.
#include <benchmark/benchmark.h>
#include <fcntl.h>
#include <mqueue.h>
#include <sched.h>
#include <semaphore.h>
#include <signal.h>
#include <sys/mman.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <new>
#include <string>
#include <vector>

#include "chimera/ipc/clock.hpp"
#include "chimera/msg.hpp"
#include "chimera/sem.hpp"
#include "chimera/xmail.hpp"

namespace {

using chimera::xm::Status;
namespace msg = chimera::msg;
namespace sem = chimera::sem;
namespace xm = chimera::xm;

[[noreturn]] void die(const char* what) {
    std::perror(what);
    std::abort();
}

// A zeroed MAP_SHARED anonymous mapping: shared with children forked later.
struct SharedMemory {
    explicit SharedMemory(std::size_t n) : size(n) {
        ptr = mmap(nullptr, n, PROT_READ | PROT_WRITE, MAP_SHARED | MAP_ANONYMOUS, -1, 0);
        if (ptr == MAP_FAILED) die("mmap");
    }
    ~SharedMemory() { munmap(ptr, size); }
    SharedMemory(const SharedMemory&) = delete;
    SharedMemory& operator=(const SharedMemory&) = delete;
    void* ptr;
    std::size_t size;
};

msg::Params queue_params() {
    msg::Params p;
    p.blknum = 16;
    p.blksize = 1024;  // every benchmarked size fits one block
    p.policy = msg::Policy::fifo;
    return p;
}

// Reaps the ping-pong partner; a partner that failed makes the benchmark fail.
void reap(benchmark::State& state, pid_t child) {
    int status = 0;
    waitpid(child, &status, 0);
    if (!WIFEXITED(status) || WEXITSTATUS(status) != 0) state.SkipWithError("partner process failed");
}

constexpr std::int64_t kPartnerTimeout = 5'000'000'000;  // a partner never hangs

// The MSG round trip blocks without a time limit, as mq_send/mq_receive do
// beside it (a timed wait arms a kernel timer, one more cost than the
// baseline pays). Instead of timeouts, a process that stops answering ends
// the whole run: SIGALRM after this long without a finished benchmark, and
// the partner dies with its parent (PR_SET_PDEATHSIG).
constexpr std::int64_t kWaitForever = -1;
constexpr unsigned kWatchdogSeconds = 120;

// Each round trip's own time (one clock read per trip, as the peers'
// harness in ../shared/peers/ipc-baselines does): reported as the counters
// p50_ns and p99_ns beside Google Benchmark's mean, which a single trip
// preempted by other work on a shared machine can move a lot.
class RoundTrips {
public:
    RoundTrips() { samples_.reserve(kMax); }
    void start() noexcept { last_ = chimera::ipc::now_ns(); }
    void mark() noexcept {
        const std::int64_t now = chimera::ipc::now_ns();
        if (samples_.size() < kMax) samples_.push_back(now - last_);
        last_ = now;
    }
    void report(benchmark::State& state) {
        if (samples_.empty()) return;
        const auto at = [&](double q) {
            auto nth = samples_.begin() + static_cast<std::ptrdiff_t>(q * static_cast<double>(samples_.size() - 1));
            std::nth_element(samples_.begin(), nth, samples_.end());
            return static_cast<double>(*nth);
        };
        state.counters["p50_ns"] = at(0.5);
        state.counters["p99_ns"] = at(0.99);
    }

private:
    static constexpr std::size_t kMax = std::size_t{1} << 21;
    std::vector<std::int64_t> samples_;
    std::int64_t last_ = 0;
};

// Placement of a round trip (see the top): the caller's CPU, and its
// partner's (applied in the child after fork()). Restores the caller's
// affinity when the benchmark ends.
class Placement {
public:
    explicit Placement(const benchmark::State& state) : kind_(static_cast<int>(state.range(1))) {
        sched_getaffinity(0, sizeof saved_, &saved_);
        if (kind_ != 2) pin(kind_ == 0 ? 0 : 1);
    }
    ~Placement() { sched_setaffinity(0, sizeof saved_, &saved_); }
    Placement(const Placement&) = delete;
    Placement& operator=(const Placement&) = delete;
    /// In the forked partner.
    void partner() const {
        if (kind_ != 2) pin(1);
    }

private:
    static void pin(int cpu) {
        cpu_set_t set;
        CPU_ZERO(&set);
        CPU_SET(cpu, &set);
        if (sched_setaffinity(0, sizeof set, &set) != 0) die("sched_setaffinity");
    }
    int kind_;
    cpu_set_t saved_{};
};

// ------------------------------------------------------------- one process

void XmWriteRead(benchmark::State& state) {
    const auto size = static_cast<std::size_t>(state.range(0));
    const std::string sys = "bx" + std::to_string(getpid());
    xm::Mailbox mb(sys, "r0", 0);
    xm::Peer& self = mb.peer("r0");
    std::vector<char> out(size, 'x'), in(size);
    for (auto _ : state) {
        if (mb.write(self, out.data(), size, 0) != Status::ok) state.SkipWithError("xmWrite failed");
        xm::ReadInfo info;
        if (mb.read(in.data(), in.size(), &info) != Status::ok) state.SkipWithError("xmRead failed");
        benchmark::DoNotOptimize(in.data());
    }
    state.SetBytesProcessed(static_cast<std::int64_t>(state.iterations() * size));
}

void MsgSendReceive(benchmark::State& state) {
    const auto size = static_cast<std::size_t>(state.range(0));
    const msg::Params p = queue_params();
    std::vector<std::uint64_t> memory(msg::Queue::memory_size(p) / 8 + 1);
    msg::Queue q = msg::Queue::over(memory.data(), memory.size() * 8, p, "bench:q");
    std::vector<char> out(size, 'x'), in(size);
    for (auto _ : state) {
        if (q.send(out.data(), size, 0, 0, 0) != Status::ok) state.SkipWithError("msgSend failed");
        msg::Info info;
        if (q.receive(in.data(), in.size(), &info, 0) != Status::ok) state.SkipWithError("msgReceive failed");
        benchmark::DoNotOptimize(in.data());
    }
    state.SetBytesProcessed(static_cast<std::int64_t>(state.iterations() * size));
}

mqd_t open_mq(const std::string& name) {
    mq_attr attr{};
    attr.mq_maxmsg = 8;
    attr.mq_msgsize = 1024;
    const mqd_t q = mq_open(name.c_str(), O_RDWR | O_CREAT | O_EXCL, 0600, &attr);
    if (q == static_cast<mqd_t>(-1)) die("mq_open");
    mq_unlink(name.c_str());  // gone when the last descriptor closes
    return q;
}

void MqSendReceive(benchmark::State& state) {
    const auto size = static_cast<std::size_t>(state.range(0));
    const mqd_t q = open_mq("/bench_xmail_mq." + std::to_string(getpid()));
    std::vector<char> out(size, 'x'), in(1024);
    for (auto _ : state) {
        if (mq_send(q, out.data(), size, 0) != 0) state.SkipWithError("mq_send failed");
        if (mq_receive(q, in.data(), in.size(), nullptr) != static_cast<ssize_t>(size))
            state.SkipWithError("mq_receive failed");
        benchmark::DoNotOptimize(in.data());
    }
    mq_close(q);
    state.SetBytesProcessed(static_cast<std::int64_t>(state.iterations() * size));
}

void PipeWriteRead(benchmark::State& state) {
    const auto size = static_cast<std::size_t>(state.range(0));
    int fd[2];
    if (pipe(fd) != 0) die("pipe");
    std::vector<char> out(size, 'x'), in(size);
    for (auto _ : state) {
        if (write(fd[1], out.data(), size) != static_cast<ssize_t>(size)) state.SkipWithError("write failed");
        if (read(fd[0], in.data(), size) != static_cast<ssize_t>(size)) state.SkipWithError("read failed");
        benchmark::DoNotOptimize(in.data());
    }
    close(fd[0]);
    close(fd[1]);
    state.SetBytesProcessed(static_cast<std::int64_t>(state.iterations() * size));
}

void SemPV(benchmark::State& state) {
    alignas(64) static std::byte memory[sem::Semaphore::memory_size()];
    sem::Semaphore s = sem::Semaphore::over(memory, sem::Kind::binary, 1, "bench:s");
    for (auto _ : state) {
        if (s.p(0) != Status::ok) state.SkipWithError("semP failed");
        if (s.v() != Status::ok) state.SkipWithError("semV failed");
    }
}

void PosixSemPV(benchmark::State& state) {
    SharedMemory m(sizeof(sem_t));
    auto* s = static_cast<sem_t*>(m.ptr);
    sem_init(s, 1, 1);
    for (auto _ : state) {
        if (sem_wait(s) != 0) state.SkipWithError("sem_wait failed");
        sem_post(s);
    }
    sem_destroy(s);
}

// ------------------------------------------------------------- two processes

void SemPingPong(benchmark::State& state) {
    struct Shared {
        alignas(64) std::byte ping[sem::Semaphore::memory_size()];
        alignas(64) std::byte pong[sem::Semaphore::memory_size()];
        std::atomic<std::uint32_t> stop;
    };
    SharedMemory m(sizeof(Shared));
    auto* sh = new (m.ptr) Shared{};
    sem::Semaphore ping = sem::Semaphore::over(sh->ping, sem::Kind::binary, 0, "bench:ping");
    sem::Semaphore pong = sem::Semaphore::over(sh->pong, sem::Kind::binary, 0, "bench:pong");
    const Placement place(state);
    const pid_t child = fork();
    if (child < 0) die("fork");
    if (child == 0) {
        place.partner();
        for (;;) {
            if (ping.p(kPartnerTimeout) != Status::ok) _exit(1);
            if (sh->stop.load()) _exit(0);
            if (pong.v() != Status::ok) _exit(1);
        }
    }
    RoundTrips trips;
    trips.start();
    for (auto _ : state) {
        if (ping.v() != Status::ok) {
            state.SkipWithError("semV failed");
            break;
        }
        if (pong.p(kPartnerTimeout) != Status::ok) {
            state.SkipWithError("semP timed out");
            break;
        }
        trips.mark();
    }
    sh->stop.store(1);
    if (ping.v() != Status::ok) kill(child, SIGKILL);  // the partner never sees the stop: reap() reports it
    trips.report(state);
    reap(state, child);
}

void MsgPingPong(benchmark::State& state) {
    const auto size = static_cast<std::size_t>(state.range(0));
    const msg::Params p = queue_params();
    const std::size_t qsize = (msg::Queue::memory_size(p) + 63) & ~std::size_t{63};
    SharedMemory m(2 * qsize);
    msg::Queue request = msg::Queue::over(m.ptr, qsize, p, "bench:request");
    msg::Queue reply = msg::Queue::over(static_cast<std::byte*>(m.ptr) + qsize, qsize, p, "bench:reply");
    std::vector<char> out(size, 'x'), in(1024);
    const Placement place(state);
    const pid_t child = fork();
    if (child < 0) die("fork");
    if (child == 0) {
        prctl(PR_SET_PDEATHSIG, SIGKILL);
        place.partner();
        for (;;) {
            msg::Info info;
            if (request.receive(in.data(), in.size(), &info, kWaitForever) != Status::ok) _exit(1);
            if (info.type == 1) _exit(0);  // stop
            if (reply.send(in.data(), info.size, 0, 0, kWaitForever) != Status::ok) _exit(1);
        }
    }
    alarm(kWatchdogSeconds);
    RoundTrips trips;
    trips.start();
    for (auto _ : state) {
        if (request.send(out.data(), size, 0, 0, kWaitForever) != Status::ok) {
            state.SkipWithError("msgSend timed out");
            break;
        }
        msg::Info info;
        if (reply.receive(in.data(), in.size(), &info, kWaitForever) != Status::ok) {
            state.SkipWithError("msgReceive timed out");
            break;
        }
        trips.mark();
    }
    if (request.send(out.data(), 0, 1, 0, kWaitForever) != Status::ok) kill(child, SIGKILL);  // see reap()
    trips.report(state);
    reap(state, child);
    alarm(0);
    state.SetBytesProcessed(static_cast<std::int64_t>(state.iterations() * size * 2));
}

void MqPingPong(benchmark::State& state) {
    const auto size = static_cast<std::size_t>(state.range(0));
    const std::string base = "/bench_xmail_mq." + std::to_string(getpid());
    const mqd_t request = open_mq(base + ".request");
    const mqd_t reply = open_mq(base + ".reply");
    std::vector<char> out(size, 'x'), in(1024);
    const Placement place(state);
    const pid_t child = fork();
    if (child < 0) die("fork");
    if (child == 0) {
        place.partner();
        for (;;) {
            unsigned prio = 0;
            const ssize_t n = mq_receive(request, in.data(), in.size(), &prio);
            if (n < 0) _exit(1);
            if (prio == 1) _exit(0);  // stop
            if (mq_send(reply, in.data(), static_cast<std::size_t>(n), 0) != 0) _exit(1);
        }
    }
    RoundTrips trips;
    trips.start();
    for (auto _ : state) {
        mq_send(request, out.data(), size, 0);
        if (mq_receive(reply, in.data(), in.size(), nullptr) != static_cast<ssize_t>(size)) {
            state.SkipWithError("mq_receive failed");
            break;
        }
        trips.mark();
    }
    mq_send(request, out.data(), 0, 1);
    trips.report(state);
    reap(state, child);
    mq_close(request);
    mq_close(reply);
    state.SetBytesProcessed(static_cast<std::int64_t>(state.iterations() * size * 2));
}

// Both sides poll (receive with timeout 0) instead of sleeping: no system
// call, no wake-up; only meaningful with the two processes on two cores.
void MsgBusyPingPong(benchmark::State& state) {
    const auto size = static_cast<std::size_t>(state.range(0));
    const msg::Params p = queue_params();
    const std::size_t qsize = (msg::Queue::memory_size(p) + 63) & ~std::size_t{63};
    SharedMemory m(2 * qsize);
    msg::Queue request = msg::Queue::over(m.ptr, qsize, p, "bench:request");
    msg::Queue reply = msg::Queue::over(static_cast<std::byte*>(m.ptr) + qsize, qsize, p, "bench:reply");
    std::vector<char> out(size, 'x'), in(1024);
    const Placement place(state);
    const auto poll = [&](msg::Queue& q, msg::Info& info) {
        const std::int64_t deadline = chimera::ipc::now_ns() + kPartnerTimeout;
        for (;;) {
            const Status st = q.receive(in.data(), in.size(), &info, 0);
            if (st != Status::would_block) return st;
            if (chimera::ipc::now_ns() > deadline) return Status::timed_out;
        }
    };
    const pid_t child = fork();
    if (child < 0) die("fork");
    if (child == 0) {
        place.partner();
        for (;;) {
            msg::Info info;
            if (poll(request, info) != Status::ok) _exit(1);
            if (info.type == 1) _exit(0);  // stop
            if (reply.send(in.data(), info.size, 0, 0, 0) != Status::ok) _exit(1);
        }
    }
    RoundTrips trips;
    trips.start();
    for (auto _ : state) {
        if (request.send(out.data(), size, 0, 0, 0) != Status::ok) {
            state.SkipWithError("msgSend refused");
            break;
        }
        msg::Info info;
        if (poll(reply, info) != Status::ok) {
            state.SkipWithError("msgReceive polled in vain");
            break;
        }
        trips.mark();
    }
    if (request.send(out.data(), 0, 1, 0, kPartnerTimeout) != Status::ok) kill(child, SIGKILL);  // see reap()
    trips.report(state);
    reap(state, child);
    state.SetBytesProcessed(static_cast<std::int64_t>(state.iterations() * size * 2));
}

bool read_all(int fd, char* p, std::size_t n) {
    while (n > 0) {
        const ssize_t r = read(fd, p, n);
        if (r <= 0) return false;
        p += r;
        n -= static_cast<std::size_t>(r);
    }
    return true;
}

void PipePingPong(benchmark::State& state) {
    const auto size = static_cast<std::size_t>(state.range(0));
    int request[2], reply[2];
    if (pipe(request) != 0 || pipe(reply) != 0) die("pipe");
    std::vector<char> out(size, 'x'), in(size);
    const Placement place(state);
    const pid_t child = fork();
    if (child < 0) die("fork");
    if (child == 0) {
        place.partner();
        close(request[1]);
        close(reply[0]);
        // The parent closing its end is the stop.
        while (read_all(request[0], in.data(), size))
            if (write(reply[1], in.data(), size) != static_cast<ssize_t>(size)) _exit(1);
        _exit(0);
    }
    close(request[0]);
    close(reply[1]);
    RoundTrips trips;
    trips.start();
    for (auto _ : state) {
        if (write(request[1], out.data(), size) != static_cast<ssize_t>(size) ||
            !read_all(reply[0], in.data(), size)) {
            state.SkipWithError("pipe round trip failed");
            break;
        }
        trips.mark();
    }
    close(request[1]);
    trips.report(state);
    reap(state, child);
    close(reply[0]);
    state.SetBytesProcessed(static_cast<std::int64_t>(state.iterations() * size * 2));
}

void Sizes(benchmark::internal::Benchmark* b) {
    for (int size : {24, 144, 1024}) b->Arg(size);
}
// Round trips also with a 1-byte token (the pipe/mqueue equivalent of
// SemPingPong), in each placement.
void RoundTripSizes(benchmark::internal::Benchmark* b) {
    b->ArgNames({"bytes", "place"});
    for (int place : {0, 1, 2})
        for (int size : {1, 24, 144, 1024}) b->Args({size, place});
}
void PlacementOnly(benchmark::internal::Benchmark* b) {
    b->ArgNames({"bytes", "place"});
    for (int place : {0, 1, 2}) b->Args({1, place});
}
void BusySizes(benchmark::internal::Benchmark* b) {
    b->ArgNames({"bytes", "place"});
    for (int size : {24, 144, 1024}) b->Args({size, 0});
}

BENCHMARK(XmWriteRead)->Apply(Sizes);
BENCHMARK(MsgSendReceive)->Apply(Sizes);
BENCHMARK(MqSendReceive)->Apply(Sizes);
BENCHMARK(PipeWriteRead)->Apply(Sizes);
BENCHMARK(SemPV);
BENCHMARK(PosixSemPV);
BENCHMARK(SemPingPong)->Apply(PlacementOnly)->UseRealTime();
BENCHMARK(MsgPingPong)->Apply(RoundTripSizes)->UseRealTime();
BENCHMARK(MqPingPong)->Apply(RoundTripSizes)->UseRealTime();
BENCHMARK(PipePingPong)->Apply(RoundTripSizes)->UseRealTime();
BENCHMARK(MsgBusyPingPong)->Apply(BusySizes)->UseRealTime();

}  // namespace

BENCHMARK_MAIN();
