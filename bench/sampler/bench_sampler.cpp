// What a sample costs the sampling task's cycle, against its peer measured in
// the same run: the one-lock copy of the same variables that any task's
// in-var transfer is (svar::LocalTable::copy_from_global).
//
//   SvarCopyFrom     the sampled variables global -> local, one lock (the peer)
//   SamplerSample    Sampler::sample(): that copy, the elements converted to
//                    double, one ring entry published
//   RingPublish      the ring entry alone (stamps and the values)
//
// Argument: the number of double[6] variables sampled (6 channels each).
#include <benchmark/benchmark.h>
#include <unistd.h>

#include <string>
#include <vector>

#include "chimera/ipc/clock.hpp"
#include "chimera/sampler.hpp"

namespace {

using namespace chimera;

std::string svar_text(int vars) {
    std::string s;
    for (int v = 0; v < vars; ++v)
        s += "NAME V" + std::to_string(v) + "\nTYPE double\nDESC d\nUNITS u\nNELEM 6\n";
    return s + "EOF\n";
}

struct Fixture {
    explicit Fixture(int vars)
        : table(svar::Table::create("/chimera.bsamp" + std::to_string(getpid()) + ".svar",
                                    svar::parse_svar_string(svar_text(vars), "bench.svar"))) {
        for (int v = 0; v < vars; ++v) names.push_back("V" + std::to_string(v));
    }
    ~Fixture() { (void)table.destroy(); }
    svar::Table table;
    std::vector<std::string> names;
};

void BM_SvarCopyFrom(benchmark::State& state) {
    Fixture f(static_cast<int>(state.range(0)));
    svar::LocalTable local(f.table, f.names);
    const svar::VarSet set = local.make_set(f.names);
    for (auto _ : state) benchmark::DoNotOptimize(local.copy_from_global(set));
}

void BM_SamplerSample(benchmark::State& state) {
    Fixture f(static_cast<int>(state.range(0)));
    sampler::Sampler s(f.table, sampler::parse_channels(f.table, f.names),
                       "/chimera.bsamp" + std::to_string(getpid()) + ".ring", 4096, 1000.0);
    std::uint64_t cycle = 0;
    const std::int64_t t = ipc::now_ns();
    for (auto _ : state) benchmark::DoNotOptimize(s.sample(t, cycle++));
}

void BM_RingPublish(benchmark::State& state) {
    const std::size_t channels = 6 * static_cast<std::size_t>(state.range(0));
    std::vector<sampler::Channel> c;
    for (std::size_t i = 0; i < channels; ++i) c.push_back({"V", i, "V[" + std::to_string(i) + "]"});
    std::vector<std::uint32_t> ix(channels, 0);
    sampler::RingWriter w = sampler::RingWriter::create("/chimera.bsamp" + std::to_string(getpid()) + ".ring2", c,
                                                        ix, 4096, 1000.0);
    std::vector<double> row(channels, 1.5);
    std::uint64_t cycle = 0;
    for (auto _ : state) w.publish_row(0, cycle++, row.data());
}

BENCHMARK(BM_SvarCopyFrom)->Arg(1)->Arg(2)->Arg(6);
BENCHMARK(BM_SamplerSample)->Arg(1)->Arg(2)->Arg(6);
BENCHMARK(BM_RingPublish)->Arg(1)->Arg(2)->Arg(6);

}  // namespace

BENCHMARK_MAIN();
