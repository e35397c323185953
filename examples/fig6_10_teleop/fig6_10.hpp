// fig6_10.hpp — where the Figure 6.10 subsystem's files are, for its master
// program and tests: the .sbs of this folder, the .rmod files (this folder
// first, then the module folders that ship them), the module shared objects
// and the teleop_feed program of the build tree. meson passes the folders as
// defines, so nothing has to be set by the user.
#pragma once

#include <chimera/sbs.hpp>

#include <sched.h>

#include <filesystem>
#include <string>
#include <string_view>
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

inline std::vector<std::string> split_path(std::string_view path) {
    std::vector<std::string> out;
    while (!path.empty()) {
        const auto colon = path.find(':');
        if (colon != 0) out.emplace_back(path.substr(0, colon));
        if (colon == std::string_view::npos) break;
        path.remove_prefix(colon + 1);
    }
    return out;
}

/// The teleop_feed program built beside the master program.
inline std::string feed_program() { return FIG6_10_FEED; }

/// This example's folder (the first .rmod folder).
inline std::string example_dir() { return split_path(FIG6_10_RMOD_PATH).front(); }

/// The path of `<name>.rmod`: this example's folder first, then the modules'.
inline std::string rmod(std::string_view name) {
    std::string searched;
    for (const auto& dir : split_path(FIG6_10_RMOD_PATH)) {
        const auto p = std::filesystem::path(dir) / (std::string(name) + ".rmod");
        if (std::filesystem::exists(p)) return p.string();
        searched += (searched.empty() ? "" : ", ") + dir;
    }
    throw chimera::sbs::Error(std::string(name) + ".rmod not found in " + searched);
}

/// Reads fig6_10.sbs. An RTPU whose CPU this process may not use is moved onto
/// an allowed CPU (`notes` gets one line per move); `subsystem`, when given,
/// replaces the SUBSYSTEM name (tests run side by side under unique names).
inline chimera::SbsFile load_sbs(std::vector<std::string>* notes = nullptr, std::string subsystem = {}) {
    chimera::SbsFile file = chimera::read_sbs(example_dir() + "/fig6_10.sbs");
    if (!subsystem.empty()) file.subsystem = std::move(subsystem);
    cpu_set_t allowed;
    CPU_ZERO(&allowed);
    if (sched_getaffinity(0, sizeof(allowed), &allowed) != 0) return file;
    std::vector<int> cpus;
    for (int c = 0; c < CPU_SETSIZE; ++c)
        if (CPU_ISSET(c, &allowed)) cpus.push_back(c);
    if (cpus.empty()) return file;
    for (std::size_t i = 0; i < file.rtpus.size(); ++i) {
        auto& r = file.rtpus[i];
        if (r.cpu >= 0 && r.cpu < CPU_SETSIZE && CPU_ISSET(r.cpu, &allowed)) continue;
        const int to = cpus[i % cpus.size()];
        if (notes)
            notes->push_back("RTPU " + r.name + ": CPU " + std::to_string(r.cpu) +
                             " is not available to this process, using CPU " + std::to_string(to));
        r.cpu = to;
    }
    return file;
}

/// Adds the build tree's module folders to a subsystem's module path.
inline void add_module_dirs(chimera::sbs::Subsystem& sbs) {
    for (const auto& d : split_path(FIG6_10_MODULE_PATH)) sbs.add_module_path(d);
}

}  // namespace fig6_10
