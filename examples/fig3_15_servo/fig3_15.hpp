// fig3_15.hpp — where the Figures 3.15/3.16 subsystem (its master program and tests) finds its files: the
// fig3_15.sbs of this folder, the .rmod files and the module shared objects of the
// build tree (see examples/common/example_files.hpp).
#pragma once

#include "example_files.hpp"

#include <array>
#include <cmath>
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

/// The scene (modules/vision camera.rmod, vservo.rmod): where vservo wants the
/// target's four corners in the image (its DESIRED, pixels) ...
inline constexpr std::array<double, 8> kDesired{220, 140, 420, 140, 420, 340, 220, 340};
/// ... and where the target goes at the swap (the camera's LOCAL TARGET): the
/// 10 cm square 4 cm to the base's +y and 2 cm lower than camera.rmod has it.
inline constexpr const char* kMovedTarget = "0.96 -0.13 0.72  0.96 -0.13 0.62  0.96 -0.03 0.62  0.96 -0.03 0.72";

/// The feature error: RMS over the corners of |image position - desired| (pixels).
inline double feature_error(const double* features) {
    double sum = 0;
    for (std::size_t k = 0; k < kDesired.size(); ++k) sum += (features[k] - kDesired[k]) * (features[k] - kDesired[k]);
    return std::sqrt(sum / (kDesired.size() / 2));
}

}  // namespace fig3_15
