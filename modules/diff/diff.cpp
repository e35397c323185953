// diff — differentiator over time of any vector variable (thesis §3.8, Figure
// 3.12: qmdiff.rmod / qrdiff.rmod). Generic ports configured with SVARALIAS:
//
//   [INCONST NDOF]   when given, Z and Z^ must have NDOF elements
//   INVAR   Z        any double vector
//   OUTVAR  Z^       its time derivative, (z_k - z_{k-1}) * freq, optionally low-pass filtered
//   LOCAL   [FILTER a]  first-order filter: z^ = a * z^_prev + (1 - a) * raw, 0 <= a < 1 (default 0)
#include <chimera/module.hpp>

#include "robotics/ports.hpp"

namespace rb = chimera::robotics;

namespace {

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kDiffLocalKeys[] = {
    {"FILTER", chimera::LocalType::number, 0.0, 1.0, false, "low-pass factor of the derivative (0: none)", "0"},
};

class Diff : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kDiffLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        n_ = rb::has_in_const(t, "NDOF") ? rb::read_ndof(t) : rb::port_nelem(t, "Z");
        z_ = rb::vec_port(t, "Z", n_);
        zdot_ = rb::vec_port(t, "Z^", n_);
        filter_ = rb::local_number(t, "FILTER", 0.0);
        if (!(filter_ >= 0 && filter_ < 1)) rb::module_error(t, "LOCAL FILTER must be in [0, 1)");
        last_.setZero(static_cast<Eigen::Index>(n_));
        return chimera::Result::OK;
    }

    chimera::Result on(chimera::Task&) override {
        // Start from the present value, so the first derivative is not a jump
        // from zero; Z^ keeps the value read on `on` until the first cycle.
        last_ = Eigen::Map<const Eigen::VectorXd>(z_, static_cast<Eigen::Index>(n_));
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task& t) override {
        const auto n = static_cast<Eigen::Index>(n_);
        const Eigen::Map<const Eigen::VectorXd> z(z_, n);
        Eigen::Map<Eigen::VectorXd> zdot(zdot_, n);
        const double f = 1.0 / t.period();
        zdot = filter_ * zdot + (1.0 - filter_) * f * (z - last_);
        last_ = z;
        return chimera::Result::OK;
    }

private:
    std::size_t n_ = 0;
    const double* z_ = nullptr;
    double* zdot_ = nullptr;
    double filter_ = 0;
    Eigen::VectorXd last_;
};

}  // namespace

CHIMERA_MODULE(diff, Diff)
