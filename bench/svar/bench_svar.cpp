// SVAR and TBUF transfer costs, in the shape of the thesis's Tables 2 and 3
// (§6.6.1), with the baselines measured in the same run:
//
//   Memcpy              the raw data transfer alone (the floor)
//   AtomicLockUnlock    one uncontended test-and-set lock/unlock pair on a
//                       plain atomic word (what a lock can cost at the least)
//   AtomicLockMemcpy    the two together: the floor a locked transfer is
//                       measured against
//   AtomicLockCopyVar   the same floor with the copy routine the table uses
//                       (detail::copy_var: inline moves for 8..64 bytes, memcpy
//                       beyond) instead of memcpy: what is left of the distance
//                       to the floor once the copy itself is the same
//   PthreadMutexMemcpy  pthread mutex + memcpy (what most frameworks do)
//   TableLockUnlock     the SVAR table lock (ipc::lock / ipc::unlock)
//   SvarRead/Write      N single-variable transfers (svarRead / svarWrite):
//                       one lock per variable
//   SvarCopyFrom/To     one multi-variable transfer of N variables
//                       (svarCopyFromShm / svarCopyToShm): one lock
//   TbufWriteRead       one item written and read back (tbufWrite + tbufRead)
//   PthreadMutexWriteRead  the same item through a mutex-protected buffer
//   PthreadMutexWriteReadStamped  the same, time-stamped by the writer as TBUF does
//   MonotonicClock      the clock read that tbufWrite's time-stamp costs
//
// Arguments are {nelem, count}: `count` variables of float[nelem]. The table
// is a real one in POSIX shared memory, created from a .svar file written at
// start-up; the transfers go through the public API.
#include <benchmark/benchmark.h>
#include <pthread.h>
#include <unistd.h>

#include <array>
#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <memory>
#include <string>
#include <vector>

#include "chimera/ipc/clock.hpp"
#include "chimera/ipc/lock.hpp"
#include "chimera/ipc/segment.hpp"
#include "chimera/svar.hpp"
#include "chimera/tbuf.hpp"
#include "layout.hpp"  // detail::copy_var, for the floor with the table's own copy

namespace {

using chimera::svar::LocalTable;
using chimera::svar::Status;
using chimera::svar::Table;
using chimera::svar::VarSet;

constexpr std::array<int, 3> kNelems{6, 32, 256};
constexpr int kMaxCount = 6;

std::size_t size_index(std::int64_t nelem) {
    for (std::size_t i = 0; i < kNelems.size(); ++i)
        if (kNelems[i] == nelem) return i;
    std::fprintf(stderr, "bench_svar: no variables of float[%lld]\n", static_cast<long long>(nelem));
    std::abort();
}

std::string var_name(int nelem, int k) { return "F" + std::to_string(nelem) + "_" + std::to_string(k); }

// The .svar file: six variables of each size, F6_0..F6_5, F32_0.., F256_0..
std::string write_svar_file() {
    const std::string path = "/tmp/bench_svar." + std::to_string(getpid()) + ".svar";
    std::ofstream f(path);
    f << "# written by bench_svar at start-up\n";
    for (int nelem : kNelems)
        for (int k = 0; k < kMaxCount; ++k)
            f << "NAME  " << var_name(nelem, k) << "\nTYPE  float\nDESC  bench variable\n"
              << "UNITS none\nNELEM " << nelem << "\n\n";
    f << "EOF\n";
    if (!f) {
        std::fprintf(stderr, "bench_svar: cannot write %s\n", path.c_str());
        std::abort();
    }
    return path;
}

// One table, one local table holding every variable, and the sets used below.
struct Setup {
    std::string svar_file;
    Table table;
    std::unique_ptr<LocalTable> local;
    float* vars[kNelems.size()][kMaxCount]{};
    VarSet sets[kNelems.size()][kMaxCount + 1];  // [size][count]

