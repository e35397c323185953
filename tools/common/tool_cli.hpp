// tools/common/tool_cli.hpp — what the command line of every Chimera program
// has in common: --help, --version (the project's version), and the exit
// status: 0 done, 1 a runtime failure, 2 a usage error (an unknown option, a
// missing or malformed argument). CLI11's own codes (105, 106, 109, ...) are
// not for shell scripts to learn.
#pragma once

#include <CLI/CLI.hpp>

#include <string>

#ifndef CHIMERA_VERSION
#error "CHIMERA_VERSION must be defined by the build (meson.project_version())"
#endif

namespace chimera::tools {

inline constexpr int kUsageError = 2;

/// Adds --version, printing "NAME (Chimera) VERSION".
inline void add_version(CLI::App& app, const std::string& name) {
    app.set_version_flag("--version", name + " (Chimera) " CHIMERA_VERSION, "print the version and exit");
}

/// Parses the command line. Returns -1 when the program should go on, else the
/// exit status: 0 after --help or --version (printed), 2 after a usage error
/// (said on stderr with a pointer to --help).
inline int parse(CLI::App& app, int argc, char** argv) {
    try {
        app.parse(argc, argv);
        return -1;
    } catch (const CLI::CallForHelp& e) {
        return app.exit(e);
    } catch (const CLI::CallForAllHelp& e) {
        return app.exit(e);
    } catch (const CLI::CallForVersion& e) {
        return app.exit(e);
    } catch (const CLI::ParseError& e) {
        app.exit(e);
        return kUsageError;
    }
}

}  // namespace chimera::tools
