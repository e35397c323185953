// join — join connector (thesis §3.3, Figure 3.6): two or more modules producing
// the same output have it renamed (SVARALIAS) to intermediate variables p', p''
// ...; the join connector combines them into the single output p by a weighted
// average.
//
//   [INCONST NDOF]         when given, every port must have NDOF elements
//   INVAR   Z1 Z2 [Z3 ... Z8]   the conflicting outputs (as many as listed)
//   OUTVAR  Z              sum_i w_i Z_i / sum_i w_i
//   LOCAL   [WEIGHTS w1 w2 ...]  one per input, >= 0, not all 0 (default equal)
#include <chimera/module.hpp>

#include <array>
#include <string>

#include "robotics/ports.hpp"

namespace rb = chimera::robotics;

namespace {

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kJoinLocalKeys[] = {
    {"WEIGHTS", chimera::LocalType::numbers, -chimera::unbounded, chimera::unbounded, false, "weight of each input", "1"},
};

class Join : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kJoinLocalKeys; }

    static constexpr std::size_t max_inputs = 8;

    chimera::Result init(chimera::Task& t) override {
        for (const std::string& port : t.rmod_file().in_vars) {
            if (port == "NDOF") continue;
            if (port.size() < 2 || port[0] != 'Z' || port.size() > 2 || port[1] < '1' ||
                port[1] > '8') {
                rb::module_error(t, "join's in-vars are Z1 .. Z8, found " + port);
            }
            ++k_;
        }
        if (k_ < 2) rb::module_error(t, "a join connector needs at least two inputs (Z1 Z2)");
        n_ = rb::has_in_const(t, "NDOF") ? rb::read_ndof(t) : rb::port_nelem(t, "Z");
        for (std::size_t i = 0; i < k_; ++i) {
            const std::string port = "Z" + std::to_string(i + 1);
            if (!rb::has_in_var(t, port)) rb::module_error(t, "in-vars must be Z1 .. Z" + std::to_string(k_) + "; " + port + " is missing");
            in_[i] = rb::vec_port(t, port, n_);
        }
        out_ = rb::vec_port(t, "Z", n_);
        const Eigen::VectorXd w = rb::local_vector(t, "WEIGHTS", k_, 1.0);
        if ((w.array() < 0).any() || w.sum() <= 0) {
            rb::module_error(t, "LOCAL WEIGHTS must be >= 0 and not all zero");
        }
        for (std::size_t i = 0; i < k_; ++i) w_[i] = w[static_cast<Eigen::Index>(i)] / w.sum();
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task&) override {
        const auto n = static_cast<Eigen::Index>(n_);
        Eigen::Map<Eigen::VectorXd> z(out_, n);
        z.setZero();
        for (std::size_t i = 0; i < k_; ++i) z += w_[i] * Eigen::Map<const Eigen::VectorXd>(in_[i], n);
        return chimera::Result::OK;
    }

private:
    std::size_t k_ = 0, n_ = 0;
    std::array<const double*, max_inputs> in_{};
    std::array<double, max_inputs> w_{};
    double* out_ = nullptr;
};

}  // namespace

CHIMERA_MODULE(join, Join)
