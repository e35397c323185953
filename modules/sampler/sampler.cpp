// sampler — the real-time side of the scope and of `record` (include/chimera/
// sampler.hpp): at its own rate (FREQ) it reads chosen elements of chosen
// state variables, one consistent set under one table lock, and publishes
// them with a time-stamp and its cycle count into a shared-memory ring that
// any number of readers follow (the web console's scope, `sbs … record`,
// Python's chimera.record()).
//
// A task like any other, so its RTPU's scheduler analyses, profiles and
// budgets it; the other tasks' code paths do not change when one is added.
// It lists no INVAR: an observer is not a consumer, so sampling a variable
// never changes what §3.3.1 verification says about a configuration.
//
//   LOCAL  CHANNELS VAR|VAR[i]|VAR[i:j]...   what to sample (one column per element)
//          [RING name]       the ring's object name: segment /chimera.<subsystem>.<name>
//                            (default sample.<rmod>)
//          [CAPACITY n]      entries in the ring (rounded up to a power of two;
//                            default: 10 s at FREQ, at least 1024)
//
// The ring is made at spawn and removed at kill; between off and on it keeps
// its numbering, so a reader sees the pause only in the time-stamps.
#include <chimera/ipc/clock.hpp>
#include <chimera/module.hpp>
#include <chimera/sampler.hpp>

#include <sys/stat.h>

#include <memory>
#include <stdexcept>
#include <string>

namespace {

constexpr chimera::LocalKey kSamplerLocalKeys[] = {
    {"CHANNELS", chimera::LocalType::text, -chimera::unbounded, chimera::unbounded, false,
     "variables or elements sampled: VAR, VAR[i], VAR[i:j]", ""},
    {"RING", chimera::LocalType::word, -chimera::unbounded, chimera::unbounded, false,
     "object name of the ring segment (/chimera.SUBSYSTEM.NAME)", "sample.RMOD"},
    {"CAPACITY", chimera::LocalType::integer, 2.0, static_cast<double>(chimera::sampler::kMaxCapacity), false,
     "entries in the ring (default: 10 s at FREQ, at least 1024)", ""},
};

// "/chimera.arm.svar" → "arm": the table's segment names the subsystem.
std::string subsystem_of(const std::string& table_segment) {
    const std::string head = "/chimera.", tail = ".svar";
    if (table_segment.size() > head.size() + tail.size() && table_segment.compare(0, head.size(), head) == 0)
        return table_segment.substr(head.size(), table_segment.size() - head.size() - tail.size());
    return table_segment;
}

// Whoever may watch the table (docs/permissions.md: the group, 0640) may watch its samples.
chimera::ipc::CreateOptions same_mode_as(const std::string& table_segment) {
    chimera::ipc::CreateOptions o;
    struct stat st {};
    if (::stat(("/dev/shm" + table_segment).c_str(), &st) == 0) o.mode = st.st_mode & 0777;
    return o;
}

class SamplerModule : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kSamplerLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        const auto words = t.local().find("CHANNELS");
        if (!words || words->values.empty())
            throw std::invalid_argument(std::string(t.rmod()) + ": LOCAL CHANNELS (the variables to sample) is required");
        chimera::svar::Table& table = t.local_table().global();
        const auto ring = t.local().text("RING").value_or("sample." + std::string(t.rmod()));
        const double hz = t.freq() > 0 ? t.freq() : 1.0;
        std::size_t capacity = chimera::sampler::capacity_for(hz, 10.0);
        if (t.local().has("CAPACITY")) {
            const auto want = static_cast<std::size_t>(t.local().number("CAPACITY", 0));
            capacity = 2;
            while (capacity < want && capacity < chimera::sampler::kMaxCapacity) capacity *= 2;
        }
        auto channels = chimera::sampler::parse_channels(table, words->values);  // throws naming the word
        sampler_ = std::make_unique<chimera::sampler::Sampler>(
            table, std::move(channels), chimera::ipc::segment_name(subsystem_of(table.name()), ring), capacity, hz,
            same_mode_as(table.name()));
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        // Not taken (lock timeout): no sample this cycle; readers see the gap
        // in the cycle numbers, not a stale value.
        (void)sampler_->sample(chimera::ipc::now_ns(), t.cycle_count());
        return chimera::Result::OK;
    }

    chimera::Result kill(chimera::Task&) override {
        sampler_.reset();  // readers see the ring closed
        return chimera::Result::OK;
    }

private:
    std::unique_ptr<chimera::sampler::Sampler> sampler_;
};

}  // namespace

CHIMERA_MODULE(sampler, SamplerModule)