    Setup() {
        svar_file = write_svar_file();
        table = Table::create(
            chimera::ipc::segment_name("bench" + std::to_string(getpid()), "svar"), svar_file);
        std::vector<std::string> names;
        for (int nelem : kNelems)
            for (int k = 0; k < kMaxCount; ++k) names.push_back(var_name(nelem, k));
        local = std::make_unique<LocalTable>(table, names);
        for (std::size_t s = 0; s < kNelems.size(); ++s) {
            for (int k = 0; k < kMaxCount; ++k)
                vars[s][k] = local->translate<float>(var_name(kNelems[s], k));
            for (int count : {1, 2, 6}) {
                std::vector<std::string> set;
                for (int k = 0; k < count; ++k) set.push_back(var_name(kNelems[s], k));
                sets[s][count] = local->make_set(set);
            }
        }
    }
    ~Setup() {
        local.reset();
        table.destroy();
        std::remove(svar_file.c_str());
    }
};

Setup& setup() {
    static Setup s;
    return s;
}

void check(Status s, benchmark::State& state) {
    if (s != Status::ok) state.SkipWithError(chimera::svar::to_string(s));
}

// Plain buffers for the baselines, laid out like the table's data: `count`
// variables of `bytes` each, 16-byte aligned.
struct Buffers {
    explicit Buffers(std::size_t bytes) : stride((bytes + 15) / 16 * 16) {
        src.assign(stride * kMaxCount / sizeof(float) + 16, 1.0f);
        dst.assign(stride * kMaxCount / sizeof(float) + 16, 0.0f);
    }
    std::size_t stride;
    std::vector<float> src, dst;
    char* s(int k) { return reinterpret_cast<char*>(src.data()) + k * stride; }
    char* d(int k) { return reinterpret_cast<char*>(dst.data()) + k * stride; }
};

void set_counters(benchmark::State& state, std::size_t bytes_per_iteration) {
    state.SetBytesProcessed(static_cast<std::int64_t>(state.iterations() * bytes_per_iteration));
}

// --- baselines ---------------------------------------------------------------

// The sizes are hidden from the compiler so that it calls memcpy as the table
// code must (its sizes come from the table at run time), instead of turning a
// 24-byte copy into three moves.
void BM_Memcpy(benchmark::State& state) {
    const int count = static_cast<int>(state.range(1));
    std::size_t bytes = static_cast<std::size_t>(state.range(0)) * sizeof(float);
    Buffers b(bytes);
    for (auto _ : state) {
        benchmark::DoNotOptimize(bytes);
        for (int k = 0; k < count; ++k) std::memcpy(b.d(k), b.s(k), bytes);
        benchmark::DoNotOptimize(b.dst.data());
        benchmark::ClobberMemory();
    }
    set_counters(state, bytes * count);
}

// A minimal test-and-set lock on a plain atomic word: CAS to take, store to give.
struct AtomicLock {
    std::atomic<std::uint64_t> word{0};
    void lock() noexcept {
        std::uint64_t expected = 0;
        while (!word.compare_exchange_weak(expected, 1, std::memory_order_acquire,
                                           std::memory_order_relaxed))
            expected = 0;
    }
    void unlock() noexcept { word.store(0, std::memory_order_release); }
};

void BM_AtomicLockUnlock(benchmark::State& state) {
    alignas(64) AtomicLock l;
    for (auto _ : state) {
        l.lock();
        benchmark::ClobberMemory();
        l.unlock();
    }
}

void BM_AtomicLockMemcpy(benchmark::State& state) {
    const int count = static_cast<int>(state.range(1));
    std::size_t bytes = static_cast<std::size_t>(state.range(0)) * sizeof(float);
    Buffers b(bytes);
    alignas(64) AtomicLock l;
    for (auto _ : state) {
        benchmark::DoNotOptimize(bytes);
        l.lock();
        for (int k = 0; k < count; ++k) std::memcpy(b.d(k), b.s(k), bytes);
        l.unlock();
        benchmark::DoNotOptimize(b.dst.data());
        benchmark::ClobberMemory();
    }
    set_counters(state, bytes * count);
}

void BM_AtomicLockCopyVar(benchmark::State& state) {
    const int count = static_cast<int>(state.range(1));
    std::size_t bytes = static_cast<std::size_t>(state.range(0)) * sizeof(float);
    Buffers b(bytes);
    alignas(64) AtomicLock l;
    for (auto _ : state) {
        benchmark::DoNotOptimize(bytes);
        l.lock();
        for (int k = 0; k < count; ++k)
            chimera::svar::detail::copy_var(reinterpret_cast<std::byte*>(b.d(k)),
                                            reinterpret_cast<const std::byte*>(b.s(k)), bytes);
        l.unlock();
        benchmark::DoNotOptimize(b.dst.data());
        benchmark::ClobberMemory();
    }
    set_counters(state, bytes * count);
}

void BM_PthreadMutexMemcpy(benchmark::State& state) {
    const int count = static_cast<int>(state.range(1));
    std::size_t bytes = static_cast<std::size_t>(state.range(0)) * sizeof(float);
    Buffers b(bytes);
    pthread_mutex_t m = PTHREAD_MUTEX_INITIALIZER;
    for (auto _ : state) {
        benchmark::DoNotOptimize(bytes);
        pthread_mutex_lock(&m);
        for (int k = 0; k < count; ++k) std::memcpy(b.d(k), b.s(k), bytes);
        pthread_mutex_unlock(&m);
        benchmark::DoNotOptimize(b.dst.data());
        benchmark::ClobberMemory();
    }
    set_counters(state, bytes * count);
}

// --- the table lock ------------------------------------------------------------

void BM_TableLockUnlock(benchmark::State& state) {
    chimera::ipc::LockWord& lock = setup().table.lock_word();
    const chimera::ipc::LockOptions options = setup().table.lock_options();
    for (auto _ : state) {
        if (chimera::ipc::lock(lock, options) != chimera::ipc::LockStatus::acquired) {
            state.SkipWithError("table lock not acquired");
            break;
        }
        benchmark::ClobberMemory();
        if (!chimera::ipc::unlock(lock)) [[unlikely]] {
            state.SkipWithError("table lock lost");
            break;
        }
    }
}

// --- SVAR transfers (Table 3) ------------------------------------------------------

// `count` single-variable reads: one lock acquisition per variable.
void BM_SvarRead(benchmark::State& state) {
    Setup& s = setup();
    const std::size_t si = size_index(state.range(0));
    const int count = static_cast<int>(state.range(1));
    LocalTable& lt = *s.local;
    for (auto _ : state) {
        Status st = Status::ok;
        for (int k = 0; k < count; ++k) {
            const Status r = lt.read(s.vars[si][k]);
            if (r != Status::ok) st = r;
        }
        benchmark::DoNotOptimize(s.vars[si][0]);
        benchmark::ClobberMemory();
        if (st != Status::ok) {
            check(st, state);
            break;
        }
    }
    set_counters(state, static_cast<std::size_t>(state.range(0)) * sizeof(float) * count);
}

void BM_SvarWrite(benchmark::State& state) {
    Setup& s = setup();
    const std::size_t si = size_index(state.range(0));
    const int count = static_cast<int>(state.range(1));
    LocalTable& lt = *s.local;
    for (auto _ : state) {
        Status st = Status::ok;
        for (int k = 0; k < count; ++k) {
            s.vars[si][k][0] += 1.0f;  // a new value every time
            const Status r = lt.write(s.vars[si][k]);
            if (r != Status::ok) st = r;
        }
        benchmark::ClobberMemory();
        if (st != Status::ok) {
            check(st, state);
            break;
        }
    }
    set_counters(state, static_cast<std::size_t>(state.range(0)) * sizeof(float) * count);
}

// One multi-variable transfer of `count` variables: one lock acquisition.
void BM_SvarCopyFrom(benchmark::State& state) {
    Setup& s = setup();
    const std::size_t si = size_index(state.range(0));
    const int count = static_cast<int>(state.range(1));
    LocalTable& lt = *s.local;
    const VarSet& set = s.sets[si][count];
    for (auto _ : state) {
        const Status st = lt.copy_from_global(set);
        benchmark::DoNotOptimize(s.vars[si][0]);
        benchmark::ClobberMemory();
        if (st != Status::ok) {
            check(st, state);
            break;
        }
    }
    set_counters(state, static_cast<std::size_t>(state.range(0)) * sizeof(float) * count);
}

void BM_SvarCopyTo(benchmark::State& state) {
    Setup& s = setup();
    const std::size_t si = size_index(state.range(0));
    const int count = static_cast<int>(state.range(1));
    LocalTable& lt = *s.local;
    const VarSet& set = s.sets[si][count];
    for (auto _ : state) {
        for (int k = 0; k < count; ++k) s.vars[si][k][0] += 1.0f;
        const Status st = lt.copy_to_global(set);
        benchmark::ClobberMemory();
        if (st != Status::ok) {
            check(st, state);
            break;
        }
    }
    set_counters(state, static_cast<std::size_t>(state.range(0)) * sizeof(float) * count);
}

// --- TBUF (§5.6) ---------------------------------------------------------------------

// One item written and read back through a triple buffer in shared memory
// (both roles in this thread: the cost of the operations, not of a cache line
// moving between cores). Range 0 is the item size in bytes; range 1 is 1 when
// the writer supplies its own time-stamp (no clock read).
void BM_TbufWriteRead(benchmark::State& state) {
    const auto bytes = static_cast<std::size_t>(state.range(0));
    const bool stamped = state.range(1) != 0;
    const std::string name =
        chimera::ipc::segment_name("bench" + std::to_string(getpid()), "tbuf" + std::to_string(bytes));
    chimera::tbuf::Tbuf tb = chimera::tbuf::Tbuf::create(name, bytes);
    Buffers b(bytes);
    std::int64_t stamp = 0;
    for (auto _ : state) {
        const std::uint64_t counter = stamped ? tb.write(b.s(0), ++stamp) : tb.write(b.s(0));
        if (counter == chimera::tbuf::kCorrupt) [[unlikely]] {
            state.SkipWithError("tbuf write refused");
            break;
        }
        const chimera::tbuf::ReadResult r = tb.read(b.d(0));
        benchmark::DoNotOptimize(r);
        benchmark::DoNotOptimize(b.dst.data());
        benchmark::ClobberMemory();
    }
    tb.destroy();
    set_counters(state, bytes);
}

// What the default tbuf write() adds: one read of CLOCK_MONOTONIC (vDSO).
void BM_MonotonicClock(benchmark::State& state) {
    for (auto _ : state) benchmark::DoNotOptimize(chimera::ipc::now_ns());
}

// The same item through a buffer guarded by a pthread mutex: lock, copy in,
// unlock (writer); lock, copy out, unlock (reader).
void BM_PthreadMutexWriteRead(benchmark::State& state) {
    std::size_t bytes = static_cast<std::size_t>(state.range(0));
    Buffers shared(bytes), b(bytes);
    pthread_mutex_t m = PTHREAD_MUTEX_INITIALIZER;
    for (auto _ : state) {
        benchmark::DoNotOptimize(bytes);
        pthread_mutex_lock(&m);
        std::memcpy(shared.d(0), b.s(0), bytes);
        pthread_mutex_unlock(&m);
        pthread_mutex_lock(&m);
        std::memcpy(b.d(0), shared.d(0), bytes);
        pthread_mutex_unlock(&m);
        benchmark::DoNotOptimize(b.dst.data());
        benchmark::ClobberMemory();
    }
    set_counters(state, bytes);
}

// Like for like with TBUF's default write(): the writer also time-stamps the
// item (one CLOCK_MONOTONIC read), and the stamp travels with it.
void BM_PthreadMutexWriteReadStamped(benchmark::State& state) {
    std::size_t bytes = static_cast<std::size_t>(state.range(0));
    Buffers shared(bytes), b(bytes);
    pthread_mutex_t m = PTHREAD_MUTEX_INITIALIZER;
    std::int64_t shared_stamp = 0, stamp = 0;
    for (auto _ : state) {
        benchmark::DoNotOptimize(bytes);
        const std::int64_t now = chimera::ipc::now_ns();
        pthread_mutex_lock(&m);
        std::memcpy(shared.d(0), b.s(0), bytes);
        shared_stamp = now;
        pthread_mutex_unlock(&m);
        pthread_mutex_lock(&m);
        std::memcpy(b.d(0), shared.d(0), bytes);
        stamp = shared_stamp;
        pthread_mutex_unlock(&m);
        benchmark::DoNotOptimize(stamp);
        benchmark::DoNotOptimize(b.dst.data());
        benchmark::ClobberMemory();
    }
    set_counters(state, bytes);
}

void transfer_args(benchmark::internal::Benchmark* b) {
    b->ArgNames({"nelem", "count"});
    for (int count : {1, 2, 6})
        for (int nelem : kNelems) b->Args({nelem, count});
}

void tbuf_args(benchmark::internal::Benchmark* b) {
    b->ArgNames({"bytes", "stamped"});
    for (int bytes : {24, 128, 144, 1024})
        for (int stamped : {0, 1}) b->Args({bytes, stamped});
}

void mutex_write_read_args(benchmark::internal::Benchmark* b) {
    b->ArgNames({"bytes"});
    for (int bytes : {24, 128, 144, 1024}) b->Args({bytes});
}

}  // namespace

