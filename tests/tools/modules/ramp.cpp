// The test module of the sbs command-line tests: one output that ramps (no
// input) or follows its input times a gain. LOCAL keys, read at every call so
// `set` changes them while the task runs:
//   STEP v     added to the output each cycle when there is no input (default 1)
//   GAIN v     output = GAIN * input when there is an input (default 2)
//   FAIL 1     cycle raises an error (the task goes to ERROR)
//   INITFAIL 1 init fails (spawn reports it, the task is not created)
//   WARN text  on() records this warning
#include <chimera/module.hpp>

#include <string>

namespace {

using chimera::Result;
using chimera::Task;

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kRampLocalKeys[] = {
    {"STEP", chimera::LocalType::number, -1000000.0, 1000000.0, true, "increment per cycle without an input", "1"},
    {"GAIN", chimera::LocalType::number, -1000000.0, 1000000.0, true, "output = GAIN * input", "2"},
    {"WARN", chimera::LocalType::text, -chimera::unbounded, chimera::unbounded, true, "a warning raised in on()", ""},
    {"INITFAIL", chimera::LocalType::number, -chimera::unbounded, chimera::unbounded, false, "non-zero: init fails", "0"},
    {"FAIL", chimera::LocalType::number, -chimera::unbounded, chimera::unbounded, true, "non-zero: the cycle fails", "0"},
};

class Ramp : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kRampLocalKeys; }

    Result init(Task& t) override {
        const auto& f = t.rmod_file();
        if (!f.in_vars.empty()) in_ = t.translate<double>(f.in_vars[0]);
        if (!f.out_vars.empty()) out_ = t.translate<double>(f.out_vars[0]);
        if (t.local().number("INITFAIL", 0.0) != 0.0) {
            return t.error(chimera::err::code::user + 2, "INITFAIL is set");
        }
        return Result::OK;
    }
    Result on(Task& t) override {
        if (const auto w = t.local().text("WARN")) t.warning(*w);
        return Result::OK;
    }
    Result cycle(Task& t) override {
        if (t.local().number("FAIL", 0.0) != 0.0) {
            return t.error(chimera::err::code::user + 1, "FAIL is set");
        }
        if (out_ == nullptr) return Result::OK;
        if (in_ != nullptr) *out_ = t.local().number("GAIN", 2.0) * *in_;
        else *out_ += t.local().number("STEP", 1.0);
        return Result::OK;
    }

private:
    double* in_ = nullptr;
    double* out_ = nullptr;
};

}  // namespace

CHIMERA_MODULE(ramp, Ramp)
