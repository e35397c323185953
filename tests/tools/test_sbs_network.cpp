// A real `sbs` master with its network interface (§4.4.2), talked to by a
// client: the commands over the socket, malformed and oversized requests,
// a peer that disconnects mid-command, exclusive control, TCP with a token,
// passing control from the prompt and back, attaching from a second `sbs`.
#include "client.hpp"
#include "flood.hpp"
#include "chimera/prof.hpp"
#include "sbs_harness.hpp"

#include <gtest/gtest.h>

#include <fcntl.h>
#include <poll.h>
#include <pty.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <optional>
#include <regex>
#include <set>
#include <sstream>
#include <thread>

using chimera::cli::ClientError;
using chimera::cli::NetworkClient;
using sbs_test::Workspace;

namespace {

/// `sbs ... args` in the background, its stderr kept for the messages.
class Master {
public:
    /// `wrapper`: a program and its options that run sbs (strace).
    Master(const Workspace& ws, const std::vector<std::string>& args, const std::vector<std::string>& wrapper = {}) {
        auto a = ws.sbs_args(args);
        a.insert(a.begin(), sbs_test::env("SBS_EXE"));
        a.insert(a.begin(), wrapper.begin(), wrapper.end());
        int err[2];
        EXPECT_EQ(::pipe2(err, O_CLOEXEC), 0);
        pid_ = ::fork();
        if (pid_ == 0) {
            ::setpgid(0, 0);  // the wrapper's children (strace's sbs) are killed with it
            ::dup2(err[1], 2);
            const int null = ::open("/dev/null", O_RDWR);
            ::dup2(null, 0);
            ::dup2(null, 1);
            std::vector<char*> v;
            for (const auto& s : a) v.push_back(const_cast<char*>(s.c_str()));
            v.push_back(nullptr);
            ::execv(v[0], v.data());
            ::_exit(127);
        }
        ::close(err[1]);
        err_ = err[0];
    }
    ~Master() {
        if (pid_ > 0 && !done_) {
            ::kill(-pid_, SIGKILL);
            sbs_test::wait_child(pid_, 5000);
        }
        ::close(err_);
    }
    /// Waits for `pattern` on the master's stderr.
    bool stderr_has(const std::string& pattern, int timeout_ms = 10000) {
        return sbs_test::read_until(err_, err_text_, pattern, timeout_ms);
    }
    const std::string& err_text() const { return err_text_; }
    int wait(int timeout_ms = 20000) {
        done_ = true;
        return sbs_test::wait_child(pid_, timeout_ms);
    }
    pid_t pid() const { return pid_; }

private:
    pid_t pid_ = -1;
    int err_ = -1;
    bool done_ = false;
    std::string err_text_;
};

NetworkClient connect(const Workspace& ws) {
    EXPECT_TRUE(sbs_test::wait_for_file(ws.socket_path())) << ws.socket_path();
    return NetworkClient::connect_unix(ws.socket_path());
}

}  // namespace

// Issue 16.4: a peer's `status` restarts its own window, never another
// reader's (chimtop's "cycle 4132" no longer falls to 1); `status reset` is the
// thesis's reset for everyone. Issue 14.11: the running task's status carries
// its lateness and cycle-time percentiles, in µs.
TEST(SbsNetwork, StatusWindowsPerReaderPercentilesAndTheExplicitReset) {
    Workspace ws;
    Master m(ws, {"--serve", "-c", "spawn ramp; on ramp"});
    auto c = connect(ws);
    ASSERT_TRUE(c.hello().value("ok", false)) << c.hello().dump();
    auto other = chimera::prof::StatusReader::attach(ws.subsystem());  // as chimtop reads
    chimera::prof::StatusWindow others_window;                         // never restarted
    auto chosen = c.request("status set rmod cycle cycP50 cycP99 latP50 latP99", 10000);
    ASSERT_TRUE(chosen["ok"].get<bool>()) << chosen.dump();
    std::this_thread::sleep_for(std::chrono::milliseconds(300));

    auto first = c.request("status", 10000);
    ASSERT_TRUE(first["ok"].get<bool>()) << first.dump();
    EXPECT_EQ(first["data"]["time_unit"], "us");
    const auto& t = first["data"]["tasks"][0];
    ASSERT_GT(t["cycle"].get<std::uint64_t>(), 3u) << t.dump();
    for (const char* f : {"cycP50", "cycP99", "latP50", "latP99"}) ASSERT_TRUE(t[f].is_number()) << f << " " << t.dump();
    EXPECT_GT(t["cycP50"].get<double>(), 0.0);
    EXPECT_LE(t["cycP50"].get<double>(), t["cycP99"].get<double>());
    EXPECT_LE(t["latP50"].get<double>(), t["latP99"].get<double>());
    const std::string text = first["text"];
    EXPECT_NE(text.find("(times in us)"), std::string::npos) << text;
    EXPECT_NE(text.find("cycP99[us]"), std::string::npos) << text;
    EXPECT_NE(text.find("latP50[us]"), std::string::npos) << text;

    const std::uint64_t before = others_window.snapshot(other)[0].cycle;
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    auto second = c.request("status", 10000);
    const std::uint64_t peer = second["data"]["tasks"][0]["cycle"];
    const chimera::prof::TaskStatus seen = others_window.snapshot(other)[0];
    EXPECT_GE(seen.cycle, before) << "another reader's status lowered this reader's counts";
    EXPECT_LT(peer, seen.cycle) << "the peer's window restarted at its first status";
    EXPECT_GE(seen.cycle_time.total(), seen.cycle);

    const std::uint32_t epoch = other.rtpu_epoch(0).epoch;
    auto reset = c.request("status reset", 10000);
    ASSERT_TRUE(reset["ok"].get<bool>()) << reset.dump();
    EXPECT_TRUE(reset["data"]["reset"].get<bool>());
    EXPECT_NE(reset["text"].get<std::string>().find("profiling reset on every RTPU"), std::string::npos);
    EXPECT_GT(other.rtpu_epoch(0).epoch, epoch) << "the explicit reset restarts every reader's counts";
    EXPECT_LT(others_window.snapshot(other)[0].cycle, seen.cycle);
    c.request("finish", 10000);
    EXPECT_EQ(m.wait(), 0) << m.err_text();
}

