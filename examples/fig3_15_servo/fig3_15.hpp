// fig3_15.hpp — where the Figures 3.15/3.16 subsystem (its master program and tests) finds its files: the
// fig3_15.sbs of this folder, the .rmod files and the module shared objects of the
// build tree (see examples/common/example_files.hpp).
#pragma once

#include "example_files.hpp"

#include <string>
#include <string_view>
#include <utility>
#include <vector>

#ifndef FIG3_15_RMOD_PATH
#error "FIG3_15_RMOD_PATH (colon-separated .rmod folders) must be defined by the build"
#endif
#ifndef FIG3_15_MODULE_PATH
#error "FIG3_15_MODULE_PATH (colon-separated module folders) must be defined by the build"
#endif

namespace fig3_15 {

/// This example's folder (the first .rmod folder).
inline std::string example_dir() { return chimera_examples::split_path(FIG3_15_RMOD_PATH).front(); }

/// The path of `<name>.rmod`: this example's folder first, then the modules'.
inline std::string rmod(std::string_view name) { return chimera_examples::find_rmod(FIG3_15_RMOD_PATH, name); }

/// Reads fig3_15.sbs, moving RTPUs onto CPUs this process may use (see load_sbs).
inline chimera::SbsFile load_sbs(std::vector<std::string>* notes = nullptr, std::string subsystem = {}) {
    return chimera_examples::load_sbs(example_dir() + "/fig3_15.sbs", notes, std::move(subsystem));
}

/// Adds the build tree's module folders to a subsystem's module path.
inline void add_module_dirs(chimera::sbs::Subsystem& sbs) { chimera_examples::add_module_dirs(sbs, FIG3_15_MODULE_PATH); }

}  // namespace fig3_15
