// Helpers for the multi-process ipc tests.
#pragma once

#include <unistd.h>

#include <atomic>
#include <string>

#include "process.hpp"

namespace chimera::ipc::test {

/// A unique segment name for this process and test.
inline std::string unique_name(const std::string& what) {
    return "/chimera.test" + std::to_string(getpid()) + "." + what;
}

using chimera::test::fork_child;
using chimera::test::shared_anon;
using chimera::test::wait_child;
using chimera::test::wait_for;

}  // namespace chimera::ipc::test