// Issue #36: a peer that connects as soon as the socket file exists is never
// refused. The file used to appear at bind() and accept only after listen();
// strace holds every listen() half a second, so that window would be
// certain here (python's serve() hit it 1 run in 5 under load).
TEST(SbsNetwork, TheSocketFileAppearsOnlyOnceItAccepts) {
    ASSERT_EQ(::access("/usr/bin/strace", X_OK), 0) << "strace is missing (scripts/setup-debian.sh installs it)";
    Workspace ws;
    // LeakSanitizer cannot run under ptrace: a sanitizer build's sbs keeps
    // its other checks there.
    const char* asan = std::getenv("ASAN_OPTIONS");
    const std::string no_leak_check = "ASAN_OPTIONS=" + std::string(asan ? asan : "") + ":detect_leaks=0";
    Master m(ws, {"--serve", "-c", "spawn ramp"},
             {"/usr/bin/strace", "-f", "-qq", "-o", "/dev/null", "-E", no_leak_check, "-e", "trace=listen", "-e",
              "inject=listen:delay_enter=500000"});
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(20);
    while (::access(ws.socket_path().c_str(), F_OK) != 0) {
        ASSERT_LT(std::chrono::steady_clock::now(), deadline) << ws.socket_path() << " never appeared";
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    auto c = NetworkClient::connect_unix(ws.socket_path());  // throws on a refused connect
    ASSERT_TRUE(c.hello().value("ok", false)) << c.hello().dump();
    EXPECT_TRUE(c.request("finish", 10000)["ok"].get<bool>());
    EXPECT_EQ(m.wait(), 0) << m.err_text();
    const auto staged = std::filesystem::directory_iterator(std::filesystem::path(ws.socket_path()).parent_path());
    for (const auto& f : staged) ADD_FAILURE() << "left behind: " << f.path();
}

TEST(SbsNetwork, CommandsOverTheUnixSocket) {
    Workspace ws;
    Master m(ws, {"--serve", "-c", "spawn ramp"});
    auto c = connect(ws);
    ASSERT_TRUE(c.hello().value("ok", false)) << c.hello().dump();
    EXPECT_EQ(c.hello()["subsystem"], ws.subsystem());
    EXPECT_EQ(c.hello()["protocol"], 1);

    // Owner-only socket in an owner-only folder.
    struct stat st {};
    ASSERT_EQ(::stat(ws.socket_path().c_str(), &st), 0);
    EXPECT_EQ(st.st_mode & 0777, 0600u);

    auto on = c.request("on ramp", 10000);
    EXPECT_TRUE(on["ok"].get<bool>()) << on.dump();
    EXPECT_EQ(on["rmod"], "ramp");
    EXPECT_EQ(on["data"]["state"], "ON");
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    auto status = c.request(R"({"cmd": "status", "id": 7})", 10000);
    EXPECT_EQ(status["id"], 7);
    ASSERT_EQ(status["data"]["tasks"].size(), 1u);
    EXPECT_EQ(status["data"]["tasks"][0]["state"], "ON");
    EXPECT_GT(status["data"]["tasks"][0]["cycle"].get<std::uint64_t>(), 3u);
    auto display = c.request("display", 10000);
    EXPECT_EQ(display["data"]["vars"][0]["name"], "X");

    // Errors are replies; the session goes on.
    auto unknown = c.request("bogus", 10000);
    EXPECT_FALSE(unknown["ok"].get<bool>());
    EXPECT_NE(unknown["error"].get<std::string>().find("unknown command 'bogus'"), std::string::npos);
    auto refused = c.request("on ramp", 10000);
    EXPECT_NE(refused["error"].get<std::string>().find("already ON"), std::string::npos);
    auto malformed = c.request("{\"cmd\": ", 10000);
    EXPECT_EQ(malformed["error"], "malformed JSON request");
    auto no_cmd = c.request(R"({"id": 3})", 10000);
    EXPECT_EQ(no_cmd["id"], 3);
    EXPECT_FALSE(no_cmd["ok"].get<bool>());
    auto two = c.request("status; status", 10000);
    EXPECT_NE(two["error"].get<std::string>().find("one command per request line"), std::string::npos);
    auto quote = c.request("display 'open", 10000);
    EXPECT_NE(quote["error"].get<std::string>().find("unterminated"), std::string::npos);
    auto control = c.request(std::string("status\x01"), 10000);
    EXPECT_NE(control["error"].get<std::string>().find("control characters"), std::string::npos);
    auto big = c.request(std::string(c.hello()["max_request"].get<std::size_t>() + 10, 'x'), 10000);
    EXPECT_NE(big["error"].get<std::string>().find("request longer than"), std::string::npos);
    auto net = c.request("network", 10000);
    EXPECT_NE(net["error"].get<std::string>().find("already has control"), std::string::npos);
    auto after = c.request("status ramp", 10000);
    EXPECT_TRUE(after["ok"].get<bool>()) << after.dump();

    // A second peer is refused while this one has control.
    auto other = NetworkClient::connect_unix(ws.socket_path());
    EXPECT_FALSE(other.hello().value("ok", true));
    EXPECT_NE(other.hello()["error"].get<std::string>().find("another network peer"), std::string::npos);

    // finish: the master turns everything off, removes socket and segments, exits 0.
    auto fin = c.request("finish", 10000);
    EXPECT_TRUE(fin["ok"].get<bool>());
    EXPECT_EQ(m.wait(), 0) << m.err_text();
    EXPECT_FALSE(std::filesystem::exists(ws.socket_path()));
    EXPECT_FALSE(std::filesystem::exists("/dev/shm/chimera." + ws.subsystem() + ".svar"));
}

TEST(SbsNetwork, PeerThatDisconnectsMidCommand) {
    Workspace ws;
    Master m(ws, {"--serve", "-c", "spawn ramp; on ramp"});
    {
        // Half a request, then gone.
        auto c = connect(ws);
        c.send_raw("stat");
    }
    {
        // A whole command whose reply nobody reads: the peer leaves while it runs.
        auto c = connect(ws);
        ASSERT_TRUE(c.hello().value("ok", false)) << c.hello().dump();
        c.send_raw("sleep 0.3\n");
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    {
        // Quit hands control back; the next peer gets it.
        auto c = connect(ws);
        ASSERT_TRUE(c.hello().value("ok", false)) << c.hello().dump();
        EXPECT_TRUE(c.request("quit", 10000)["ok"].get<bool>());
    }
    // The master is unharmed and the task kept running throughout.
    auto c = connect(ws);
    ASSERT_TRUE(c.hello().value("ok", false)) << c.hello().dump();
    auto s = c.request("status ramp", 10000);
    EXPECT_EQ(s["data"]["tasks"][0]["state"], "ON") << s.dump();
    auto d = c.request("display ramp", 10000);
    EXPECT_GT(d["data"]["vars"][0]["values"][0].get<double>(), 10.0);
    c.request("finish", 10000);
    EXPECT_EQ(m.wait(), 0) << m.err_text();
}

TEST(SbsNetwork, TcpNeedsTheToken) {
    Workspace ws;
    Master m(ws, {"--serve", "--tcp", "127.0.0.1:0", "--token", "s3cret"});
    ASSERT_TRUE(m.stderr_has("TCP 127.0.0.1:")) << m.err_text();
    ASSERT_TRUE(m.stderr_has("\n")) << m.err_text();
    EXPECT_EQ(m.err_text().find("unix socket"), std::string::npos) << "TCP only when asked: " << m.err_text();
    const auto at = m.err_text().find("TCP 127.0.0.1:");
    const int port = std::stoi(m.err_text().substr(at + 14));
    ASSERT_GT(port, 0);
    {
        auto c = NetworkClient::connect_tcp("127.0.0.1", static_cast<std::uint16_t>(port));
        EXPECT_EQ(c.hello()["auth"], "token");
        auto r = c.request("status", 10000);
        EXPECT_NE(r["error"].get<std::string>().find("authenticate first"), std::string::npos);
        EXPECT_THROW(c.request("status", 2000), ClientError);  // closed after one try
    }
    {
        auto c = NetworkClient::connect_tcp("127.0.0.1", static_cast<std::uint16_t>(port));
        const auto r = c.request("token wrong", 10000);
        EXPECT_EQ(r["error"], "wrong token");
        // The address now backs off (issue #29.3): a token sooner is not judged.
        std::this_thread::sleep_for(std::chrono::milliseconds(r["data"]["retry_after_ms"].get<long>() + 20));
    }
    auto c = NetworkClient::connect_tcp("127.0.0.1", static_cast<std::uint16_t>(port));
    EXPECT_TRUE(c.request("token s3cret", 10000)["ok"].get<bool>());
    EXPECT_TRUE(c.request("spawn ramp", 10000)["ok"].get<bool>());
    c.request("finish", 10000);
    EXPECT_EQ(m.wait(), 0) << m.err_text();
}

TEST(SbsNetwork, ListenOptionsAreChecked) {
    Workspace ws;
    // TCP needs a token on every address: loopback is open to every local user.
    for (const char* where : {"0.0.0.0:0", "127.0.0.1:0", "localhost:0"}) {
        auto r = ws.sbs_run({"--serve", "--tcp", where});
        EXPECT_EQ(r.status, 2) << where;
        EXPECT_NE(r.err.find("--tcp needs --token"), std::string::npos) << r.err;
    }
    auto r = ws.sbs_run({"--serve", "--tcp", "127.0.0.1:http", "--token", "t"});
    EXPECT_EQ(r.status, 1);
    EXPECT_NE(r.err.find("not a port number"), std::string::npos) << r.err;
    r = ws.sbs_run({"--token", "x", "-c", "status"});
    EXPECT_EQ(r.status, 2);
    EXPECT_FALSE(std::filesystem::exists("/dev/shm/chimera." + ws.subsystem() + ".svar"));
}

TEST(SbsNetwork, TokenFileMustBeTheOwnersAlone) {
    Workspace ws;
    const std::string file = ws.write("token", "s3cret\n");
    ::chmod(file.c_str(), 0644);
    auto r = ws.sbs_run({"--serve", "--tcp", "127.0.0.1:0", "--token-file", file});
    EXPECT_EQ(r.status, 2);
    EXPECT_NE(r.err.find("readable or writable by others"), std::string::npos) << r.err;
    ::chmod(file.c_str(), 0600);
    Master m(ws, {"--serve", "--tcp", "127.0.0.1:0", "--token-file", file});
    ASSERT_TRUE(m.stderr_has("TCP 127.0.0.1:")) << m.err_text();
    ASSERT_TRUE(m.stderr_has("\n")) << m.err_text();
    const int port = std::stoi(m.err_text().substr(m.err_text().find("TCP 127.0.0.1:") + 14));
    auto c = NetworkClient::connect_tcp("127.0.0.1", static_cast<std::uint16_t>(port));
    EXPECT_TRUE(c.request("token s3cret", 10000)["ok"].get<bool>());
    c.request("finish", 10000);
    EXPECT_EQ(m.wait(), 0) << m.err_text();
}

namespace {

// The attacker's folder: probe.rmod beside the probe library under every
// name the loader tries (its constructor runs the moment dlopen() maps it).
// The probe library's bytes, read by the test (root) before the attacker
// forks: the attacker, as nobody, may not be able to read the build tree (a
// clone under /root, mode 0700), and brings its library along anyway.
std::string probe_library() {
    std::ifstream in(sbs_test::env("PROBE_SO"), std::ios::binary);
    return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

std::string plant_probe(const std::string& dir, const std::string& library) {
    for (const char* name : {"/probe.so", "/libprobe.so"})
        std::ofstream(dir + name, std::ios::binary) << library;
    std::ofstream f(dir + "/probe.rmod");
    f << "MODULE probe\nDESC probe\nINVAR none\nOUTVAR none\nTASKTYPE periodic\nFREQ 10\nEOF\n";
    return dir + "/probe.rmod";
}

}  // namespace

// The attack that was possible: an unprivileged local user reaches a root
// master's TCP port and names a .rmod in a folder of its own, beside a
// library whose constructor runs the moment dlopen() maps it.
TEST(SbsNetwork, UnprivilegedUserCannotGetCodeLoadedByTheMaster) {
    if (::geteuid() != 0) GTEST_SKIP() << "needs root: the master must run as root and the attacker as nobody";
    Workspace ws;
    const std::string marker = ws.write("marker-parent-check", "");
    std::filesystem::remove(marker);
    ::setenv("CHIMERA_PROBE_MARKER", marker.c_str(), 1);
    Master m(ws, {"--serve", "--listen", "--tcp", "127.0.0.1:0", "--token", "s3cret"});
    ::unsetenv("CHIMERA_PROBE_MARKER");
    ASSERT_TRUE(m.stderr_has("TCP 127.0.0.1:")) << m.err_text();
    ASSERT_TRUE(m.stderr_has("\n")) << m.err_text();
    const int port = std::stoi(m.err_text().substr(m.err_text().find("TCP 127.0.0.1:") + 14));

    // The attacker, as nobody: its own folder with the probe; then the
    // master, without the token, over TCP and over the owner's Unix socket.
    const std::string probe_bytes = probe_library();
    ASSERT_FALSE(probe_bytes.empty()) << sbs_test::env("PROBE_SO");
    int report[2];
    ASSERT_EQ(::pipe(report), 0);
    const pid_t attacker = ::fork();
    if (attacker == 0) {
        ::close(report[0]);
        std::string out;
        if (::setgid(65534) != 0 || ::setuid(65534) != 0) ::_exit(3);
        char tmpl[] = "/tmp/attacker_XXXXXX";
        if (::mkdtemp(tmpl) == nullptr) ::_exit(4);
        const std::string dir = tmpl;
        out += dir + "\n";
        try {
            const std::string rmod = plant_probe(dir, probe_bytes);
            auto c = NetworkClient::connect_tcp("127.0.0.1", static_cast<std::uint16_t>(port));
            out += c.request("spawn " + rmod, 10000).dump() + "\n";
        } catch (const std::exception& e) {
            out += std::string("tcp: ") + e.what() + "\n";
        }
        try {
            auto c = NetworkClient::connect_unix(ws.socket_path());
            out += "unix: " + c.hello().dump() + "\n";
        } catch (const std::exception& e) {
            out += std::string("unix: ") + e.what() + "\n";
        }
        [[maybe_unused]] auto n = ::write(report[1], out.data(), out.size());
        ::_exit(0);
    }
    ::close(report[1]);
    std::string said;
    char buf[4096];
    for (ssize_t n; (n = ::read(report[0], buf, sizeof buf)) > 0;) said.append(buf, static_cast<std::size_t>(n));
    ::close(report[0]);
    ASSERT_EQ(sbs_test::wait_child(attacker, 10000), 0) << said;
    const std::string dir = said.substr(0, said.find('\n'));
    ASSERT_TRUE(std::filesystem::is_regular_file(dir + "/probe.rmod")) << said;
    EXPECT_NE(said.find("authenticate first"), std::string::npos) << said;
    EXPECT_EQ(said.find("spawned"), std::string::npos) << said;
    EXPECT_NE(said.find("unix: "), std::string::npos) << said;
    EXPECT_EQ(said.find(R"("ok":true)"), std::string::npos) << "nobody was let in: " << said;

    // Even a peer holding the token names nothing outside the module path.
    auto c = NetworkClient::connect_tcp("127.0.0.1", static_cast<std::uint16_t>(port));
    ASSERT_TRUE(c.request("token s3cret", 10000)["ok"].get<bool>());
    for (const std::string& name : {dir + "/probe.rmod", dir + "/probe", std::string("../../../..") + dir + "/probe",
                                    "ramp+" + dir + "/probe"}) {
        for (const char* cmd : {"spawn ", "module "}) {
            const auto r = c.request(cmd + name, 10000);
            EXPECT_FALSE(r["ok"].get<bool>()) << cmd << name;
            EXPECT_NE(r.value("error", "").find("over the network only"), std::string::npos) << r.dump();
        }
    }
    // A file that is not a .rmod is never read for the peer, so never shown:
    // neither one named by path nor one on the module path (the probe
    // library is on it: it was built there).
    const auto passwd = c.request("spawn /etc/passwd", 10000);
    EXPECT_FALSE(passwd["ok"].get<bool>());
    EXPECT_EQ(passwd.dump().find("root:"), std::string::npos) << passwd.dump();
    const std::string library = std::filesystem::path(sbs_test::env("PROBE_SO")).filename();
    for (const char* cmd : {"spawn ", "module "}) {
        const auto r = c.request(cmd + library, 10000);
        EXPECT_FALSE(r["ok"].get<bool>()) << r.dump();
        EXPECT_EQ(r.dump().find("ELF"), std::string::npos) << r.dump();
        EXPECT_EQ(r.dump().find("found"), std::string::npos) << r.dump();
    }
    // Nor loads a library by path, nor writes a file.
    for (const std::string& cmd : {"module load " + sbs_test::env("PROBE_SO"), "save " + dir + "/x.sbs"}) {
        const auto r = c.request(cmd, 10000);
        EXPECT_FALSE(r["ok"].get<bool>()) << cmd;
        EXPECT_NE(r.value("error", "").find("over the network"), std::string::npos) << r.dump();
    }
    EXPECT_FALSE(std::filesystem::exists(dir + "/x.sbs"));
    EXPECT_FALSE(std::filesystem::exists(marker)) << "the probe's constructor ran in the master";
    // What is on the module path still spawns by name.
    EXPECT_TRUE(c.request("spawn ramp", 10000)["ok"].get<bool>());
    c.request("finish", 10000);
    EXPECT_EQ(m.wait(), 0) << m.err_text();
    EXPECT_FALSE(std::filesystem::exists(marker)) << "the probe's constructor ran in the master";

    // The control: the owner's own command line may name that folder, and
    // then the probe's constructor does run — so the marker above would have
    // shown a load through the network.
    ::setenv("CHIMERA_PROBE_MARKER", marker.c_str(), 1);
    const auto local = ws.sbs_run({"--no-attach", "-c", "spawn " + dir + "/probe.rmod; quit"});
    ::unsetenv("CHIMERA_PROBE_MARKER");
    EXPECT_TRUE(std::filesystem::exists(marker)) << "the probe never runs, so the test above proves nothing: "
                                                 << local.out << local.err;
    std::error_code ec;
    std::filesystem::remove_all(dir, ec);
}

TEST(SbsNetwork, AttachToARunningMaster) {
    Workspace ws;
    Master m(ws, {"--serve", "-c", "spawn ramp; on"});
    ASSERT_TRUE(sbs_test::wait_for_file(ws.socket_path()));
    // A second `sbs` on the same .sbs finds the master and becomes its peer.
    const auto r = ws.sbs_run({"-c", "status; display ramp", "--json"});
    EXPECT_EQ(r.status, 0) << r.err;
    const auto replies = sbs_test::json_lines(r.out);
    ASSERT_EQ(replies.size(), 2u) << r.out;
    EXPECT_EQ(replies[0]["data"]["tasks"][0]["rmod"], "ramp");
    EXPECT_EQ(replies[1]["data"]["vars"][0]["units"], "m");
    const auto bad = ws.sbs_run({"-c", "on"});
    EXPECT_EQ(bad.status, 1);
    EXPECT_NE(bad.err.find("already ON"), std::string::npos) << bad.err;
    // Control came back each time: a third one gets in and finishes it.
    const auto fin = ws.sbs_run({"-c", "finish"});
    EXPECT_EQ(fin.status, 0) << fin.err;
    EXPECT_EQ(m.wait(), 0) << m.err_text();
}

// Issue #35.2: an attached sbs fed commands on a pipe exits 1 when one failed.
TEST(SbsNetwork, AttachedOnAPipeExitsNonZeroAfterAFailedCommand) {
    Workspace ws;
    Master m(ws, {"--serve", "-c", "spawn ramp"});
    ASSERT_TRUE(sbs_test::wait_for_file(ws.socket_path()));
    const auto failed = ws.sbs_run({}, "status\nbogus\nstatus\n");
    EXPECT_EQ(failed.status, 1) << failed.out << failed.err;
    EXPECT_NE(failed.out.find("error: unknown command 'bogus'"), std::string::npos) << failed.out;
    const auto fine = ws.sbs_run({}, "status\n");
    EXPECT_EQ(fine.status, 0) << fine.out << fine.err;
    EXPECT_EQ(ws.sbs_run({"-c", "finish"}).status, 0);
    EXPECT_EQ(m.wait(), 0) << m.err_text();
}

TEST(SbsNetwork, PromptPassesControlAndGetsItBack) {
    Workspace ws;
    auto a = ws.sbs_args({"--listen"});
    a.insert(a.begin(), sbs_test::env("SBS_EXE"));
    int fd = -1;
    const pid_t pid = ::forkpty(&fd, nullptr, nullptr, nullptr);
    if (pid == 0) {
        std::vector<char*> v;
        for (const auto& s : a) v.push_back(const_cast<char*>(s.c_str()));
        v.push_back(nullptr);
        ::execv(v[0], v.data());
        ::_exit(127);
    }
    std::string out;
    const std::string prompt = "SBS " + ws.subsystem() + "<";
    ASSERT_TRUE(sbs_test::read_until(fd, out, prompt + "> ")) << out;
    // The command line has control: a peer is told so.
    {
        auto c = NetworkClient::connect_unix(ws.socket_path());
        EXPECT_FALSE(c.hello().value("ok", true));
        EXPECT_NE(c.hello()["error"].get<std::string>().find("command line"), std::string::npos);
    }
    auto type = [&](const std::string& s) { sbs_test::type_at_prompt(fd, s); };
    type("network\r");
    out.clear();
    ASSERT_TRUE(sbs_test::read_until(fd, out, "control passed to the network")) << out;
    {
        auto c = NetworkClient::connect_unix(ws.socket_path());
        ASSERT_TRUE(c.hello().value("ok", false)) << c.hello().dump();
        EXPECT_TRUE(c.request("spawn ramp", 10000)["ok"].get<bool>());
        // Connection lost without quit.
    }
    out.clear();
    ASSERT_TRUE(sbs_test::read_until(fd, out, "network connection lost: control is back")) << out;
    // The prompt has the RMOD the peer addressed last.
    ASSERT_TRUE(sbs_test::read_until(fd, out, prompt + "ramp> ")) << out;
    type("network\r");
    out.clear();
    ASSERT_TRUE(sbs_test::read_until(fd, out, "control passed to the network")) << out;
    {
        auto c = NetworkClient::connect_unix(ws.socket_path());
        ASSERT_TRUE(c.hello().value("ok", false));
        EXPECT_TRUE(c.request("on", 10000)["ok"].get<bool>());
        EXPECT_TRUE(c.request("quit", 10000)["ok"].get<bool>());
    }
    out.clear();
    ASSERT_TRUE(sbs_test::read_until(fd, out, "network peer quit: control is back")) << out;
    // Ctrl-C takes control back from a connected peer.
    type("network\r");
    out.clear();
    ASSERT_TRUE(sbs_test::read_until(fd, out, "control passed to the network")) << out;
    auto c = NetworkClient::connect_unix(ws.socket_path());
    ASSERT_TRUE(c.hello().value("ok", false));
    // Ctrl-C while the network has control (no prompt: the terminal is cooked).
    [[maybe_unused]] const auto n = ::write(fd, "\x03", 1);
    out.clear();
    ASSERT_TRUE(sbs_test::read_until(fd, out, "control taken back from the network")) << out;
    const auto line = c.read_line(5000);
    ASSERT_TRUE(line.has_value());
    EXPECT_NE(line->find("control taken back"), std::string::npos) << *line;
    ASSERT_TRUE(sbs_test::read_until(fd, out, prompt + "ramp> ")) << out;
    type("status\r");
    out.clear();
    ASSERT_TRUE(sbs_test::read_until(fd, out, "1 task")) << out;
    ASSERT_TRUE(sbs_test::read_until(fd, out, prompt + "ramp> ")) << out;
    EXPECT_NE(out.find(" ON "), std::string::npos) << out;
    type("quit\r");
    std::string rest;
    sbs_test::read_until(fd, rest, "\x01never\x01", 500);
    EXPECT_EQ(sbs_test::wait_child(pid, 15000), 0);
    ::close(fd);
    EXPECT_FALSE(std::filesystem::exists(ws.socket_path()));
}

// `record` from a second sbs attached to a running master: the master runs
// the sampler task, the attached sbs reads the ring and writes the file where
// it runs. Sent by a peer straight to the master, `record` is refused (the
// master writes no file for a peer).
TEST(SbsNetwork, RecordFromAnAttachedSbsAndNotFromAPeer) {
    Workspace ws;
    Master m(ws, {"--serve", "-c", "spawn ramp; on"});
    ASSERT_TRUE(sbs_test::wait_for_file(ws.socket_path()));
    const std::string csv = ws.dir() + "/attached.csv";
    const auto r = ws.sbs_run({"-c", "record X 0.25s " + csv, "--json"});
    EXPECT_EQ(r.status, 0) << r.out << r.err;
    const auto replies = sbs_test::json_lines(r.out);
    ASSERT_EQ(replies.size(), 1u) << r.out;
    EXPECT_EQ(replies[0]["data"]["samples"], 50);
    std::ifstream in(csv);
    std::string line;
    std::getline(in, line);
    EXPECT_EQ(line, "t,X");
    int rows = 0;
    while (std::getline(in, line)) ++rows;
    EXPECT_EQ(rows, 50);
    {
        NetworkClient c = connect(ws);
        const auto j = c.request("record X 1s " + ws.dir() + "/peer.csv", 5000);
        EXPECT_FALSE(j.value("ok", true));
        EXPECT_EQ(j.value("error", ""), "record writes a file, so it runs in the sbs program that asked (sbs FILE.sbs -c "
                                        "'record ...'), never over the network: a peer runs `sample` and reads the ring itself");
        const auto status = c.request("status", 5000);
        EXPECT_EQ(status["data"]["tasks"].size(), 1u) << "the attached record killed its sampler";
        c.request("finish", 5000);
    }
    EXPECT_EQ(m.wait(), 0) << m.err_text();
    EXPECT_FALSE(std::filesystem::exists(ws.dir() + "/peer.csv"));
}

// Issue #29.4: no command from the network makes a file be written. A peer
// may neither spawn nor turn on (on, reconfig on) a task whose module writes a
// file (the logger's LOCAL FILE); the master's own -c may, and writes it.
TEST(SbsNetwork, APeerMakesNoFileBeWritten) {
    const char* logger = std::getenv("LOGGER_SO");
    if (logger == nullptr) GTEST_SKIP() << "the logger module is not built (robotics disabled)";
    Workspace ws;  // HOME is its folder: the output folder is $HOME/.local/state/chimera/SUBSYSTEM
    ::unsetenv("XDG_STATE_HOME");
    ::unsetenv("CHIMERA_OUTPUT_DIR");
    ws.write("xlog.rmod", "MODULE logger\nDESC x logger\nINCONST none\nOUTCONST none\nINVAR X\nOUTVAR none\n"
                          "TASKTYPE periodic\nFREQ 50\n\nLOCAL\nFILE x.csv\nEOF\n");
    ws.write("ylog.rmod", "MODULE logger\nDESC y logger\nINCONST none\nOUTCONST none\nINVAR Y\nOUTVAR none\n"
                          "TASKTYPE periodic\nFREQ 50\n\nLOCAL\nFILE y.csv\nEOF\n");
    const std::string out_dir = ws.dir() + "/.local/state/chimera/" + ws.subsystem();
    Master m(ws, {"--serve", "-c", std::string("module load ") + logger + "; spawn ramp; on; spawn ylog"});
    {
        NetworkClient c = connect(ws);
        const auto refused = [&](const std::string& command, const std::string& expected) {
            const auto j = c.request(command, 5000);
            EXPECT_FALSE(j.value("ok", true)) << command;
            EXPECT_EQ(j.value("error", ""), expected) << command;
        };
        const std::string where = "at the master's own prompt, with -c, or in the .sbs (TASK ... ON)";
        refused("spawn xlog", "spawn xlog refused: its module writes a file (LOCAL FILE), and over the network no "
                              "file is written; spawn it " + where);
        refused("on ylog", "on ylog refused: its module writes a file (LOCAL FILE), and over the network no file is "
                           "written; on it " + where);
        refused("reconfig off ramp, on ylog", "reconfig on ylog refused: its module writes a file (LOCAL FILE), and "
                                              "over the network no file is written; reconfig on it " + where);
        const auto status = c.request("status all", 5000);
        ASSERT_EQ(status["data"]["tasks"].size(), 2u) << status.dump();
        for (const auto& t : status["data"]["tasks"])  // as before the refused reconfig
            EXPECT_EQ(t["state"], t["rmod"] == "ramp" ? "ON" : "OFF") << t.dump();
        c.request("finish", 5000);
    }
    EXPECT_EQ(m.wait(), 0) << m.err_text();
    EXPECT_FALSE(std::filesystem::exists(out_dir + "/x.csv"));
    EXPECT_FALSE(std::filesystem::exists(out_dir + "/y.csv"));
    // The master's own -c spawns and turns it on, and it writes its file.
    const auto local = ws.sbs_run({"-c", std::string("module load ") + logger + "; spawn xlog; on; sleep 0.2; off"});
    EXPECT_EQ(local.status, 0) << local.out << local.err;
    EXPECT_TRUE(std::filesystem::is_regular_file(out_dir + "/x.csv")) << local.out << local.err;
}

// Ctrl-C during a long `record` stops it: the rows taken are kept in the
// file, the command fails saying so, and the sampler task is killed.
TEST(SbsNetwork, RecordInterruptedKeepsWhatItTook) {
    Workspace ws;
    const std::string csv = ws.dir() + "/long.csv";
    Master m(ws, {"-c", "spawn ramp; on; record X 60s " + csv});
    ASSERT_TRUE(sbs_test::wait_for_file(csv + ".part"));
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    ::kill(m.pid(), SIGINT);
    EXPECT_TRUE(m.stderr_has("error: record: interrupted after ")) << m.err_text();
    EXPECT_EQ(m.wait(), 1) << m.err_text();
    EXPECT_NE(m.err_text().find(" of 12000 samples"), std::string::npos) << m.err_text();
    EXPECT_FALSE(std::filesystem::exists(csv + ".part"));
    std::ifstream in(csv);
    std::string line;
    std::getline(in, line);
    EXPECT_EQ(line, "t,X");
    int rows = 0;
    while (std::getline(in, line)) ++rows;
    EXPECT_GT(rows, 0);
    EXPECT_LT(rows, 12000);
}

// Who may watch the table may watch its samples: the ring has the table's mode
// (0640 with the watch group, docs/permissions.md; else both 0600).
TEST(SbsNetwork, ASampleRingHasTheTablesMode) {
    Workspace ws;
    Master m(ws, {"--serve", "-c", "spawn ramp; on"});
    NetworkClient c = connect(ws);
    const auto j = c.request("sample X", 5000);
    ASSERT_TRUE(j.value("ok", false)) << j.dump();
    struct stat ring {}, table {};
    ASSERT_EQ(::stat(("/dev/shm" + j["data"]["ring"].get<std::string>()).c_str(), &ring), 0);
    ASSERT_EQ(::stat(("/dev/shm/chimera." + ws.subsystem() + ".svar").c_str(), &table), 0);
    EXPECT_EQ(ring.st_mode & 0777, table.st_mode & 0777);
    c.request("finish", 5000);
    EXPECT_EQ(m.wait(), 0) << m.err_text();
}

// What a client can make the master allocate is bounded (issue #29.2,
// docs/permissions.md): the issue's --capacity 4194304 ring (256 MiB for one
// channel: entries are 64 bytes) is refused naming the 32 MiB bound; rings of
// 16 MiB are granted until all clients' rings would pass 128 MiB; then small
// ones until clients run 8 samplers. Each refusal leaves no task; killing one
// frees its share.
TEST(SbsNetwork, AClientsSamplersAreBoundedAndNeverShrunk) {
    Workspace ws;
    Master m(ws, {"--serve", "-c", "spawn ramp; on"});
    NetworkClient c = connect(ws);
    const auto error_of = [&](const std::string& command) {
        const auto j = c.request(command, 10000);
        EXPECT_FALSE(j.value("ok", true)) << command;
        return j.value("error", "");
    };
    const auto started = [&](const std::string& command) {
        const auto j = c.request(command, 10000);
        EXPECT_TRUE(j.value("ok", false)) << command << ": " << j.dump();
        return j.value("data", nlohmann::json::object()).value("rmod", "");
    };
    EXPECT_EQ(error_of("sample X --capacity 4194304"),
              "sample refused: its ring would take 256.0 MiB, over the 32.0 MiB a client's ring may have (fewer "
              "channels, a lower --rate or a smaller --capacity)");
    const std::string big = "sample X --capacity 262144";  // 16 MiB
    std::vector<std::string> rings;
    for (int i = 0; i < 7; ++i) rings.push_back(started(big));
    EXPECT_EQ(error_of(big), "sample refused: clients' rings already take 112.0 MiB; with 16.0 MiB more they would "
                             "pass the 128.0 MiB all clients' rings may have");
    rings.push_back(started("sample X --capacity 1024"));
    EXPECT_EQ(error_of("sample X --capacity 1024"),
              "sample refused: clients already run 8 samplers, the most they may (kill one first)");
    EXPECT_TRUE(c.request("kill " + rings.front(), 10000).value("ok", false));
    EXPECT_FALSE(started(big).empty()) << "a killed sampler's ring no longer counts";
    const auto status = c.request("status all", 10000);
    EXPECT_EQ(status["data"]["tasks"].size(), 9u) << "ramp and 8 samplers, no refused one";
    c.request("finish", 10000);
    EXPECT_EQ(m.wait(), 0) << m.err_text();
}

// ------------------------------------------ issue #29.2: a client's tasks are admitted like a sampler

namespace {

// cpu0 (MUF, 1..1000 Hz) and quick (up to 5 kHz); heavy reserves 99% of cpu0
// (C 4.95 ms every 5 ms); fast runs at 2 kHz; brisk (C 100 us at 1 kHz)
// would come before heavy in MUF's order and push it out; slow (C 100 us at
// 10 Hz) fits beside it. Only heavy writes a variable, so verification never
// stands in the way.
void admission_tasks(const Workspace& ws) {
    ws.write(ws.subsystem() + ".sbs", "SUBSYSTEM " + ws.subsystem() + "\nSVARFILE  " + sbs_test::env("SBS_TEST_DATA") +
                                          "/tools.svar\nRTPU      cpu0\nBACKEND   other\n"
                                          "RTPU      quick 0\nMAXFREQ   5000\nBACKEND   other\nEOF\n");
    const auto rmod = [&](const std::string& name, const std::string& out, const std::string& timing) {
        ws.write(name + ".rmod", "MODULE ramp\nDESC " + name + "\nINVAR none\nOUTVAR " + out +
                                     "\nTASKTYPE periodic\n" + timing + "\nEOF\n");
    };
    rmod("heavy", "X", "FREQ 200\nWCET 0.00495");
    rmod("fast", "none", "FREQ 2000");
    rmod("brisk", "none", "FREQ 1000\nWCET 0.0001");
    rmod("slow", "none", "FREQ 10\nWCET 0.0001");
}

}  // namespace

// Issue #29.2: a TCP peer with control may not spawn a task at a rate outside
// its RTPU's range (it is offered the RTPU that runs it), nor turn on or
// re-rate one so that the RTPU's MUF analysis would lose heavy from its
// critical set; `off heavy, on brisk` in one reconfig is judged item by item.
// Each refusal is compared in full and leaves the tasks as they were.
TEST(SbsNetwork, AClientsSpawnOnAndFreqAreAdmittedLikeASampler) {
    Workspace ws;
    admission_tasks(ws);
    Master m(ws, {"--serve", "--tcp", "127.0.0.1:0", "--token", "s3cret", "-c", "spawn heavy; on"});
    ASSERT_TRUE(m.stderr_has("TCP 127.0.0.1:")) << m.err_text();
    ASSERT_TRUE(m.stderr_has("\n")) << m.err_text();
    const int port = std::stoi(m.err_text().substr(m.err_text().find("TCP 127.0.0.1:") + 14));
    auto c = NetworkClient::connect_tcp("127.0.0.1", static_cast<std::uint16_t>(port));
    ASSERT_TRUE(c.request("token s3cret", 10000).value("ok", false));
    const auto refused = [&](const std::string& command, const std::string& expected) {
        const auto j = c.request(command, 10000);
        EXPECT_FALSE(j.value("ok", true)) << command;
        EXPECT_EQ(j.value("error", ""), expected) << command;
    };
    const auto granted = [&](const std::string& command) {
        const auto j = c.request(command, 10000);
        EXPECT_TRUE(j.value("ok", false)) << command << ": " << j.dump();
        EXPECT_FALSE(j.value("data", nlohmann::json::object()).contains("admission")) << j.dump();
        return j;
    };
    refused("spawn fast", "spawn fast refused: 2000 Hz is above RTPU cpu0's MAXFREQ (it runs tasks at 1 to 1000 Hz); "
                          "spawn fast quick takes it");
    EXPECT_EQ(granted("spawn fast quick")["data"]["rtpu"], "quick");
    granted("spawn brisk");  // OFF: it takes no CPU until `on`
    const std::string brisk = "RTPU cpu0 (MUF) cannot take brisk at 1000 Hz (C 100 us, U 0.100): the critical set "
                              "would lose heavy (U 0.990) (utilisation with it 1.090, bound 1.000)";
    refused("on brisk", "on brisk refused: " + brisk);
    refused("reconfig on brisk", "reconfig on brisk refused: " + brisk);
    granted("reconfig off heavy, on brisk");
    refused("reconfig on heavy", "reconfig on heavy refused: RTPU cpu0 (MUF) cannot take heavy at 200 Hz (C 4950 us, "
                                 "U 0.990): it would not be in the critical set itself (utilisation with it 1.090, "
                                 "bound 1.000)");
    granted("reconfig off brisk, on heavy");
    granted("spawn slow");
    granted("on slow");
    refused("freq slow 2000", "freq slow refused: 2000 Hz is above RTPU cpu0's MAXFREQ (it runs tasks at 1 to 1000 Hz)");
    refused("freq slow 500", "freq slow refused: RTPU cpu0 (MUF) cannot take slow at 500 Hz (C 100 us, U 0.050): the "
                             "critical set would lose heavy (U 0.990) (utilisation with it 1.040, bound 1.000)");
    EXPECT_EQ(granted("freq slow 20")["data"]["freq"], 20.0);
    refused("freq brisk 2000", "freq brisk refused: 2000 Hz is above RTPU cpu0's MAXFREQ (it runs tasks at 1 to 1000 Hz)");
    const auto status = c.request("status all", 10000);
    std::map<std::string, std::string> states;
    for (const auto& t : status["data"]["tasks"]) states[t["rmod"]] = t["state"];
    EXPECT_EQ(states, (std::map<std::string, std::string>{{"brisk", "OFF"}, {"fast", "OFF"}, {"heavy", "ON"}, {"slow", "ON"}}))
        << status.dump();
    c.request("finish", 10000);
    EXPECT_EQ(m.wait(), 0) << m.err_text();
}

// The owner (the prompt, -c, the .sbs) is not refused: the thesis lets the
// operator run a task outside MINFREQ..MAXFREQ (it only scales criticality),
// so the command runs and its reply carries the warning a client's refusal
// would have given (docs/permissions.md).
TEST(SbsNetwork, TheOwnerIsWarnedNotRefused) {
    Workspace ws;
    admission_tasks(ws);
    const auto r = ws.sbs_run({"-c", "spawn heavy; on; spawn fast; spawn brisk; on brisk; freq brisk 2000; status all",
                               "--json"});
    EXPECT_EQ(r.status, 0) << r.out << r.err;
    const std::vector<nlohmann::json> replies = sbs_test::json_lines(r.out);
    ASSERT_EQ(replies.size(), 7u) << r.out;
    const auto warning = [&](std::size_t i) {
        EXPECT_TRUE(replies[i].value("ok", false)) << replies[i].dump();
        return replies[i].value("data", nlohmann::json::object()).value("admission", "");
    };
    const std::string owner = " (run as the owner asked; a client would be refused)";
    EXPECT_EQ(warning(0), "");
    EXPECT_EQ(warning(2), "WARNING> spawn fast: 2000 Hz is above RTPU cpu0's MAXFREQ (it runs tasks at 1 to 1000 Hz)" + owner);
    EXPECT_EQ(warning(4), "WARNING> on brisk: RTPU cpu0 (MUF) cannot take brisk at 1000 Hz (C 100 us, U 0.100): the "
                          "critical set would lose heavy (U 0.990) (utilisation with it 1.090, bound 1.000)" + owner);
    EXPECT_EQ(warning(5), "WARNING> freq brisk: 2000 Hz is above RTPU cpu0's MAXFREQ (it runs tasks at 1 to 1000 Hz)" + owner);
    EXPECT_NE(replies[4].value("text", "").find("\n" + warning(4)), std::string::npos) << replies[4].dump();
    std::map<std::string, std::string> states;
    for (const auto& t : replies[6]["data"]["tasks"]) states[t["rmod"]] = t["state"];
    EXPECT_EQ(states, (std::map<std::string, std::string>{{"brisk", "ON"}, {"fast", "OFF"}, {"heavy", "ON"}}));
}

// ------------------------------------------ issue #29.3: the web console under a flood

using namespace std::chrono_literals;

namespace {

/// A blocking loopback TCP connection from `source` (a 127/8 address) with a
/// 3 s receive timeout, or -1.
int dial_from(const char* source, std::uint16_t port) {
    const int fd = flood_test::connect_from(source, port);
    if (fd < 0) return -1;
    pollfd p{fd, POLLOUT, 0};
    ::poll(&p, 1, 3000);
    ::fcntl(fd, F_SETFL, 0);
    timeval tv{3, 0};
    ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
    return fd;
}

int dial(std::uint16_t port) { return dial_from("127.0.0.1", port); }

bool send_all(int fd, const std::string& s) { return ::send(fd, s.data(), s.size(), MSG_NOSIGNAL) == static_cast<ssize_t>(s.size()); }

std::string read_head(int fd) {
    std::string head;
    char c = 0;
    while (head.find("\r\n\r\n") == std::string::npos && ::recv(fd, &c, 1, 0) == 1) head += c;
    return head;
}

bool recv_exact(int fd, void* buf, std::size_t n) { return ::recv(fd, buf, n, MSG_WAITALL) == static_cast<ssize_t>(n); }

/// One WebSocket frame from the server (unmasked, RFC 6455), its payload.
std::optional<std::string> read_frame(int fd) {
    unsigned char h[2];
    if (!recv_exact(fd, h, 2)) return std::nullopt;
    std::uint64_t len = h[1] & 0x7f;
    if (len >= 126) {
        unsigned char ext[8];
        const std::size_t n = len == 126 ? 2 : 8;
        if (!recv_exact(fd, ext, n)) return std::nullopt;
        len = 0;
        for (std::size_t i = 0; i < n; ++i) len = (len << 8) | ext[i];
    }
    std::string payload(len, '\0');
    if (len > 0 && !recv_exact(fd, payload.data(), len)) return std::nullopt;
    return payload;
}

/// A masked text frame, as a client must send it.
bool send_text(int fd, const std::string& text) {
    std::string f{'\x81'};
    f += static_cast<char>(0x80 | text.size());  // short messages only
    const char mask[4] = {0x11, 0x22, 0x33, 0x44};
    f.append(mask, 4);
    for (std::size_t i = 0; i < text.size(); ++i) f += static_cast<char>(text[i] ^ mask[i % 4]);
    return send_all(fd, f);
}

/// Reads frames until the reply to `cmd` (pushed graph frames are skipped).
nlohmann::json reply_to(int fd, const std::string& cmd) {
    for (int i = 0; i < 20; ++i) {
        const auto f = read_frame(fd);
        if (!f) return nullptr;
        const auto j = nlohmann::json::parse(*f, nullptr, false);
        if (j.is_object() && j.value("cmd", "") == cmd) return j;
    }
    return nullptr;
}

std::string upgrade_request(std::uint16_t port) {
    return "GET /ws HTTP/1.1\r\nHost: 127.0.0.1:" + std::to_string(port) +
           "\r\nUpgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
           "Sec-WebSocket-Version: 13\r\n\r\n";
}

/// A page's socket from `source`, open (101 and the greeting read), or -1.
int open_page(const char* source, std::uint16_t port) {
    const int fd = dial_from(source, port);
    if (fd < 0) return -1;
    send_all(fd, upgrade_request(port));
    if (read_head(fd).rfind("HTTP/1.1 101", 0) != 0 || !read_frame(fd)) {
        ::close(fd);
        return -1;
    }
    return fd;
}

/// A new page from `source` sends `token T` first: the reply (null when the
/// page could not be opened). The page is closed after.
nlohmann::json page_token(const char* source, std::uint16_t port, const std::string& token) {
    const int fd = open_page(source, port);
    if (fd < 0) return nullptr;
    send_text(fd, "token " + token);
    auto reply = reply_to(fd, "token");
    ::close(fd);
    return reply;
}

/// The port in "... on http://127.0.0.1:PORT/" of the master's stderr.
std::uint16_t web_port(const Master& m) {
    const auto at = m.err_text().find("http://127.0.0.1:");
    return at == std::string::npos ? 0 : static_cast<std::uint16_t>(std::stoi(m.err_text().substr(at + 17)));
}

/// The operator's browser at 127.0.0.1: GET / served, then a page's socket:
/// token, control, release. Timed from the first connect to control granted.
flood_test::Attempt operator_over_http(std::uint16_t port) {
    const auto start = std::chrono::steady_clock::now();
    flood_test::Attempt a;
    auto elapsed = [&] {
        return std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::steady_clock::now() - start);
    };
    int fd = dial(port);
    send_all(fd, "GET / HTTP/1.1\r\nHost: 127.0.0.1:" + std::to_string(port) + "\r\n\r\n");
    const std::string page = read_head(fd);
    ::close(fd);
    if (page.rfind("HTTP/1.1 200", 0) != 0) {
        a.detail = "GET /: " + page.substr(0, 80);
        a.took = elapsed();
        return a;
    }
    fd = dial(port);
    send_all(fd, upgrade_request(port));
    const std::string head = read_head(fd);
    const auto hello = read_frame(fd);
    send_text(fd, "token tok");
    const auto token = reply_to(fd, "token");
    send_text(fd, "control");
    const auto control = reply_to(fd, "control");
    a.took = elapsed();
    a.got_control = head.rfind("HTTP/1.1 101", 0) == 0 && hello && token.is_object() && token.value("ok", false) &&
                    control.is_object() && control.value("ok", false);
    if (!a.got_control) a.detail = head.substr(0, 40) + " | " + token.dump() + " | " + control.dump();
    send_text(fd, "release");
    reply_to(fd, "release");  // control is free before the next attempt
    ::close(fd);
    return a;
}

/// The TCP ports on which process `pid` listens, as this process's network
/// namespace sees them: its listening sockets' inodes looked up in
/// /proc/net/tcp and tcp6 (a socket in another namespace is not there).
std::set<std::uint16_t> listening_ports_seen_here(pid_t pid) {
    std::set<std::string> inodes;
    const std::string fd_dir = "/proc/" + std::to_string(pid) + "/fd";
    for (const auto& e : std::filesystem::directory_iterator(fd_dir)) {
        std::error_code ec;
        const std::string target = std::filesystem::read_symlink(e.path(), ec).string();
        if (!ec && target.rfind("socket:[", 0) == 0) inodes.insert(target.substr(8, target.size() - 9));
    }
    std::set<std::uint16_t> ports;
    for (const char* table : {"/proc/net/tcp", "/proc/net/tcp6"}) {
        std::ifstream in(table);
        std::string line;
        std::getline(in, line);  // the heading
        while (std::getline(in, line)) {
            std::istringstream f(line);
            std::string slot, local, remote, state, queues, timer, retr, uid, timeout, inode;
            f >> slot >> local >> remote >> state >> queues >> timer >> retr >> uid >> timeout >> inode;
            if (state == "0A" && inodes.count(inode))  // 0A: LISTEN
                ports.insert(static_cast<std::uint16_t>(std::stoul(local.substr(local.find(':') + 1), nullptr, 16)));
        }
    }
    return ports;
}

}  // namespace

// Two threads from 127.0.0.2 connect to the web console every 2 ms each for
// 10 s, hold up to 1000 connections, and open an unauthenticated page
// (a complete WebSocket upgrade, then silence) on a third of them. The
// operator at 127.0.0.1 gets the page and control 20 of 20 times, each
// within 1 s (before the gate, idle sockets held civetweb's 24 workers).
TEST(SbsNetwork, ATokenlessFloodNeverKeepsTheOperatorOutOfTheWebConsole) {
    const int probe = flood_test::connect_from("127.0.0.2", 9);
    if (probe < 0) GTEST_SKIP() << "cannot bind 127.0.0.2 (no 127/8 on lo here)";
    ::close(probe);
    flood_test::raise_fd_limit();
    Workspace ws;
    Master m(ws, {"--serve", "--http", "127.0.0.1:0", "--token", "tok"});
    if (!m.stderr_has("web console of subsystem", 20000)) GTEST_SKIP() << "no web console here: " << m.err_text();
    ASSERT_TRUE(m.stderr_has("/ (the page")) << m.err_text();
    const auto at = m.err_text().find("http://127.0.0.1:");
    const auto port = static_cast<std::uint16_t>(std::stoi(m.err_text().substr(at + 17)));
    flood_test::StallDetector stalls;
    flood_test::Flood flood(port, upgrade_request(port));
    std::this_thread::sleep_for(1s);
    const auto tries = flood_test::timed_attempts(20, 400ms, 1000ms, stalls, [&] { return operator_over_http(port); },
                                                  [](const std::string& what) { std::printf("[ stall ] %s\n", what.c_str()); });
    const std::uint64_t flooded = flood.connections();
    flood.stop();
    flood_test::expect_each_in_control(tries, 1000ms, flooded);
    EXPECT_GT(flooded, 1000u) << "the flood was not a flood";
}

// Issue #29.3: wrong tokens on a page slow its address down as over TCP (the
// one TokenBackOff): the reply says how long; a token sent sooner is refused
// unjudged, the right one too; another address is not slowed; the right token
// after the wait is accepted and starts the address afresh.
TEST(SbsNetwork, WrongTokensOnAPageAreThrottledPerAddressWithBackOff) {
    const int probe = flood_test::connect_from("127.0.0.2", 9);
    if (probe < 0) GTEST_SKIP() << "cannot bind 127.0.0.2 (no 127/8 on lo here)";
    ::close(probe);
    Workspace ws;
    Master m(ws, {"--serve", "--http", "127.0.0.1:0", "--token", "tok"});
    if (!m.stderr_has("web console of subsystem", 20000)) GTEST_SKIP() << "no web console here: " << m.err_text();
    ASSERT_TRUE(m.stderr_has("/ (the page")) << m.err_text();
    const std::uint16_t port = web_port(m);
    std::chrono::steady_clock::time_point last_guess;
    for (long expected : {100, 200, 400, 800}) {
        const auto r = page_token("127.0.0.2", port, "guess");
        last_guess = std::chrono::steady_clock::now();
        ASSERT_EQ(r.value("error", ""), "wrong token") << r.dump();
        EXPECT_EQ(r["data"]["retry_after_ms"], expected);
        // The back-off itself is what is waited for: it started before the reply came.
        if (expected < 800) std::this_thread::sleep_for(std::chrono::milliseconds(expected + 20));
    }
    // Within the 800 ms: refused unjudged, the right token too.
    const auto early = page_token("127.0.0.2", port, "tok");
    std::smatch left;
    const std::string why = early.value("error", "");
    const std::regex refused("too many wrong tokens from 127\\.0\\.0\\.2: retry after ([0-9]+) ms");
    ASSERT_TRUE(std::regex_match(why, left, refused)) << early.dump();
    EXPECT_GT(std::stol(left[1]), 0);
    EXPECT_LE(std::stol(left[1]), 800);
    EXPECT_FALSE(early.contains("data")) << "an unjudged token adds no back-off";
    // The operator's address is not slowed by 127.0.0.2's guesses.
    EXPECT_EQ(page_token("127.0.0.1", port, "tok").value("ok", false), true);
    std::this_thread::sleep_until(last_guess + std::chrono::milliseconds(850));
    EXPECT_EQ(page_token("127.0.0.2", port, "tok").value("ok", false), true);
    EXPECT_EQ(page_token("127.0.0.2", port, "guess")["data"]["retry_after_ms"], 100) << "started afresh";
}

// Issue #29.2: one reply to a network client is at most 1 MiB, and never
// cut. `display all` of a table with a 300 000-element array (about 1.8 MB of
// JSON) reaches the owner's Unix socket whole; a TCP peer and a web page get,
// instead, the refusal naming the bound, its size and their request, and
// their sessions go on.
TEST(SbsNetwork, AReplyPastOneMiBIsRefusedToNetworkClientsNeverCut) {
    Workspace ws;
    ws.write("big.svar", "NAME  BIG\nTYPE  double\nDESC  large\nUNITS m\nNELEM 300000\nINIT  0\n\n"
                         "NAME  X\nTYPE  double\nDESC  small\nUNITS m\nNELEM 1\nINIT  0\nEOF\n");
    ws.write(ws.subsystem() + ".sbs", "SUBSYSTEM " + ws.subsystem() + "\nSVARFILE  " + ws.dir() +
                                          "/big.svar\nRTPU      cpu0\nBACKEND   other\nEOF\n");
    Master m(ws, {"--serve", "--listen", "--tcp", "127.0.0.1:0", "--http", "127.0.0.1:0", "--token", "tok"});
    if (!m.stderr_has("web console of subsystem", 20000)) GTEST_SKIP() << "no web console here: " << m.err_text();
    ASSERT_TRUE(m.stderr_has("/ (the page")) << m.err_text();
    const auto at = m.err_text().find("TCP 127.0.0.1:");
    ASSERT_NE(at, std::string::npos) << m.err_text();
    const auto tcp_port = static_cast<std::uint16_t>(std::stoi(m.err_text().substr(at + 14)));

    NetworkClient owner = connect(ws);
    ASSERT_EQ(owner.request("token tok", 10000).value("ok", false), true);
    const auto whole = owner.request("display all", 20000);
    ASSERT_EQ(whole.value("ok", false), true) << whole.dump().substr(0, 300);
    ASSERT_EQ(whole["data"]["vars"][0]["values"].size(), 300000u);
    const std::size_t bytes = whole.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace).size();
    ASSERT_GT(bytes, 1048576u) << "the table is too small to test the bound";
    owner.request("quit", 10000);
    const nlohmann::json refusal = {
        {"ok", false},
        {"cmd", "display"},
        {"error", "the reply to 'display all' is " + std::to_string(bytes) +
                      " bytes, over the 1048576 (1 MiB) one reply to a network client may take, so none of it is "
                      "sent; ask for less, e.g. display VAR... (names, or patterns such as Q*) rather than display all"}};

    auto peer = NetworkClient::connect_tcp("127.0.0.1", tcp_port);
    ASSERT_EQ(peer.request("token tok", 10000).value("ok", false), true);
    EXPECT_EQ(peer.request("display all", 20000), refusal);
    EXPECT_EQ(peer.request("display X", 10000)["data"]["vars"][0]["name"], "X") << "the session goes on";
    peer.request("quit", 10000);

    const int page = open_page("127.0.0.1", web_port(m));
    ASSERT_GE(page, 0);
    send_text(page, "token tok");
    ASSERT_EQ(reply_to(page, "token").value("ok", false), true);
    send_text(page, "display all");
    EXPECT_EQ(reply_to(page, "display"), refusal);
    send_text(page, "display X");
    EXPECT_EQ(reply_to(page, "display")["data"]["vars"][0]["name"], "X") << "the page goes on";
    ::close(page);

    auto last = NetworkClient::connect_tcp("127.0.0.1", tcp_port);
    ASSERT_EQ(last.request("token tok", 10000).value("ok", false), true);
    last.request("finish", 10000);
    EXPECT_EQ(m.wait(), 0) << m.err_text();
}

// Issue #29.3: a civetweb worker is reached only through the gate. Where the
// master may make a network namespace (root), civetweb's own port is in one
// of its own: of the master's listening sockets, this machine's namespace
// sees the console's public port alone, so no local user can dial civetweb
// and hold its workers with idle sockets past the gate's bounds. The gate
// still relays into it: the operator's page gets control.
TEST(SbsNetwork, CivetwebsOwnPortIsOutOfEveryOtherProcesssReach) {
    if (::geteuid() != 0) GTEST_SKIP() << "a network namespace needs root: not run as root";
    Workspace ws;
    Master m(ws, {"--serve", "--http", "127.0.0.1:0", "--token", "tok"});
    if (!m.stderr_has("web console of subsystem", 20000)) GTEST_SKIP() << "no web console here: " << m.err_text();
    ASSERT_TRUE(m.stderr_has("/ (the page")) << m.err_text();
    const std::uint16_t port = web_port(m);
    EXPECT_EQ(listening_ports_seen_here(m.pid()), std::set<std::uint16_t>{port}) << m.err_text();
    EXPECT_EQ(m.err_text().find("past the gate"), std::string::npos) << m.err_text();
    const auto a = operator_over_http(port);
    EXPECT_TRUE(a.got_control) << a.detail;
}
