// The `warner` test module: every cycle raises one warning and nothing else
// (no allocation of its own), so a test can count what the runtime does on
// the task thread for a warning. LOCAL THROW_AT N: cycle N throws instead;
// LOCAL FAIL_AT N: cycle N returns ERROR instead.
#include "chimera/module.hpp"

#include <stdexcept>

namespace {

class Warner : public chimera::Module {
public:
    chimera::Result init(chimera::Task& t) override {
        throw_at_ = static_cast<long>(t.local().number("THROW_AT", 0.0));
        fail_at_ = static_cast<long>(t.local().number("FAIL_AT", 0.0));
        return chimera::Result::OK;
    }
    chimera::Result cycle(chimera::Task& t) override {
        if (++n_ == throw_at_) throw std::runtime_error("joint 3 encoder lost");
        if (n_ == fail_at_) return chimera::Result::ERROR;
        t.warning("joint 3 clipped to its limit");
        return chimera::Result::OK;
    }

private:
    long n_ = 0, throw_at_ = 0, fail_at_ = 0;
};

}  // namespace

CHIMERA_MODULE(warner, Warner)
