// fig6_10.hpp — where the Figure 6.10 subsystem (its master program and tests) finds its files: the
// fig6_10.sbs of this folder, the .rmod files and the module shared objects of the
// build tree (see examples/common/example_files.hpp); and the simulated trackball
// on its serial line (SimulatedTrackball).
#pragma once

#include "example_files.hpp"

#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <regex>
#include <sstream>
#include <string>
#include <string_view>
#include <thread>
#include <utility>
#include <vector>

extern char** environ;

#ifndef FIG6_10_RMOD_PATH
#error "FIG6_10_RMOD_PATH (colon-separated .rmod folders) must be defined by the build"
#endif
#ifndef FIG6_10_MODULE_PATH
#error "FIG6_10_MODULE_PATH (colon-separated module folders) must be defined by the build"
#endif
#ifndef FIG6_10_FEED
#error "FIG6_10_FEED (the teleop_feed program) must be defined by the build"
#endif
#ifndef FIG6_10_TRACKBALL
#error "FIG6_10_TRACKBALL (the trackball_sim program) must be defined by the build"
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

/// The trackball_sim program built beside the master program.
inline std::string trackball_program() { return FIG6_10_TRACKBALL; }

/// A trackball_sim process on a pseudo-terminal of its own, and the files jtball
/// needs to read it: in a fresh folder `dir`, the IOD database trackball.iod
/// (device named as its folder, class SIO, driver termios, PATH the line's link) and a copy
/// of jtball.rmod reading it, with LOCAL lines replaced by key (`local`). The
/// process sends idle packets until start(), then runs the phases given
/// (trackball_sim's PHASE arguments); the constructor returns once the line is
/// there. Everything is removed at the end.
class SimulatedTrackball {
public:
    SimulatedTrackball(std::filesystem::path dir, const std::vector<std::string>& phases,
                       const std::vector<std::pair<std::string, std::string>>& local = {},
                       const std::vector<std::string>& options = {})
        : dir_(std::move(dir)) {
        std::filesystem::remove_all(dir_);
        std::filesystem::create_directories(dir_);
        const auto link = dir_ / "tball";
        // Device names are machine-wide (their port locks are): this line's is
        // its folder's, so two runs at once each have their own.
        const std::string device = dir_.filename().string();
        std::ofstream(dir_ / "trackball.iod") << "# The simulated trackball's serial line (trackball_sim).\n"
                                                 "DEVICE " << device << " SIO termios\n  PATH "
                                              << link.string() << "\n  BAUD 9600\nEND\nEOF\n";
        std::ifstream in(rmod("jtball"));
        std::stringstream text;
        text << in.rdbuf();
        std::string r = std::regex_replace(text.str(), std::regex("\nDEVICE +[^\n]*"), "\nDEVICE    " + device);
        for (const auto& [key, value] : local)
            r = std::regex_replace(r, std::regex("\n" + key + " +[^\n]*"), "\n" + key + " " + value);
        std::ofstream(dir_ / "jtball.rmod") << r;

        std::vector<std::string> args{trackball_program(), link.string(), "--wait-start"};
        args.insert(args.end(), options.begin(), options.end());
        args.insert(args.end(), phases.begin(), phases.end());
        std::vector<char*> argv;
        for (auto& a : args) argv.push_back(a.data());
        argv.push_back(nullptr);
        // Its "ready LINK" line is for a person at a terminal; here the link is
        // waited for below, and the owner's stdout stays its own (bench_modules
        // prints JSON there). Its warnings still go to stderr.
        posix_spawn_file_actions_t quiet;
        ::posix_spawn_file_actions_init(&quiet);
        ::posix_spawn_file_actions_addopen(&quiet, STDOUT_FILENO, "/dev/null", O_WRONLY, 0);
        const int rc = ::posix_spawn(&pid_, argv[0], &quiet, nullptr, argv.data(), environ);
        ::posix_spawn_file_actions_destroy(&quiet);
        if (rc != 0) throw chimera::sbs::Error("starting " + args[0] + ": " + std::strerror(rc));
        for (int i = 0; i < 500 && !std::filesystem::is_symlink(link); ++i)
            std::this_thread::sleep_for(std::chrono::milliseconds(10));
        if (!std::filesystem::is_symlink(link)) {
            stop();
            throw chimera::sbs::Error(args[0] + " did not create its line " + link.string() + " within 5 s");
        }
    }
    SimulatedTrackball(const SimulatedTrackball&) = delete;
    SimulatedTrackball& operator=(const SimulatedTrackball&) = delete;
    ~SimulatedTrackball() {
        stop();
        std::error_code ec;
        std::filesystem::remove_all(dir_, ec);
    }

    /// The operator starts the phases.
    void start() const {
        if (::kill(pid_, SIGUSR1) != 0) throw chimera::sbs::Error("signalling trackball_sim: " + std::string(std::strerror(errno)));
    }
    /// The jtball.rmod that reads this trackball.
    std::string rmod_path() const { return (dir_ / "jtball.rmod").string(); }
    pid_t pid() const noexcept { return pid_; }
    /// Exit status once the phases are done (-1 while it runs; `block`: wait).
    int exit_status(bool block) {
        if (pid_ > 0 && status_ < 0) {
            int st = 0;
            if (::waitpid(pid_, &st, block ? 0 : WNOHANG) == pid_)
                status_ = WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
        }
        return status_;
    }

private:
    void stop() {
        if (pid_ > 0 && exit_status(false) < 0) {
            ::kill(pid_, SIGTERM);
            exit_status(true);
        }
    }

    std::filesystem::path dir_;
    pid_t pid_ = -1;
    int status_ = -1;
};

}  // namespace fig6_10
