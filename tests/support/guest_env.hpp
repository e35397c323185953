// guest_env.hpp — what the test programs of the PREEMPT_RT guest suite
// (tests/rtguest) share: the environment guest-init.sh sets, the rule "skip
// outside the guest, fail inside it when the interface is missing", and the
// gpio-sim attributes that drive and read simulated lines.
#pragma once

#include <gtest/gtest.h>

#include <cstdlib>
#include <fstream>
#include <string>

namespace chimera::test {

/// The variable's value, "" when unset.
inline std::string env(const char* name) {
    const char* v = std::getenv(name);
    return v ? v : "";
}

/// True inside the guest (guest-init.sh sets CHIMERA_RTGUEST=1).
inline bool in_guest() { return env("CHIMERA_RTGUEST") == "1"; }

/// gpio-sim: drives simulated input `line` of a bank (its sysfs folder,
/// /sys/devices/platform/<dev>/<chip>) up or down, as a switch would.
inline void gpiosim_pull(const std::string& bank_dir, int line, bool up) {
    std::ofstream f(bank_dir + "/sim_gpio" + std::to_string(line) + "/pull");
    ASSERT_TRUE(f.good()) << "no gpio-sim attribute for " << bank_dir << " line " << line;
    f << (up ? "pull-up" : "pull-down");
}

/// gpio-sim: the value `line` of a bank shows (what an output drives); -1
/// when it cannot be read.
inline int gpiosim_value(const std::string& bank_dir, int line) {
    std::ifstream f(bank_dir + "/sim_gpio" + std::to_string(line) + "/value");
    int v = -1;
    f >> v;
    return v;
}

}  // namespace chimera::test

/// In a test body: skip when `var` (set by guest-init.sh) is absent outside
/// the guest; fail when it is absent inside it.
#define CHIMERA_REQUIRE_GUEST_ENV(var)                                                    \
    do {                                                                                  \
        if (::chimera::test::env(var).empty()) {                                          \
            if (::chimera::test::in_guest()) FAIL() << var " is not set by guest-init.sh"; \
            GTEST_SKIP() << "runs in the rtguest suite (" var " not set)";                \
        }                                                                                 \
    } while (0)
