// The `sbs` prompt under a pseudo-terminal, as an operator uses it: the
// `SBS <subsystem><<rmod>>` prompt following the last RMOD addressed (§4.4.1),
// a command, an error line that leaves the prompt alive, completion with TAB,
// Ctrl-C, history, quit.
#include "sbs_harness.hpp"

#include <gtest/gtest.h>

#include <pty.h>
#include <termios.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <optional>
#include <thread>

#include <filesystem>
#include <fstream>
#include <iterator>

using sbs_test::read_until;
using sbs_test::Workspace;

namespace {

class Terminal {
public:
    explicit Terminal(const std::vector<std::string>& argv) {
        winsize ws{};
        ws.ws_row = 40;
        ws.ws_col = 200;
        pid_ = ::forkpty(&fd_, nullptr, nullptr, &ws);
        if (pid_ == 0) {
            std::vector<char*> a;
            for (const auto& s : argv) a.push_back(const_cast<char*>(s.c_str()));
            a.push_back(nullptr);
            ::execv(a[0], a.data());
            ::_exit(127);
        }
    }
    ~Terminal() {
        if (pid_ > 0 && !exited_) {
            ::kill(pid_, SIGKILL);
            sbs_test::wait_child(pid_, 5000);
        }
        if (fd_ >= 0) ::close(fd_);
    }
    void type(const std::string& keys) { sbs_test::type_at_prompt(fd_, keys); }
    /// Waits for `pattern` in the output after what expect() consumed last.
    bool expect(const std::string& pattern, int timeout_ms = 10000) {
        const bool ok = read_until(fd_, seen_, pattern, timeout_ms);
        if (ok) {
            const auto at = seen_.find(pattern);
            last_ = seen_.substr(0, at + pattern.size());
            seen_.erase(0, at + pattern.size());
        } else {
            last_ = seen_;
        }
        return ok;
    }
    /// The program's state and the terminal's mode, for a failure message.
    std::string describe() const {
        std::string out = " [pid " + std::to_string(pid_);
        std::ifstream st("/proc/" + std::to_string(pid_) + "/stat");
        std::string line;
        std::getline(st, line);
        out += " stat: " + line.substr(0, 60);
        std::ifstream wc("/proc/" + std::to_string(pid_) + "/wchan");
        std::getline(wc, line);
        out += " wchan: " + line;
        termios tio{};
        if (::tcgetattr(fd_, &tio) == 0)
            out += std::string(" icanon ") + ((tio.c_lflag & ICANON) ? "1" : "0") + " echo " +
                   ((tio.c_lflag & ECHO) ? "1" : "0") + " isig " + ((tio.c_lflag & ISIG) ? "1" : "0");
        return out + "]";
    }
    /// Everything read up to and including the last pattern found.
    const std::string& last() const { return last_; }
    /// Exit status if the program ended within `ms`, else nullopt (still running).
    std::optional<int> exited_within(int ms) {
        std::string rest;
        const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(ms);
        while (std::chrono::steady_clock::now() < deadline) {
            read_until(fd_, rest, "\x01never\x01", 50);  // keep the terminal drained
            int st = 0;
            if (::waitpid(pid_, &st, WNOHANG) == pid_) {
                exited_ = true;
                return WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
            }
        }
        return std::nullopt;
    }
    int wait_exit() {
        exited_ = true;
        // Drain the terminal so the program is never blocked writing to it.
        std::string rest;
        read_until(fd_, rest, "\x01never\x01", 500);
        return sbs_test::wait_child(pid_, 15000);
    }

private:
    int fd_ = -1;
    pid_t pid_ = -1;
    bool exited_ = false;
    std::string seen_, last_;
};

}  // namespace

