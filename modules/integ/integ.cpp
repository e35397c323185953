// integ — time integrator of any vector variable (thesis Figure 3.16: the
// damped-least-squares controller's joint velocities into joint positions).
// Generic ports configured with SVARALIAS:
//
//   [INCONST NDOF]   when given, Z^ and Z must have NDOF elements
//   INVAR   Z^       rate (units/s)
//   OUTVAR  Z        z_k = z_{k-1} + z^ / freq, optionally clamped to [MIN, MAX]
//   LOCAL   [MIN v...] [MAX v...]  (1 or n values each)
//
// On `on` it starts from the current global value of Z (the out-var is read
// before `on`, §3.5), so taking over Z from another module makes no jump.
#include <chimera/module.hpp>

#include "robotics/ports.hpp"

namespace rb = chimera::robotics;

namespace {

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kIntegLocalKeys[] = {
    {"MIN", chimera::LocalType::numbers, -chimera::unbounded, chimera::unbounded, false, "lower clamp per joint", "-1e300"},
    {"MAX", chimera::LocalType::numbers, -chimera::unbounded, chimera::unbounded, false, "upper clamp per joint", "1e300"},
};

class Integ : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kIntegLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        n_ = rb::has_in_const(t, "NDOF") ? rb::read_ndof(t) : rb::port_nelem(t, "Z");
        zdot_ = rb::vec_port(t, "Z^", n_);
        z_ = rb::vec_port(t, "Z", n_);
        lo_ = rb::local_vector(t, "MIN", n_, -1e300);
        hi_ = rb::local_vector(t, "MAX", n_, 1e300);
        if ((lo_.array() > hi_.array()).any()) rb::module_error(t, "LOCAL MIN exceeds MAX");
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        const auto n = static_cast<Eigen::Index>(n_);
        Eigen::Map<Eigen::VectorXd> z(z_, n);
        z = (z + t.period() * Eigen::Map<const Eigen::VectorXd>(zdot_, n)).cwiseMax(lo_).cwiseMin(hi_);
        return chimera::Result::OK;
    }

private:
    std::size_t n_ = 0;
    const double* zdot_ = nullptr;
    double* z_ = nullptr;
    Eigen::VectorXd lo_, hi_;
};

}  // namespace

CHIMERA_MODULE(integ, Integ)
