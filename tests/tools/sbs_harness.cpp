#include "sbs_harness.hpp"

#include <gtest/gtest.h>

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <termios.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <thread>

namespace sbs_test {

namespace fs = std::filesystem;

std::string env(const char* name) {
    const char* v = std::getenv(name);
    if (v == nullptr || *v == '\0') {
        ADD_FAILURE() << "environment variable " << name << " is not set (run the test through meson)";
        return {};
    }
    return v;
}

namespace {

int decode_status(int st) {
    if (WIFEXITED(st)) return WEXITSTATUS(st);
    if (WIFSIGNALED(st)) return 128 + WTERMSIG(st);
    return -1;
}

}  // namespace

int wait_child(pid_t pid, int timeout_ms) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
    for (;;) {
        int st = 0;
        const pid_t r = ::waitpid(pid, &st, WNOHANG);
        if (r == pid) return decode_status(st);
        if (r < 0) return -1;
        if (std::chrono::steady_clock::now() > deadline) {
            ::kill(pid, SIGKILL);
            ::waitpid(pid, &st, 0);
            return -1;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
}

Outcome run(const std::string& program, const std::vector<std::string>& args, const std::string& input, int timeout_s) {
    int in[2], out[2], err[2];
    if (::pipe2(in, O_CLOEXEC) != 0 || ::pipe2(out, O_CLOEXEC) != 0 || ::pipe2(err, O_CLOEXEC) != 0) {
        ADD_FAILURE() << "pipe: " << std::strerror(errno);
        return {};
    }
    const pid_t pid = ::fork();
    if (pid == 0) {
        ::dup2(in[0], 0);
        ::dup2(out[1], 1);
        ::dup2(err[1], 2);
        std::vector<char*> argv;
        argv.push_back(const_cast<char*>(program.c_str()));
        for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
        argv.push_back(nullptr);
        ::execv(program.c_str(), argv.data());
        std::perror("execv");
        ::_exit(127);
    }
    ::close(in[0]);
    ::close(out[1]);
    ::close(err[1]);
    // Input is small (a few commands): written at once, then closed.
    if (!input.empty()) {
        [[maybe_unused]] const auto n = ::write(in[1], input.data(), input.size());
    }
    ::close(in[1]);
    Outcome r;
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(timeout_s);
    bool out_open = true, err_open = true, timed_out = false;
    while (out_open || err_open) {
        pollfd p[2] = {{out_open ? out[0] : -1, POLLIN, 0}, {err_open ? err[0] : -1, POLLIN, 0}};
        const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
        if (left.count() <= 0) {
            timed_out = true;
            break;
        }
        if (::poll(p, 2, static_cast<int>(left.count())) < 0 && errno != EINTR) break;
        char buf[4096];
        for (int i = 0; i < 2; ++i) {
            if (p[i].revents == 0) continue;
            const ssize_t n = ::read(i == 0 ? out[0] : err[0], buf, sizeof buf);
            if (n <= 0) {
                (i == 0 ? out_open : err_open) = false;
            } else {
                (i == 0 ? r.out : r.err).append(buf, static_cast<std::size_t>(n));
            }
        }
    }
    ::close(out[0]);
    ::close(err[0]);
    if (timed_out) {
        ::kill(pid, SIGKILL);
        ADD_FAILURE() << program << " did not finish within " << timeout_s << " s; output so far:\n" << r.out << r.err;
    }
    r.status = wait_child(pid, timed_out ? 1000 : 20000);
    if (timed_out) r.status = -1;
    return r;
}

std::vector<nlohmann::json> json_lines(const std::string& text) {
    std::vector<nlohmann::json> out;
    std::istringstream in(text);
    std::string line;
    while (std::getline(in, line)) {
        if (line.empty()) continue;
        auto j = nlohmann::json::parse(line, nullptr, false);
        EXPECT_FALSE(j.is_discarded()) << "not JSON: " << line;
        if (!j.is_discarded()) out.push_back(std::move(j));
    }
    return out;
}

Workspace::Workspace() {
    char tmpl[] = "/tmp/sbs_test_XXXXXX";
    dir_ = ::mkdtemp(tmpl);
    static std::atomic<int> counter{0};
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    std::string name = info != nullptr ? info->name() : "t";
    for (auto& c : name)
        if (!std::isalnum(static_cast<unsigned char>(c))) c = '_';
    subsystem_ = "t" + std::to_string(::getpid()) + "_" + std::to_string(counter++) + "_" + name.substr(0, 20);
    sbs_ = write(subsystem_ + ".sbs", "SUBSYSTEM " + subsystem_ + "\nSVARFILE  " + env("SBS_TEST_DATA") +
                                           "/tools.svar\nRTPU      cpu0\nBACKEND   other\nEOF\n");
    fs::create_directories(dir_ + "/run");
    ::chmod((dir_ + "/run").c_str(), 0700);
    ::setenv("XDG_RUNTIME_DIR", (dir_ + "/run").c_str(), 1);
    ::setenv("HOME", dir_.c_str(), 1);
}

Workspace::~Workspace() {
    std::error_code ec;
    fs::remove_all(dir_, ec);
    // Segments of this test's subsystem that a failed run left behind.
    for (const char* object : {"svar", "status"}) fs::remove("/dev/shm/chimera." + subsystem_ + "." + object, ec);
}

std::string Workspace::socket_path() const { return dir_ + "/run/chimera/" + subsystem_ + ".sock"; }

std::string Workspace::write(const std::string& name, const std::string& text) const {
    const std::string path = dir_ + "/" + name;
    std::ofstream(path) << text;
    return path;
}

std::vector<std::string> Workspace::sbs_args(const std::vector<std::string>& args) const {
    std::vector<std::string> a = {sbs_, "--module-path", env("SBS_TEST_DATA")};
    a.insert(a.end(), args.begin(), args.end());
    return a;
}

Outcome Workspace::sbs_run(const std::vector<std::string>& args, const std::string& input, int timeout_s) const {
    return run(env("SBS_EXE"), sbs_args(args), input, timeout_s);
}

bool read_until(int fd, std::string& seen, const std::string& pattern, int timeout_ms) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
    while (seen.find(pattern) == std::string::npos) {
        const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
        if (left.count() <= 0) return false;
        pollfd p{fd, POLLIN, 0};
        const int rc = ::poll(&p, 1, static_cast<int>(left.count()));
        if (rc < 0 && errno == EINTR) continue;
        if (rc <= 0) return false;
        char buf[4096];
        const ssize_t n = ::read(fd, buf, sizeof buf);
        if (n <= 0) return seen.find(pattern) != std::string::npos;
        seen.append(buf, static_cast<std::size_t>(n));
    }
    return true;
}

void type_at_prompt(int fd, const std::string& keys) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(2);
    termios tio{};
    while (::tcgetattr(fd, &tio) == 0 && (tio.c_lflag & ICANON) != 0 && std::chrono::steady_clock::now() < deadline)
        std::this_thread::sleep_for(std::chrono::milliseconds(2));
    [[maybe_unused]] const auto n = ::write(fd, keys.data(), keys.size());
}

bool wait_for_file(const std::string& path, int timeout_ms) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
    while (!fs::exists(path)) {
        if (std::chrono::steady_clock::now() > deadline) return false;
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    return true;
}

}  // namespace sbs_test
