// example_files.hpp — finding an example subsystem's files, shared by every
// example's master program and tests. Each example's meson.build passes two
// colon-separated folder lists as defines: its .rmod folders (the example's own
// folder first, then the module folders that ship the .rmod files) and the
// build tree's module folders, so nothing has to be set by the user.
#pragma once

#include <chimera/sbs.hpp>

#include <sched.h>

#include <filesystem>
#include <string>
#include <string_view>
#include <vector>

namespace chimera_examples {

/// "a:b::c" -> {"a", "b", "c"}.
inline std::vector<std::string> split_path(std::string_view path) {
    std::vector<std::string> out;
    while (!path.empty()) {
        const auto colon = path.find(':');
        const std::string_view part = path.substr(0, colon);
        if (!part.empty()) out.emplace_back(part);
        if (colon == std::string_view::npos) break;
        path.remove_prefix(colon + 1);
    }
    return out;
}

/// The path of `<name>.rmod` in the first folder of `rmod_path` that has it.
/// Throws sbs::Error naming every folder searched when there is none.
inline std::string find_rmod(std::string_view rmod_path, std::string_view name) {
    std::string searched;
    for (const auto& dir : split_path(rmod_path)) {
        const auto p = std::filesystem::path(dir) / (std::string(name) + ".rmod");
        if (std::filesystem::exists(p)) return p.string();
        searched += (searched.empty() ? "" : ", ") + dir;
    }
    throw chimera::sbs::Error(std::string(name) + ".rmod not found in " + searched);
}

/// Reads an example's .sbs. An RTPU whose CPU this process may not use (a
/// one-CPU machine, a container's cpuset) is moved onto an allowed CPU, so the
/// example runs anywhere; `notes` receives one line per move. `subsystem`, when
/// given, replaces the SUBSYSTEM name (tests run side by side under unique names).
inline chimera::SbsFile load_sbs(const std::string& sbs_path, std::vector<std::string>* notes,
                                 std::string subsystem) {
    chimera::SbsFile file = chimera::read_sbs(sbs_path);
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

/// Adds the folders of `module_path` to a subsystem's module path.
inline void add_module_dirs(chimera::sbs::Subsystem& sbs, std::string_view module_path) {
    for (const auto& d : split_path(module_path)) sbs.add_module_path(d);
}

}  // namespace chimera_examples
