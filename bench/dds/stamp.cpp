// stamp — the bench's producer: writes its out-var every cycle with element 0
// the CLOCK_MONOTONIC time of the write (ns, exact in a double for 104 days of
// uptime) and the other elements a joint-like ramp. The bridge that publishes
// it runs as the next object of the same combined task (§3.8.1), so the
// bench's latency starts at this write.
#include <chimera/ipc/clock.hpp>
#include <chimera/module.hpp>

#include <cstddef>

namespace {

class Stamp : public chimera::Module {
public:
    chimera::Result init(chimera::Task& t) override {
        out_ = t.translate<double>(t.rmod_file().out_vars.at(0));
        n_ = t.local_table().global().var(t.global_name(t.rmod_file().out_vars.at(0))).nelem();
        return chimera::Result::OK;
    }
    chimera::Result cycle(chimera::Task& t) override {
        for (std::size_t j = 1; j < n_; ++j) out_[j] = 1e-3 * static_cast<double>(t.cycle_count() % 1000) * static_cast<double>(j);
        out_[0] = static_cast<double>(chimera::ipc::now_ns());
        return chimera::Result::OK;
    }

private:
    double* out_ = nullptr;
    std::size_t n_ = 0;
};

}  // namespace

CHIMERA_MODULE(stamp, Stamp)
