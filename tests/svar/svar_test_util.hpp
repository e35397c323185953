#pragma once

#include <sys/mman.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <fstream>
#include <string>
#include <thread>

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

template <typename T>
T* shared_anon() {
    void* p = mmap(nullptr, sizeof(T), PROT_READ | PROT_WRITE, MAP_SHARED | MAP_ANONYMOUS, -1, 0);
    if (p == MAP_FAILED) std::abort();
    return new (p) T{};
}

template <typename F>
pid_t fork_child(F&& body) {
    const pid_t pid = fork();
    if (pid == 0) {
        int rc = 1;
        try {
            rc = body();
        } catch (...) {
            rc = 99;
        }
        _exit(rc);
    }
    return pid;
}

inline int wait_child(pid_t pid) {
    int status = 0;
    if (waitpid(pid, &status, 0) != pid) return -1;
    if (WIFEXITED(status)) return WEXITSTATUS(status);
    if (WIFSIGNALED(status)) return 128 + WTERMSIG(status);
    return -1;
}

template <typename F>
bool wait_for(F&& cond, int ms = 5000) {
    const auto end = std::chrono::steady_clock::now() + std::chrono::milliseconds(ms);
    while (!cond()) {
        if (std::chrono::steady_clock::now() > end) return false;
        std::this_thread::sleep_for(std::chrono::microseconds(100));
    }
    return true;
}

}  // namespace svar_test
