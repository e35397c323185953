// fig3_13.hpp — where the Figure 3.13 subsystem's tests find its files: the
// fig3_13.sbs of this folder, the .rmod files (this folder, then the modules')
// and the module shared objects of the build tree (examples/common/example_files.hpp).
#pragma once

#include "example_files.hpp"

#include <string>
#include <string_view>
#include <utility>
#include <vector>

#ifndef FIG3_13_RMOD_PATH
#error "FIG3_13_RMOD_PATH (colon-separated .rmod folders) must be defined by the build"
#endif
#ifndef FIG3_13_MODULE_PATH
#error "FIG3_13_MODULE_PATH (colon-separated module folders) must be defined by the build"
#endif

namespace fig3_13 {

/// This example's folder (the first .rmod folder).
inline std::string example_dir() { return chimera_examples::split_path(FIG3_13_RMOD_PATH).front(); }

/// The path of `<name>.rmod`: this example's folder first, then the modules'.
inline std::string rmod(std::string_view name) { return chimera_examples::find_rmod(FIG3_13_RMOD_PATH, name); }

/// Reads `<name>.sbs` of this folder (or a path), moving RTPUs onto CPUs this process may use.
inline chimera::SbsFile load_sbs(const std::string& sbs, std::string subsystem = {}) {
    const std::string path = sbs.find('/') == std::string::npos ? example_dir() + "/" + sbs + ".sbs" : sbs;
    return chimera_examples::load_sbs(path, nullptr, std::move(subsystem));
}

/// Adds the build tree's module folders to a subsystem's module path.
inline void add_module_dirs(chimera::sbs::Subsystem& sbs) { chimera_examples::add_module_dirs(sbs, FIG3_13_MODULE_PATH); }

}  // namespace fig3_13
