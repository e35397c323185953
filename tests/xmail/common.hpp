// Helpers shared by the xmail tests.
#pragma once

#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <string>
#include <vector>

#include "sanitizer.hpp"

extern char** environ;

/// A system name unique to this process and test, so parallel runs never meet.
inline std::string test_sys(const std::string& what) {
    return "xt" + std::to_string(getpid()) + what;
}

/// fork + exec of the helper binary with `args`; stdout goes to `out_fd` if
/// >= 0, stdin comes from `in_fd` if >= 0.
inline pid_t spawn_helper(const std::vector<std::string>& args, int out_fd = -1, int in_fd = -1) {
    chimera::test::detail::another_process_under_tsan();  // posix_spawn runs no fork handler
    std::vector<std::string> all{XM_HELPER};
    all.insert(all.end(), args.begin(), args.end());
    std::vector<char*> argv;
    for (auto& a : all) argv.push_back(a.data());
    argv.push_back(nullptr);
    posix_spawn_file_actions_t fa;
    posix_spawn_file_actions_init(&fa);
    if (out_fd >= 0) posix_spawn_file_actions_adddup2(&fa, out_fd, 1);
    if (in_fd >= 0) posix_spawn_file_actions_adddup2(&fa, in_fd, 0);
    pid_t pid = -1;
    if (posix_spawn(&pid, XM_HELPER, &fa, nullptr, argv.data(), environ) != 0) pid = -1;
    posix_spawn_file_actions_destroy(&fa);
    return pid;
}

/// Runs the helper to completion and returns (exit status, stdout).
inline std::pair<int, std::string> run_helper(const std::vector<std::string>& args) {
    int p[2];
    if (pipe2(p, O_CLOEXEC) != 0) return {-1, ""};
    const pid_t pid = spawn_helper(args, p[1]);
    close(p[1]);
    std::string out;
    char buf[512];
    ssize_t n;
    while ((n = read(p[0], buf, sizeof buf)) > 0) out.append(buf, static_cast<std::size_t>(n));
    close(p[0]);
    int status = 0;
    waitpid(pid, &status, 0);
    return {WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status), out};
}

/// A helper process whose stdout is read line by line; killed and reaped on
/// destruction. With `with_stdin`, close_stdin() is its signal to finish.
struct Child {
    pid_t pid = -1;
    int fd = -1;
    int in = -1;
    std::string buffered;
    explicit Child(const std::vector<std::string>& args, bool with_stdin = false) {
        int p[2], q[2] = {-1, -1};
        if (pipe2(p, O_CLOEXEC) != 0 || (with_stdin && pipe2(q, O_CLOEXEC) != 0)) return;
        pid = spawn_helper(args, p[1], q[0]);
        close(p[1]);
        if (q[0] >= 0) close(q[0]);
        fd = p[0];
        in = q[1];
    }
    std::string line() {
        for (;;) {
            const auto nl = buffered.find('\n');
            if (nl != std::string::npos) {
                std::string l = buffered.substr(0, nl);
                buffered.erase(0, nl + 1);
                return l;
            }
            char buf[256];
            const ssize_t n = read(fd, buf, sizeof buf);
            if (n <= 0) return "<eof>";
            buffered.append(buf, static_cast<std::size_t>(n));
        }
    }
    void close_stdin() {
        if (in >= 0) close(in);
        in = -1;
    }
    int wait() {
        int st = 0;
        waitpid(pid, &st, 0);
        pid = -1;
        return WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
    }
    ~Child() {
        if (pid > 0) {
            kill(pid, SIGKILL);
            waitpid(pid, nullptr, 0);
        }
        if (fd >= 0) close(fd);
        close_stdin();
    }
};
