// fig6_10.hpp — where the Figure 6.10 subsystem (its master program and tests) finds its files: the
// fig6_10.sbs of this folder, the .rmod files and the module shared objects of the
// build tree (see examples/common/example_files.hpp).
#pragma once

#include "example_files.hpp"

#include <string>
#include <string_view>
#include <utility>
#include <vector>

#ifndef FIG6_10_RMOD_PATH
#error "FIG6_10_RMOD_PATH (colon-separated .rmod folders) must be defined by the build"
#endif
#ifndef FIG6_10_MODULE_PATH
#error "FIG6_10_MODULE_PATH (colon-separated module folders) must be defined by the build"
#endif
#ifndef FIG6_10_FEED
#error "FIG6_10_FEED (the teleop_feed program) must be defined by the build"
#endif

namespace fig6_10 {

/// This example's folder (the first .rmod folder).
inline std::string example_dir() { return chimera_examples::split_path(FIG6_10_RMOD_PATH).front(); }

/// The path of `<name>.rmod`: this example's folder first, then the modules'.
inline std::string rmod(std::string_view name) { return chimera_examples::find_rmod(FIG6_10_RMOD_PATH, name); }

/// Reads fig6_10.sbs, moving RTPUs onto CPUs this process may use (see load_sbs).
inline chimera::SbsFile load_sbs(std::vector<std::string>* notes = nullptr, std::string subsystem = {}) {
    return chimera_examples::load_sbs(example_dir() + "/fig6_10.sbs", notes, std::move(subsystem));
}

/// Adds the build tree's module folders to a subsystem's module path.
inline void add_module_dirs(chimera::sbs::Subsystem& sbs) { chimera_examples::add_module_dirs(sbs, FIG6_10_MODULE_PATH); }

/// The teleop_feed program built beside the master program.
inline std::string feed_program() { return FIG6_10_FEED; }

}  // namespace fig6_10
