#pragma once

#include <unistd.h>

#include <cstdlib>
#include <fstream>
#include <string>

#include "process.hpp"

namespace svar_test {

inline std::string data_file(const std::string& name) {
    const char* root = std::getenv("CHIMERA_SOURCE_ROOT");
    return std::string(root ? root : "..") + "/tests/svar/data/" + name;
}

inline std::string unique_name(const std::string& what) {
    return "/chimera.svartest" + std::to_string(getpid()) + "." + what;
}

/// Writes `text` to a temporary file and returns its path.
inline std::string temp_file(const std::string& stem, const std::string& text) {
    const std::string path = "/tmp/" + stem + "." + std::to_string(getpid()) + ".svar";
    std::ofstream(path) << text;
    return path;
}

using chimera::test::fork_child;
using chimera::test::shared_anon;
using chimera::test::wait_child;
using chimera::test::wait_for;

}  // namespace svar_test