BENCHMARK(BM_AtomicLockUnlock);
BENCHMARK(BM_TableLockUnlock);
BENCHMARK(BM_Memcpy)->Apply(transfer_args);
BENCHMARK(BM_AtomicLockMemcpy)->Apply(transfer_args);
BENCHMARK(BM_AtomicLockCopyVar)->Apply(transfer_args);
BENCHMARK(BM_PthreadMutexMemcpy)->Apply(transfer_args);
BENCHMARK(BM_SvarRead)->Apply(transfer_args);
BENCHMARK(BM_SvarWrite)->Apply(transfer_args);
BENCHMARK(BM_SvarCopyFrom)->Apply(transfer_args);
BENCHMARK(BM_SvarCopyTo)->Apply(transfer_args);
BENCHMARK(BM_TbufWriteRead)->Apply(tbuf_args);
BENCHMARK(BM_MonotonicClock);
BENCHMARK(BM_PthreadMutexWriteRead)->Apply(mutex_write_read_args);
BENCHMARK(BM_PthreadMutexWriteReadStamped)->Apply(mutex_write_read_args);

int main(int argc, char** argv) {
    benchmark::Initialize(&argc, argv);
    if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
    setup();  // create the table before the first measurement
    benchmark::RunSpecifiedBenchmarks();
    benchmark::Shutdown();
    return 0;
}
