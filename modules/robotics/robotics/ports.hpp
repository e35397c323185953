// robotics/ports.hpp — what every robotics module does in init: translate its
// ports with size checks, read NDOF/DH in-consts into a robot model, and read
// per-joint LOCAL values. Errors are std::invalid_argument whose message names
// the rmod (and the LOCAL line), thrown from init only — never from a cycle.
#pragma once

#include <chimera/module.hpp>
#include <chimera/svar.hpp>

#include <algorithm>
#include <cstdint>
#include <span>
#include <stdexcept>
#include <string>
#include <string_view>

#include <Eigen/Core>

#include "robotics/model.hpp"

namespace chimera::robotics {

[[noreturn]] inline void module_error(const Task& t, const std::string& message) {
    throw std::invalid_argument(std::string(t.rmod()) + ".rmod: " + message);
}

/// What set() answers after `apply` took new LOCAL values: a bad one (`apply`
/// throws std::invalid_argument) is warned and answered ERROR, and `apply`
/// must then leave the values the module runs with as they were.
template <typename Apply>
Result apply_local(Task& t, Apply&& apply) {
    try {
        apply();
    } catch (const std::invalid_argument& e) {
        t.warning(e.what());
        return Result::ERROR;
    }
    return Result::OK;
}

inline bool listed(const std::vector<std::string>& list, std::string_view port) {
    return std::find(list.begin(), list.end(), port) != list.end();
}
inline bool has_in_var(const Task& t, std::string_view port) {
    return listed(t.rmod_file().in_vars, port);
}
inline bool has_out_var(const Task& t, std::string_view port) {
    return listed(t.rmod_file().out_vars, port);
}
inline bool has_in_const(const Task& t, std::string_view port) {
    return listed(t.rmod_file().in_consts, port);
}

/// Number of elements of the global variable behind a port.
inline std::size_t port_nelem(const Task& t, std::string_view port) {
    return t.local_table().global().var(t.global_name(port)).nelem();
}

/// A double vector port of exactly `n` elements.
inline double* vec_port(Task& t, std::string_view port, std::size_t n) {
    const std::string global = t.global_name(port);
    const std::size_t have = port_nelem(t, port);
    if (have != n) {
        module_error(t, "port " + std::string(port) + " (" + global + ") has " +
                            std::to_string(have) + " elements, expected " + std::to_string(n));
    }
    return t.translate<double>(port);
}

/// The NDOF in-const (an int), checked.
inline std::size_t read_ndof(Task& t) {
    const std::int32_t* p = t.translate<std::int32_t>("NDOF");
    if (*p < 1 || *p > 64) {
        module_error(t, "in-const NDOF is " + std::to_string(*p) +
                            " (no robot interface produced it, or it is out of range 1..64)");
    }
    return static_cast<std::size_t>(*p);
}

/// The robot model from the NDOF and DH in-consts (thesis §3.5): a DH whose
/// size does not match NDOF is refused, naming both.
inline RobotModel read_model(Task& t) {
    const std::size_t n = read_ndof(t);
    const std::size_t nelem = port_nelem(t, "DH");
    const double* dh = t.translate<double>("DH");
    try {
        return RobotModel::unpack_dh(std::span<const double>(dh, nelem), static_cast<long>(n),
                                     "in-const " + t.global_name("DH"));
    } catch (const std::invalid_argument& e) {
        module_error(t, e.what());
    }
}

// --- LOCAL values ----------------------------------------------------------------
// The LocalConfig versions serve programs that read a .rmod without a task (the
// CAN drive simulator reads its robot's); their errors name the .rmod file.

[[noreturn]] inline void config_error(const LocalConfig& lc, const std::string& message) {
    throw std::invalid_argument(lc.file + ": " + message);
}

/// A LOCAL key with one value (applied to every joint) or exactly n values.
inline Eigen::VectorXd local_vector(const LocalConfig& lc, std::string_view key, std::size_t n) {
    const std::vector<double> v = lc.numbers(key);  // throws naming file, line and key
    Eigen::VectorXd out(static_cast<Eigen::Index>(n));
    if (v.size() == 1) {
        out.setConstant(v[0]);
    } else if (v.size() == n) {
        for (std::size_t i = 0; i < n; ++i) out[static_cast<Eigen::Index>(i)] = v[i];
    } else {
        const LocalConfig::Entry* e = lc.find(key);
        config_error(lc, "line " + std::to_string(e ? e->line : 0) + ": LOCAL " + std::string(key) +
                             " has " + std::to_string(v.size()) + " values, expected 1 or " +
                             std::to_string(n));
    }
    return out;
}

/// Like local_vector, with a default when the key is absent.
inline Eigen::VectorXd local_vector(const LocalConfig& lc, std::string_view key, std::size_t n,
                                    double fallback) {
    if (!lc.has(key)) return Eigen::VectorXd::Constant(static_cast<Eigen::Index>(n), fallback);
    return local_vector(lc, key, n);
}

/// A LOCAL word (first token), or `fallback` when absent.
inline std::string local_word(const LocalConfig& lc, std::string_view key, std::string fallback) {
    const LocalConfig::Entry* e = lc.find(key);
    if (!e || e->values.empty()) return fallback;
    return e->values.front();
}

/// The robot of `ROBOT puma560 | planar2 | urdf FILE ROOT-LINK TIP-LINK`
/// (default puma560).
inline RobotModel robot_from_local(const LocalConfig& lc) {
    const std::string robot = local_word(lc, "ROBOT", "puma560");
    if (robot == "puma560") return puma560();
    if (robot == "planar2") return planar2();
    if (robot == "urdf") {
        const LocalConfig::Entry* e = lc.find("ROBOT");
        if (e->values.size() != 4)
            config_error(lc, "line " + std::to_string(e->line) + ": ROBOT urdf takes FILE ROOT-LINK TIP-LINK");
        try {
            return RobotModel::from_urdf(e->values[1], e->values[2], e->values[3]);
        } catch (const std::exception& ex) {
            config_error(lc, ex.what());
        }
    }
    config_error(lc, "LOCAL ROBOT '" + robot + "': expected puma560, planar2 or urdf");
}

// The task versions: errors name the rmod as module_error does.
template <typename F>
auto with_rmod_errors(const Task& t, F&& f) -> decltype(f()) {
    try {
        return f();
    } catch (const std::invalid_argument& e) {
        std::string m = e.what();
        const std::string& file = t.local().file;
        if (!file.empty() && m.rfind(file + ": ", 0) == 0) m.erase(0, file.size() + 2);
        module_error(t, m);
    }
}

inline Eigen::VectorXd local_vector(const Task& t, std::string_view key, std::size_t n) {
    return with_rmod_errors(t, [&] { return local_vector(t.local(), key, n); });
}
inline Eigen::VectorXd local_vector(const Task& t, std::string_view key, std::size_t n,
                                    double fallback) {
    return with_rmod_errors(t, [&] { return local_vector(t.local(), key, n, fallback); });
}
inline std::string local_word(const Task& t, std::string_view key, std::string fallback) {
    return local_word(t.local(), key, std::move(fallback));
}
inline RobotModel robot_from_local(const Task& t) {
    return with_rmod_errors(t, [&] { return robot_from_local(t.local()); });
}

/// A LOCAL single number with a default, errors naming the rmod.
inline double local_number(const Task& t, std::string_view key, double fallback) {
    return with_rmod_errors(t, [&] { return t.local().number(key, fallback); });
}

using VecMap = Eigen::Map<Eigen::VectorXd>;

}  // namespace chimera::robotics