TEST(SbsPty, PromptCommandErrorCompletionQuit) {
    Workspace ws;
    Terminal t([&] {
        auto a = ws.sbs_args({});
        a.insert(a.begin(), sbs_test::env("SBS_EXE"));
        return a;
    }());
    const std::string name = ws.subsystem();
    ASSERT_TRUE(t.expect("SBS " + name + "<> ")) << t.last();

    t.type("spawn ramp\r");
    ASSERT_TRUE(t.expect("SBS " + name + "<ramp> ")) << t.last();
    EXPECT_NE(t.last().find("spawned ramp"), std::string::npos) << t.last();

    // An error is one line and the prompt survives it, default RMOD unchanged.
    t.type("on nosuch\r");
    ASSERT_TRUE(t.expect("SBS " + name + "<ramp> ")) << t.last();
    EXPECT_NE(t.last().find("error: no task nosuch in subsystem " + name + " (tasks: ramp)"), std::string::npos)
        << t.last();

    // TAB completes the command and then the RMOD.
    t.type("o\tn\t r\t\r");
    ASSERT_TRUE(t.expect("ramp: ON")) << t.last();
    ASSERT_TRUE(t.expect("SBS " + name + "<ramp> "));
    t.type("stat\t fo");  // nothing matches "fo": the line stays as typed
    t.type("\x15");       // Ctrl-U clears it
    t.type("status set rm\t st\t\r");
    ASSERT_TRUE(t.expect("status fields: rmod state")) << t.last();
    ASSERT_TRUE(t.expect("SBS " + name + "<ramp> "));

    // The prompt follows the RMOD the last command was directed to.
    t.type("spawn follow\r");
    ASSERT_TRUE(t.expect("SBS " + name + "<follow> ")) << t.last();
    t.type("status ramp\r");
    ASSERT_TRUE(t.expect("SBS " + name + "<ramp> ")) << t.last();
    EXPECT_NE(t.last().find("ON"), std::string::npos) << t.last();

    // TAB after `show ` offers graph too (issue #35.5).
    t.type("show gr\t\r");
    ASSERT_TRUE(t.expect("X -> Y")) << t.last();  // follow's line of the graph
    ASSERT_TRUE(t.expect("SBS " + name + "<ramp> "));

    // Ctrl-C gives a fresh prompt; it does not end the program.
    t.type("displ");
    t.type("\x03");
    ASSERT_TRUE(t.expect("SBS " + name + "<ramp> ")) << t.last();
    t.type("display\r");
    ASSERT_TRUE(t.expect(" m")) << t.last();  // X with its units
    ASSERT_TRUE(t.expect("SBS " + name + "<ramp> "));

    t.type("quit\r");
    EXPECT_EQ(t.wait_exit(), 0);
    // The subsystem is gone, and the commands went to the history file.
    EXPECT_FALSE(std::filesystem::exists("/dev/shm/chimera." + name + ".svar"));
    std::ifstream hist(ws.dir() + "/.chimera_sbs_history");
    const std::string h((std::istreambuf_iterator<char>(hist)), {});
    // libedit writes blanks as \040 in its history format.
    EXPECT_TRUE(h.find("spawn ramp") != std::string::npos || h.find("spawn\\040ramp") != std::string::npos) << h;
}

TEST(SbsPty, EndOfInputFinishes) {
    Workspace ws;
    Terminal t([&] {
        auto a = ws.sbs_args({});
        a.insert(a.begin(), sbs_test::env("SBS_EXE"));
        return a;
    }());
    ASSERT_TRUE(t.expect("SBS " + ws.subsystem() + "<> "));
    t.type("spawn ramp\ron\r");
    ASSERT_TRUE(t.expect("ramp: ON"));
    ASSERT_TRUE(t.expect("SBS " + ws.subsystem() + "<ramp> "));
    // Ctrl-D on an empty line. The prompt can show before libedit has put the
    // terminal in raw mode, and a ^D typed in that instant is lost to the
    // line discipline: type it again until the program ends (at most 5 times).
    std::optional<int> status;
    for (int i = 0; i < 5 && !status; ++i) {
        t.type("\x04");
        status = t.exited_within(2000);
    }
    ASSERT_TRUE(status.has_value()) << "Ctrl-D did not end the prompt";
    EXPECT_EQ(*status, 0);
    EXPECT_FALSE(std::filesystem::exists("/dev/shm/chimera." + ws.subsystem() + ".svar"));
}

// Issue #16.5: `sbs X.sbs` attached to a running master edits lines as the
// master's prompt does — TAB completion (asked of the master), history (up
// arrow, and the history file), Ctrl-C dropping the line.
TEST(SbsPty, AttachedPromptEditsCompletesAndRemembers) {
    Workspace ws;
    Terminal master([&] {
        auto a = ws.sbs_args({"--serve", "-c", "spawn ramp"});
        a.insert(a.begin(), sbs_test::env("SBS_EXE"));
        return a;
    }());
    ASSERT_TRUE(sbs_test::wait_for_file(ws.socket_path()));
    const std::string name = ws.subsystem();
    {
        Terminal t([&] {
            auto a = ws.sbs_args({});
            a.insert(a.begin(), sbs_test::env("SBS_EXE"));
            return a;
        }());
        ASSERT_TRUE(t.expect("SBS " + name + "<> ")) << t.last();
        // TAB completes the command, then the master's live task.
        t.type("o\tn\t r\t\r");
        ASSERT_TRUE(t.expect("ramp: ON")) << t.last();
        ASSERT_TRUE(t.expect("SBS " + name + "<ramp> ")) << t.last();
        // Up arrow brings back "on ramp": sent again, the master refuses it.
        t.type("\x1b[A\r");
        ASSERT_TRUE(t.expect("already ON")) << t.last();
        ASSERT_TRUE(t.expect("SBS " + name + "<ramp> ")) << t.last();
        // Ctrl-C drops a half-typed line and the prompt stays.
        t.type("displ");
        t.type("\x03");
        ASSERT_TRUE(t.expect("SBS " + name + "<")) << t.last() << t.describe();
        t.type("show sv\t\r");
        ASSERT_TRUE(t.expect("(.svar INIT)")) << t.last();  // LIMITS: no producer
        ASSERT_TRUE(t.expect("SBS " + name + "<"));
        t.type("quit\r");
        EXPECT_EQ(t.wait_exit(), 0);
    }
    std::ifstream hist(ws.dir() + "/.chimera_sbs_history");
    const std::string h((std::istreambuf_iterator<char>(hist)), {});
    EXPECT_TRUE(h.find("show svar") != std::string::npos || h.find("show\\040svar") != std::string::npos) << h;
    const auto fin = ws.sbs_run({"-c", "finish"});
    EXPECT_EQ(fin.status, 0) << fin.err;
    EXPECT_EQ(master.wait_exit(), 0);
}
