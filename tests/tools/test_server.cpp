// The network interface (§4.4.2) against a recording executor: control
// passing, the line protocol, malformed and oversized input, lost peers,
// permissions and the TCP token. The interpreter is tested separately; here
// only what the server itself decides is checked.
#include "as_user.hpp"
#include "client.hpp"
#include "flood.hpp"
#include "server.hpp"
#include "token_back_off.hpp"

#include <gtest/gtest.h>
#include <cstring>
#include <netdb.h>
#include <netinet/in.h>
#include <poll.h>
#include <pwd.h>

#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdlib>
#include <future>
#include <mutex>
#include <thread>
#include <vector>

using namespace chimera::cli;
using json = nlohmann::json;
using namespace std::chrono_literals;

namespace {

class TempDir {
public:
    TempDir() {
        char tmpl[] = "/tmp/chimera-cli-test-XXXXXX";
        path_ = ::mkdtemp(tmpl);
    }
    ~TempDir() { std::system(("rm -rf " + path_).c_str()); }
    const std::string& path() const { return path_; }

private:
    std::string path_;
};

struct Recorder {
    std::mutex mutex;
    std::vector<std::string> commands;

    Reply operator()(std::string_view command) {
        {
            std::lock_guard lock(mutex);
            commands.emplace_back(command);
        }
        Reply r;
        r.command = std::string(command.substr(0, command.find(' ')));
        if (command == "quit") r.action = Action::quit;
        if (command == "finish") r.action = Action::finish;
        if (command == "network") r.action = Action::network;
        if (command == "boom") throw std::runtime_error("executor blew up");
        if (command.substr(0, 5) == "echo ") r.text = std::string(command.substr(5));
        if (command == "fail") return Reply::failure("fail", "it failed");
        return r;
    }
    std::vector<std::string> seen() {
        std::lock_guard lock(mutex);
        return commands;
    }
};

struct Network : ::testing::Test {
    TempDir dir;
    Recorder recorder;
    std::string path = dir.path() + "/test.sock";

    std::unique_ptr<NetworkServer> make(ServerOptions o = {}) {
        o.subsystem = "testsys";
        if (o.unix_path.empty() && !o.tcp) o.unix_path = path;
        auto s = std::make_unique<NetworkServer>(o, [this](std::string_view c) { return recorder(c); });
        s->start();
        return s;
    }
};

// Runs hand_over() on another thread, as the prompt's `network` command does.
// A hand_over() running in another thread. If the test ends before the
// session did (a failed assertion, an exception), the server is stopped so the
// test fails at once instead of waiting for its timeout.
class HandOver {
public:
    HandOver(NetworkServer& s, std::atomic<bool>* interrupt)
        : server_(&s), f_(std::async(std::launch::async, [&s, interrupt] { return s.hand_over(interrupt); })) {
        std::this_thread::sleep_for(50ms);  // let the offer be made before peers connect
    }
    HandOver(HandOver&&) = default;
    HandOver& operator=(HandOver&& other) {
        finish();
        server_ = other.server_;
        f_ = std::move(other.f_);
        return *this;
    }
    ~HandOver() { finish(); }
    NetworkServer::SessionEnd get() { return f_.get(); }
    std::future_status wait_for(std::chrono::milliseconds d) { return f_.wait_for(d); }

private:
    void finish() {
        if (f_.valid() && f_.wait_for(0ms) != std::future_status::ready) server_->stop();
    }
    NetworkServer* server_;
    std::future<NetworkServer::SessionEnd> f_;
};

HandOver hand_over_async(NetworkServer& s, std::atomic<bool>* interrupt) { return HandOver(s, interrupt); }

// Names the cause when a host name the tests use does not resolve (a
// container without "localhost" in /etc/hosts), instead of a connect failure.
::testing::AssertionResult resolves(const char* host) {
    addrinfo hints{};
    hints.ai_socktype = SOCK_STREAM;
    addrinfo* res = nullptr;
    if (const int rc = ::getaddrinfo(host, "1", &hints, &res); rc != 0)
        return ::testing::AssertionFailure() << "host name '" << host << "' does not resolve (" << ::gai_strerror(rc)
                                             << "): add it to /etc/hosts";
    ::freeaddrinfo(res);
    return ::testing::AssertionSuccess();
}

}  // namespace

TEST(ParseRequest, EachLineIsACommandAKeepAliveOrMalformedWithTheReason) {
    using chimera::cli::parse_request;
    using Kind = chimera::cli::Request::Kind;
    EXPECT_EQ(parse_request("").kind, Kind::keep_alive);
    EXPECT_EQ(parse_request(" \t ").kind, Kind::keep_alive);
    const auto plain = parse_request("status all");
    EXPECT_EQ(plain.kind, Kind::command);
    EXPECT_EQ(plain.command, "status all");
    EXPECT_TRUE(plain.id.is_null());
    const auto structured = parse_request(R"({"cmd":"on ramp","id":7})");
    EXPECT_EQ(structured.kind, Kind::command);
    EXPECT_EQ(structured.command, "on ramp");
    EXPECT_EQ(structured.id, 7);
    const auto tab = parse_request("echo\ta");
    EXPECT_EQ(tab.kind, Kind::command);
    struct Bad {
        std::string line, error;
    };
    for (const Bad& b : {Bad{"{not json", "malformed JSON request"}, Bad{"{}x", "malformed JSON request"},
                         Bad{R"({"id":3})", "JSON request needs a string member \"cmd\""},
                         Bad{R"({"cmd":5})", "JSON request needs a string member \"cmd\""},
                         Bad{std::string("token\x01x"), "request contains control characters"},
                         Bad{R"({"cmd":"a\u001bb"})", "request contains control characters"}}) {
        const auto r = parse_request(b.line);
        EXPECT_EQ(r.kind, Kind::malformed) << b.line;
        EXPECT_EQ(r.error, b.error) << b.line;
        EXPECT_TRUE(r.command.empty()) << b.line;
    }
    EXPECT_EQ(parse_request(R"({"id":3})").id, 3);  // echoed even in the error reply
}

// Issue #29.2: a reply of exactly kMaxClientReplyBytes goes as it is; one
// byte more and the client gets a refusal naming the bound and its request
// instead, with its id, and no part of the reply.
TEST(ClientReply, AReplyPastTheBoundIsRefusedNamingItNeverCut) {
    Reply r;
    r.command = "display";
    const std::size_t frame = to_json_line(r, 7).size();
    r.text.assign(kMaxClientReplyBytes - frame, 'x');
    ASSERT_EQ(to_json_line(r, 7).size(), kMaxClientReplyBytes);
    EXPECT_EQ(to_client_line(r, 7, "display all"), to_json_line(r, 7));
    r.text += 'x';
    const json j = json::parse(to_client_line(r, 7, "display all"));
    EXPECT_EQ(j, json({{"id", 7}, {"ok", false}, {"cmd", "display"},
                       {"error", "the reply to 'display all' is 1048577 bytes, over the 1048576 (1 MiB) one reply "
                                 "to a network client may take, so none of it is sent; ask for less, e.g. display "
                                 "VAR... (names, or patterns such as Q*) rather than display all"}}));
}

// The back-off's rule without a clock: the waits double from 100 ms up to
// 10 s; the owner's Unix socket ("") is never throttled; a first line that is
// no token is refused without counting as a guess.
TEST(TokenBackOff, WaitsDoubleToTheCapAndOnlyWrongTokensCount) {
    EXPECT_EQ(TokenBackOff::after(1), 100ms);
    EXPECT_EQ(TokenBackOff::after(2), 200ms);
    EXPECT_EQ(TokenBackOff::after(7), 6400ms);
    EXPECT_EQ(TokenBackOff::after(8), 10000ms);
    EXPECT_EQ(TokenBackOff::after(40), 10000ms);
    TokenBackOff b;
    const auto wrong = b.judge("", "token guess", "tok");
    ASSERT_TRUE(wrong.has_value());
    EXPECT_EQ(wrong->error, "wrong token");
    EXPECT_EQ(wrong->data, json({{"retry_after_ms", 0}}));
    EXPECT_FALSE(b.judge("", "token tok", "tok").has_value()) << "the owner's socket waits for nothing";
    const auto first = b.judge("10.0.0.1", "status", "tok");
    ASSERT_TRUE(first.has_value());
    EXPECT_EQ(first->error, "authenticate first: token TOKEN");
    EXPECT_TRUE(first->data.is_null());
    EXPECT_FALSE(b.judge("10.0.0.1", "token tok", "tok").has_value()) << "no token is no guess";
}

TEST_F(Network, UnixSocketIsOwnerOnly) {
    auto s = make();
    struct stat st {};
    ASSERT_EQ(::stat(path.c_str(), &st), 0);
    EXPECT_TRUE(S_ISSOCK(st.st_mode));
    EXPECT_EQ(st.st_mode & 0777, 0600u);
    s->stop();
    EXPECT_NE(::access(path.c_str(), F_OK), 0) << "socket file must be removed on stop";
}

TEST_F(Network, PeerIsRefusedWhileTheCommandLineHasControl) {
    auto s = make();
    auto c = NetworkClient::connect_unix(path);
    EXPECT_FALSE(c.hello()["ok"].get<bool>());
    EXPECT_NE(c.hello()["error"].get<std::string>().find("command line"), std::string::npos);
    EXPECT_THROW(c.read_line(1000), ClientError) << "refused peer must be disconnected";
    EXPECT_TRUE(recorder.seen().empty());
}

TEST_F(Network, HandOverRunsCommandsUntilQuit) {
    auto s = make();
    std::atomic<bool> interrupt{false};
    auto done = hand_over_async(*s, &interrupt);
    auto c = NetworkClient::connect_unix(path);
    ASSERT_TRUE(c.hello()["ok"].get<bool>()) << c.hello().dump();
    EXPECT_EQ(c.hello()["subsystem"], "testsys");
    EXPECT_EQ(c.hello()["auth"], "none");
    auto r = c.request("echo hello world", 2000);
    EXPECT_TRUE(r["ok"].get<bool>());
    EXPECT_EQ(r["text"], "hello world");
    r = c.request("fail", 2000);
    EXPECT_FALSE(r["ok"].get<bool>());
    EXPECT_EQ(r["error"], "it failed");
    r = c.request("quit", 2000);
    EXPECT_TRUE(r["ok"].get<bool>());
    ASSERT_EQ(done.wait_for(2s), std::future_status::ready);
    EXPECT_EQ(done.get(), NetworkServer::SessionEnd::peer_quit);
    EXPECT_EQ(recorder.seen(), (std::vector<std::string>{"echo hello world", "fail", "quit"}));
    // Control is back at the command line: the next peer is refused.
    auto late = NetworkClient::connect_unix(path);
    EXPECT_FALSE(late.hello()["ok"].get<bool>());
}

TEST_F(Network, LostConnectionHandsControlBackAndDropsTheHalfCommand) {
    auto s = make();
    auto done = hand_over_async(*s, nullptr);
    {
        auto c = NetworkClient::connect_unix(path);
        ASSERT_TRUE(c.hello()["ok"].get<bool>());
        EXPECT_TRUE(c.request("echo one", 2000)["ok"].get<bool>());
        c.send_raw("echo half a comm");  // no newline: the peer dies mid-command
    }
    ASSERT_EQ(done.wait_for(2s), std::future_status::ready);
    EXPECT_EQ(done.get(), NetworkServer::SessionEnd::peer_lost);
    EXPECT_EQ(recorder.seen(), (std::vector<std::string>{"echo one"}));
}

TEST_F(Network, PeerThatDisconnectsBeforeReadingItsReply) {
    auto s = make();
    auto done = hand_over_async(*s, nullptr);
    {
        auto c = NetworkClient::connect_unix(path);
        c.send_raw("echo 1\necho 2\necho 3\n");
        ::shutdown(c.fd(), SHUT_RDWR);
    }
    ASSERT_EQ(done.wait_for(2s), std::future_status::ready);
    EXPECT_EQ(done.get(), NetworkServer::SessionEnd::peer_lost);
    // The server survives: a new hand-over works.
    auto again = hand_over_async(*s, nullptr);
    auto c = NetworkClient::connect_unix(path);
    ASSERT_TRUE(c.hello()["ok"].get<bool>());
    EXPECT_EQ(c.request("echo alive", 2000)["text"], "alive");
    c.request("quit", 2000);
    EXPECT_EQ(again.get(), NetworkServer::SessionEnd::peer_quit);
}

TEST_F(Network, MalformedRequestsGetErrorsAndTheSessionGoesOn) {
    auto s = make();
    auto done = hand_over_async(*s, nullptr);
    auto c = NetworkClient::connect_unix(path);
    auto r = c.request("{\"cmd\": ", 2000);
    EXPECT_FALSE(r["ok"].get<bool>());
    EXPECT_EQ(r["error"], "malformed JSON request");
    r = c.request("{\"id\": 4, \"cmd\": 17}", 2000);
    EXPECT_FALSE(r["ok"].get<bool>());
    EXPECT_EQ(r["id"], 4);
    r = c.request("[1,2]", 2000);  // not an object: passed on as a command, executor decides
    r = c.request(std::string("echo a\x01") + "b", 2000);
    EXPECT_FALSE(r["ok"].get<bool>());
    EXPECT_EQ(r["error"], "request contains control characters");
    r = c.request("echo \xff\xfe bytes", 2000);  // invalid UTF-8 must still give valid JSON
    EXPECT_TRUE(r["ok"].get<bool>());
    r = c.request("boom", 2000);
    EXPECT_FALSE(r["ok"].get<bool>());
    EXPECT_EQ(r["error"], "executor blew up");
    r = c.request("{\"id\": \"x1\", \"cmd\": \"echo structured\"}", 2000);
    EXPECT_TRUE(r["ok"].get<bool>());
    EXPECT_EQ(r["id"], "x1");
    EXPECT_EQ(r["text"], "structured");
    r = c.request("network", 2000);
    EXPECT_FALSE(r["ok"].get<bool>());
    EXPECT_EQ(r["error"], "the network already has control");
    c.request("quit", 2000);
    EXPECT_EQ(done.get(), NetworkServer::SessionEnd::peer_quit);
}

TEST_F(Network, OversizedRequestIsRefusedWithoutBeingExecuted) {
    ServerOptions o;
    o.max_request = 64;
    auto s = make(o);
    auto done = hand_over_async(*s, nullptr);
    auto c = NetworkClient::connect_unix(path);
    EXPECT_EQ(c.hello()["max_request"], 64);
    // Sent in pieces so the limit is hit before the newline arrives.
    const std::string big(100000, 'x');
    c.send_raw("echo ");
    c.send_raw(big);
    auto line = c.read_line(2000);
    ASSERT_TRUE(line);
    auto r = json::parse(*line);
    EXPECT_FALSE(r["ok"].get<bool>());
    EXPECT_EQ(r["error"], "request longer than 64 bytes");
    c.send_raw(big + "\n");  // the rest of the oversized line is dropped silently
    EXPECT_EQ(c.request("echo small", 2000)["text"], "small");
    c.request("quit", 2000);
    EXPECT_EQ(done.get(), NetworkServer::SessionEnd::peer_quit);
    for (const auto& cmd : recorder.seen()) EXPECT_LT(cmd.size(), 64u);
}

TEST_F(Network, SecondPeerIsRefusedWhileOneHasControl) {
    auto s = make();
    auto done = hand_over_async(*s, nullptr);
    auto first = NetworkClient::connect_unix(path);
    ASSERT_TRUE(first.hello()["ok"].get<bool>());
    auto second = NetworkClient::connect_unix(path);
    EXPECT_FALSE(second.hello()["ok"].get<bool>());
    EXPECT_NE(second.hello()["error"].get<std::string>().find("another network peer"), std::string::npos);
    EXPECT_EQ(first.request("echo still", 2000)["text"], "still");
    first.request("quit", 2000);
    EXPECT_EQ(done.get(), NetworkServer::SessionEnd::peer_quit);
}

TEST_F(Network, CommandLineTakesControlBack) {
    auto s = make();
    std::atomic<bool> interrupt{false};
    auto done = hand_over_async(*s, &interrupt);
    auto c = NetworkClient::connect_unix(path);
    ASSERT_TRUE(c.hello()["ok"].get<bool>());
    interrupt = true;
    ASSERT_EQ(done.wait_for(2s), std::future_status::ready);
    EXPECT_EQ(done.get(), NetworkServer::SessionEnd::interrupted);
    auto line = c.read_line(2000);
    ASSERT_TRUE(line);
    EXPECT_EQ(json::parse(*line)["error"], "control taken back by the command line");
    EXPECT_THROW(c.read_line(2000), ClientError);

    // Interrupt while nobody is connected.
    std::atomic<bool> again{false};
    auto waiting = hand_over_async(*s, &again);
    again = true;
    ASSERT_EQ(waiting.wait_for(2s), std::future_status::ready);
    EXPECT_EQ(waiting.get(), NetworkServer::SessionEnd::interrupted);
}

TEST_F(Network, ServeForeverAcceptsOneSessionAfterAnotherUntilFinish) {
    auto s = make();
    auto done = std::async(std::launch::async, [&] { return s->serve_forever(nullptr); });
    std::this_thread::sleep_for(50ms);
    {
        auto c = NetworkClient::connect_unix(path);
        ASSERT_TRUE(c.hello()["ok"].get<bool>());
        c.request("quit", 2000);
    }
    {
        auto c = NetworkClient::connect_unix(path);  // dropped without quit
        ASSERT_TRUE(c.hello()["ok"].get<bool>());
    }
    std::this_thread::sleep_for(100ms);
    EXPECT_EQ(done.wait_for(0s), std::future_status::timeout);
    auto c = NetworkClient::connect_unix(path);
    ASSERT_TRUE(c.hello()["ok"].get<bool>());
    EXPECT_TRUE(c.request("finish", 2000)["ok"].get<bool>());
    ASSERT_EQ(done.wait_for(2s), std::future_status::ready);
    EXPECT_EQ(done.get(), NetworkServer::SessionEnd::finish);
    EXPECT_EQ(s->sessions_ended(), 3u);
}

TEST_F(Network, StaleSocketFileIsReplacedButALiveOneIsNot) {
    {
        // A socket file nobody listens on, as a crashed master leaves it.
        const int fd = ::socket(AF_UNIX, SOCK_STREAM, 0);
        sockaddr_un a{};
        a.sun_family = AF_UNIX;
        std::snprintf(a.sun_path, sizeof a.sun_path, "%s", path.c_str());
        ASSERT_EQ(::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a), 0);
        ::close(fd);
    }
    auto s = make();
    ServerOptions o;
    o.subsystem = "testsys";
    o.unix_path = path;
    NetworkServer second(o, [this](std::string_view c) { return recorder(c); });
    try {
        second.start();
        FAIL() << "a second server on a live socket must be refused";
    } catch (const ServerError& e) {
        EXPECT_NE(std::string(e.what()).find("another master"), std::string::npos) << e.what();
    }
    // The refused server did not remove the live socket. Its probe
    // connection reached the live server, which refuses it while it has no
    // offer; let that happen before the offer, or the probe (closing at once)
    // would be the peer that takes and loses control.
    std::this_thread::sleep_for(300ms);
    auto done = hand_over_async(*s, nullptr);
    auto c = NetworkClient::connect_unix(path);
    EXPECT_TRUE(c.hello()["ok"].get<bool>());
    c.request("quit", 2000);
    done.get();
}

TEST_F(Network, TcpNeedsATokenEvenOnLoopback) {
    // Every local user can connect to a loopback port: without a token, any
    // of them would control a master that may run as root.
    for (const char* host : {"0.0.0.0", "127.0.0.1", "::1"}) {
        ServerOptions o;
        o.subsystem = "testsys";
        o.tcp = true;
        o.tcp_host = host;
        NetworkServer s(o, [this](std::string_view c) { return recorder(c); });
        try {
            s.start();
            FAIL() << "TCP on " << host << " without a token must be refused";
        } catch (const ServerError& e) {
            EXPECT_NE(std::string(e.what()).find("needs a token"), std::string::npos) << e.what();
        }
    }
    EXPECT_TRUE(is_loopback_host("127.0.0.1"));
    EXPECT_TRUE(is_loopback_host("127.8.9.1"));
    EXPECT_TRUE(is_loopback_host("::1"));
    EXPECT_TRUE(is_loopback_host("localhost"));
    EXPECT_FALSE(is_loopback_host("0.0.0.0"));
    EXPECT_FALSE(is_loopback_host("10.0.0.1"));
    EXPECT_FALSE(is_loopback_host("::"));
}

TEST_F(Network, TcpTokenIsCheckedBeforeAnyCommand) {
    ServerOptions o;
    o.tcp = true;
    o.token = "s3cret-token";
    auto s = make(o);
    ASSERT_NE(s->tcp_port(), 0);
    std::atomic<bool> interrupt{false};
    auto done = hand_over_async(*s, &interrupt);
    {
        auto c = NetworkClient::connect_tcp("127.0.0.1", s->tcp_port());
        EXPECT_EQ(c.hello()["auth"], "token");
        auto r = c.request("echo sneaky", 2000);
        EXPECT_FALSE(r["ok"].get<bool>());
        EXPECT_EQ(r["error"], "authenticate first: token TOKEN");
        EXPECT_THROW(c.read_line(2000), ClientError);
    }
    {
        auto c = NetworkClient::connect_tcp("127.0.0.1", s->tcp_port());
        auto r = c.request("token s3cret-tokeX", 2000);
        EXPECT_EQ(r["error"], "wrong token");
        EXPECT_THROW(c.read_line(2000), ClientError);
    }
    ASSERT_TRUE(resolves("localhost"));
    // Neither had control, so no session ended: the offer still stands.
    EXPECT_EQ(done.wait_for(300ms), std::future_status::timeout);
    EXPECT_EQ(s->sessions_ended(), 0u);
    auto c = NetworkClient::connect_tcp("localhost", s->tcp_port());
    EXPECT_TRUE(c.request("token s3cret-token", 2000)["ok"].get<bool>());
    EXPECT_EQ(c.request("echo in", 2000)["text"], "in");
    c.request("quit", 2000);
    EXPECT_EQ(done.get(), NetworkServer::SessionEnd::peer_quit);
    EXPECT_EQ(recorder.seen(), (std::vector<std::string>{"echo in", "quit"}));
}

TEST_F(Network, IdleUnauthenticatedPeerBlocksNobodyAndIsClosedAtItsDeadline) {
    ServerOptions o;
    o.tcp = true;
    o.token = "tok";
    o.auth_timeout = 400ms;
    auto s = make(o);
    std::atomic<bool> interrupt{false};
    auto done = hand_over_async(*s, &interrupt);
    auto idle = NetworkClient::connect_tcp("127.0.0.1", s->tcp_port());
    EXPECT_EQ(idle.hello()["auth_timeout_ms"], 400);
    // A later peer that authenticates gets control at once.
    auto c = NetworkClient::connect_tcp("127.0.0.1", s->tcp_port());
    ASSERT_TRUE(c.request("token tok", 2000)["ok"].get<bool>());
    EXPECT_EQ(c.request("echo hi", 2000)["text"], "hi");
    // The idle one is told and closed at its deadline, having run nothing.
    auto line = idle.read_line(3000);
    ASSERT_TRUE(line);
    EXPECT_NE(json::parse(*line)["error"].get<std::string>().find("no token within 400 ms"), std::string::npos)
        << *line;
    EXPECT_THROW(idle.read_line(2000), ClientError);
    c.request("quit", 2000);
    EXPECT_EQ(done.get(), NetworkServer::SessionEnd::peer_quit);
    EXPECT_EQ(recorder.seen(), (std::vector<std::string>{"echo hi", "quit"}));
}

TEST_F(Network, BadFirstLineClosesAnUnauthenticatedPeer) {
    ServerOptions o;
    o.tcp = true;
    o.token = "tok";
    auto s = make(o);
    std::atomic<bool> interrupt{false};
    auto done = hand_over_async(*s, &interrupt);
    {
        auto c = NetworkClient::connect_tcp("127.0.0.1", s->tcp_port());
        auto r = c.request(std::string("token\x01tok"), 2000);
        EXPECT_EQ(r["error"], "request contains control characters");
        EXPECT_THROW(c.read_line(2000), ClientError);
    }
    {
        auto c = NetworkClient::connect_tcp("127.0.0.1", s->tcp_port());
        auto r = c.request("token " + std::string(5000, 'x'), 2000);
        EXPECT_NE(r["error"].get<std::string>().find("longer than 4096"), std::string::npos);
        EXPECT_THROW(c.read_line(2000), ClientError);
    }
    {
        auto c = NetworkClient::connect_tcp("127.0.0.1", s->tcp_port());
        EXPECT_EQ(c.request("{not json", 2000)["error"], "malformed JSON request");
        EXPECT_THROW(c.read_line(2000), ClientError);
    }
    EXPECT_TRUE(recorder.seen().empty());
    interrupt = true;
    EXPECT_EQ(done.get(), NetworkServer::SessionEnd::interrupted);
}

namespace {

// 300 non-blocking connects in a tight loop, as a burst of clients makes
// them (a short listen backlog refused some with EAGAIN), while the server
// offers control: none is refused, and each is answered ('{' of its greeting
// or refusal) within 5 s.
void expect_a_burst_answered(NetworkServer& s, const sockaddr* addr, socklen_t len) {
    std::atomic<bool> interrupt{false};
    auto done = hand_over_async(s, &interrupt);
    std::vector<int> fds;
    int refused = 0;
    for (int i = 0; i < 300; ++i) {
        const int fd = ::socket(addr->sa_family, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
        ASSERT_GE(fd, 0);
        if (::connect(fd, addr, len) != 0 && errno != EINPROGRESS) {
            ++refused;
            ::close(fd);
            continue;
        }
        fds.push_back(fd);
    }
    int answered = 0;
    const auto deadline = std::chrono::steady_clock::now() + 5s;
    for (int fd : fds) {
        const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
        pollfd p{fd, POLLIN, 0};
        char c = 0;
        if (::poll(&p, 1, static_cast<int>(std::max<long>(left.count(), 0))) == 1 && ::read(fd, &c, 1) == 1 && c == '{')
            ++answered;
        ::close(fd);
    }
    EXPECT_EQ(refused, 0);
    EXPECT_EQ(answered, 300);
    interrupt = true;
    done.get();
}

}  // namespace

TEST_F(Network, BurstOf300ConnectionsIsAccepted) {
    // One gets control, the rest a refusal line.
    auto s = make();
    sockaddr_un addr{};
    addr.sun_family = AF_UNIX;
    std::strncpy(addr.sun_path, path.c_str(), sizeof addr.sun_path - 1);
    expect_a_burst_answered(*s, reinterpret_cast<sockaddr*>(&addr), sizeof addr);
}

TEST_F(Network, BurstOf300TcpConnectionsIsGreeted) {
    // Over TCP each waits for its token, so all 300 are pending at once and
    // each gets its greeting.
    ServerOptions o;
    o.tcp = true;
    o.token = "tok";
    auto s = make(o);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(s->tcp_port());
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    expect_a_burst_answered(*s, reinterpret_cast<sockaddr*>(&addr), sizeof addr);
}

TEST_F(Network, StopDisconnectsTheControllingPeer) {
    auto s = make();
    auto done = hand_over_async(*s, nullptr);
    auto c = NetworkClient::connect_unix(path);
    ASSERT_TRUE(c.hello()["ok"].get<bool>());
    s->stop();
    auto line = c.read_line(2000);
    ASSERT_TRUE(line);
    EXPECT_NE(json::parse(*line)["error"].get<std::string>().find("shutting down"), std::string::npos);
    EXPECT_EQ(done.get(), NetworkServer::SessionEnd::stopped);
}

// ------------------------------------------ issue #29.3: no denial without the token

namespace {

/// One connection from `source`: the greeting, then `line`, then its reply
/// (null when the server closed without one).
json ask_from(const char* source, std::uint16_t port, const std::string& line) {
    const int fd = flood_test::connect_from(source, port);
    if (fd < 0) return nullptr;
    ::fcntl(fd, F_SETFL, 0);  // blocking from here, with a receive timeout
    timeval tv{3, 0};
    ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
    const std::string out = line + "\n";
    [[maybe_unused]] auto n = ::send(fd, out.data(), out.size(), MSG_NOSIGNAL);
    std::string in;
    char c = 0;
    int lines = 0;
    std::string reply;
    while (lines < 2 && ::recv(fd, &c, 1, 0) == 1) {
        if (c != '\n') {
            (lines == 1 ? reply : in) += c;
            continue;
        }
        ++lines;
    }
    ::close(fd);
    return lines == 2 ? json::parse(reply) : json(nullptr);
}

// Stops the server when the test leaves, so serve_forever() returns even
// when an assertion ended the test early.
struct StopOnExit {
    NetworkServer& server;
    ~StopOnExit() { server.stop(); }
};

bool can_bind(const char* source) {
    const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    sockaddr_in a{};
    a.sin_family = AF_INET;
    ::inet_pton(AF_INET, source, &a.sin_addr);
    const bool ok = ::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) == 0;
    ::close(fd);
    return ok;
}

/// The operator at 127.0.0.1: connect, token, one command, quit; timed
/// from the connect to the command's reply (control held and used).
flood_test::Attempt operator_over_tcp(std::uint16_t port) {
    const auto start = std::chrono::steady_clock::now();
    flood_test::Attempt a;
    try {
        auto c = NetworkClient::connect_tcp("127.0.0.1", port);
        const json t = c.request("token tok", 3000);
        const json r = c.request("echo in control", 3000);
        a.got_control = t["ok"].get<bool>() && r.value("text", "") == "in control";
        if (!a.got_control) a.detail = t.dump() + " " + r.dump();
        a.took = std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::steady_clock::now() - start);
        c.request("quit", 3000);
    } catch (const std::exception& e) {
        a.detail = e.what();
        a.took = std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::steady_clock::now() - start);
    }
    return a;
}

}  // namespace

// Two threads from 127.0.0.2 connect every 2 ms each for 10 s, hold up to
// 1000 connections, and send wrong tokens on a third of them (before the
// fix: the 512 global slots filled and the operator was refused). The
// operator at 127.0.0.1 connects 20 times: every time it gets control within
// 1 s; the owner's Unix socket gets in as well.
TEST_F(Network, ATokenlessFloodFromAnotherAddressNeverKeepsTheOperatorOut) {
    if (!can_bind("127.0.0.2")) GTEST_SKIP() << "cannot bind 127.0.0.2 (no 127/8 on lo here)";
    flood_test::raise_fd_limit();
    ServerOptions o;
    o.tcp = true;
    o.token = "tok";
    o.unix_path = path;
    auto s = make(o);
    std::atomic<bool> interrupt{false};
    auto serving = std::async(std::launch::async, [&] { return s->serve_forever(&interrupt); });
    const StopOnExit stop_first{*s};  // a failed assertion must not wait for serve_forever
    flood_test::StallDetector stalls;
    flood_test::Flood flood(s->tcp_port(), "token guess\n");
    std::this_thread::sleep_for(1s);  // the flood is at full strength before the operator comes
    auto note = [](const std::string& what) { std::printf("[ stall ] %s\n", what.c_str()); };
    const auto tcp = flood_test::timed_attempts(20, 400ms, 1000ms, stalls, [&] { return operator_over_tcp(s->tcp_port()); }, note);
    const auto local = flood_test::timed_attempts(3, 100ms, 1000ms, stalls, [&] {
        const auto start = std::chrono::steady_clock::now();
        flood_test::Attempt a;
        try {
            auto c = NetworkClient::connect_unix(path);
            const json t = c.request("token tok", 3000);
            a.got_control = t["ok"].get<bool>();
            a.detail = t.dump();
            c.request("quit", 3000);
        } catch (const std::exception& e) {
            a.detail = e.what();
        }
        a.took = std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::steady_clock::now() - start);
        return a;
    }, note);
    const std::uint64_t flooded = flood.connections();
    flood.stop();
    flood_test::expect_each_in_control(tcp, 1000ms, flooded);
    for (const auto& a : local) EXPECT_TRUE(a.got_control && a.took <= 1000ms) << a.took.count() << " ms " << a.detail;
    EXPECT_GT(flooded, 1000u) << "the flood was not a flood";
    interrupt = true;
    serving.get();
}

// A blocking loopback connection with a receive timeout, its hello read.
int greeted_tcp(std::uint16_t port) {
    const int fd = flood_test::connect_from("127.0.0.1", port);
    if (fd < 0) return -1;
    ::fcntl(fd, F_SETFL, 0);
    timeval tv{3, 0};
    ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
    char c = 0;
    while (::recv(fd, &c, 1, 0) == 1)
        if (c == '\n') return fd;
    ::close(fd);
    return -1;
}

json line_from(int fd) {
    std::string line;
    char c = 0;
    while (::recv(fd, &c, 1, 0) == 1 && c != '\n') line += c;
    return json::parse(line, nullptr, false);
}

// Two peers waiting to authenticate send their tokens at the same instant, so
// that both are read in one poll round: the first one given control there
// left its place among the waiting ones empty until the round's end, and the
// second was looked up through it (a null pointer: the flood test crashed the
// server 2 times in 8 under ASan). Each time one gets control and the other is
// told who has it.
TEST_F(Network, TwoPeersAuthenticatingInOneRoundAreBothAnswered) {
    ServerOptions o;
    o.tcp = true;
    o.token = "tok";
    o.unix_path = path;
    auto s = make(o);
    std::atomic<bool> interrupt{false};
    auto serving = std::async(std::launch::async, [&] { return s->serve_forever(&interrupt); });
    const StopOnExit stop_first{*s};
    // Once serve_forever offers control it stays offered between sessions:
    // wait for that (one session), so every round below meets it offered.
    bool offered = false;
    for (auto end = std::chrono::steady_clock::now() + 5s; !offered && std::chrono::steady_clock::now() < end;
         std::this_thread::sleep_for(10ms)) {
        const json r = ask_from("127.0.0.1", s->tcp_port(), "token tok");
        offered = r.is_object() && r.value("ok", false);
    }
    ASSERT_TRUE(offered) << "serve_forever never offered control within 5 s";
    for (int round = 0; round < 50; ++round) {
        const int a = greeted_tcp(s->tcp_port());
        const int b = greeted_tcp(s->tcp_port());
        ASSERT_GE(a, 0);
        ASSERT_GE(b, 0);
        const std::string token = "token tok\n";
        ::send(a, token.data(), token.size(), MSG_NOSIGNAL);
        ::send(b, token.data(), token.size(), MSG_NOSIGNAL);
        const json ra = line_from(a), rb = line_from(b);
        ASSERT_TRUE(ra.is_object() && rb.is_object()) << "round " << round << ": " << ra.dump() << " / " << rb.dump();
        const bool a_has_it = ra.value("ok", false);
        EXPECT_NE(a_has_it, rb.value("ok", false)) << "round " << round << ": " << ra.dump() << " / " << rb.dump();
        const json& refused = a_has_it ? rb : ra;
        EXPECT_NE(refused.value("error", "").find("another network peer has control"), std::string::npos)
            << refused.dump();
        const std::string quit = "quit\n";
        ::send(a_has_it ? a : b, quit.data(), quit.size(), MSG_NOSIGNAL);
        line_from(a_has_it ? a : b);
        ::close(a);
        ::close(b);
    }
    interrupt = true;
    serving.get();
}

// Wrong tokens slow their address down: the n-th wrong one makes it wait
// 100 ms * 2^(n-1) (said in the reply), and a token sent sooner is not judged
// at all, the right one included; another address is not slowed, and the
// right token once judged starts its address afresh.
TEST_F(Network, WrongTokensAreThrottledPerAddressWithBackOff) {
    if (!can_bind("127.0.0.2")) GTEST_SKIP() << "cannot bind 127.0.0.2 (no 127/8 on lo here)";
    ServerOptions o;
    o.tcp = true;
    o.token = "tok";
    auto s = make(o);
    std::atomic<bool> interrupt{false};
    auto serving = std::async(std::launch::async, [&] { return s->serve_forever(&interrupt); });
    const StopOnExit stop_first{*s};
    for (long expected : {100, 200, 400, 800}) {
        const json r = ask_from("127.0.0.2", s->tcp_port(), "token guess");
        ASSERT_EQ(r.value("error", ""), "wrong token") << r.dump();
        EXPECT_EQ(r["data"]["retry_after_ms"], expected);
        if (expected < 800) std::this_thread::sleep_for(std::chrono::milliseconds(expected + 20));
    }
    // Within the 800 ms: refused unjudged, the right token too.
    const json early = ask_from("127.0.0.2", s->tcp_port(), "token tok");
    EXPECT_NE(early.value("error", "").find("too many wrong tokens from 127.0.0.2: retry after"), std::string::npos)
        << early.dump();
    // The operator's address is not slowed by 127.0.0.2's guesses.
    EXPECT_TRUE(ask_from("127.0.0.1", s->tcp_port(), "token tok")["ok"].get<bool>());
    std::this_thread::sleep_for(850ms);
    EXPECT_TRUE(ask_from("127.0.0.2", s->tcp_port(), "token tok")["ok"].get<bool>());
    EXPECT_EQ(ask_from("127.0.0.2", s->tcp_port(), "token guess")["data"]["retry_after_ms"], 100);

    // A guesser as fast as it can go for 1.5 s: judged about once per back-off.
    std::this_thread::sleep_for(120ms);
    int judged = 0, refused = 0;
    const auto end = std::chrono::steady_clock::now() + 1500ms;
    while (std::chrono::steady_clock::now() < end) {
        const std::string e = ask_from("127.0.0.2", s->tcp_port(), "token guess").value("error", "");
        judged += e == "wrong token";
        refused += e.find("retry after") != std::string::npos;
    }
    std::printf("[ guess ] 1.5 s from one address: %d tokens judged, %d refused unjudged\n", judged, refused);
    // 100+200+400+800 ms > 1.5 s: at most 4 judged (5 with a slow start).
    EXPECT_LE(judged, 5);
    EXPECT_GT(refused, judged);
    interrupt = true;
    serving.get();
}

namespace {

// As nobody, in a forked child: listens on `path` and greets every peer as a
// master would, until `hold` is closed. Writes a byte to `ready` once listening.
int squat_socket_as_nobody(const std::string& path, int ready, int hold) {
    if (!chimera::test::become_nobody({})) return 10;
    const int fd = ::socket(AF_UNIX, SOCK_STREAM, 0);
    sockaddr_un addr{};
    addr.sun_family = AF_UNIX;
    std::strncpy(addr.sun_path, path.c_str(), sizeof addr.sun_path - 1);
    if (::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0 || ::listen(fd, 4) != 0) return 11;
    if (::write(ready, "x", 1) != 1) return 12;
    for (;;) {
        pollfd p[2] = {{fd, POLLIN, 0}, {hold, POLLIN, 0}};
        if (::poll(p, 2, -1) < 0 || p[1].revents != 0) return 0;
        const int peer = ::accept(fd, nullptr, nullptr);
        const char hello[] = "{\"ok\":true,\"cmd\":\"hello\",\"subsystem\":\"testsys\",\"auth\":\"none\"}\n";
        // The client refuses this peer on its credentials alone and may have
        // closed already: no SIGPIPE (it killed the squatter once), EPIPE is fine.
        if (peer >= 0 && ::send(peer, hello, sizeof hello - 1, MSG_NOSIGNAL) < 0 && errno != EPIPE &&
            errno != ECONNRESET)
            return 13;
        if (peer >= 0) ::close(peer);
    }
}

}  // namespace

// Any local user may listen first on a socket path root's client will use
// (issue #29.5): the client refuses such a peer before it reads a word,
// naming the path, the peer's user and pid, and what to do.
TEST(SquattedSocket, AClientRefusesAPeerOfAnotherUserNamingIt) {
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    TempDir dir;
    ASSERT_EQ(::chmod(dir.path().c_str(), 0777), 0);  // nobody may create its socket there
    const std::string path = dir.path() + "/squatted.sock";
    int ready[2], hold[2];
    ASSERT_EQ(::pipe(ready), 0);
    ASSERT_EQ(::pipe(hold), 0);
    const pid_t squatter = chimera::test::fork_child([&] {
        ::close(ready[0]);
        ::close(hold[1]);
        return squat_socket_as_nobody(path, ready[1], hold[0]);
    });
    ::close(ready[1]);
    ::close(hold[0]);
    char byte = 0;
    ASSERT_EQ(::read(ready[0], &byte, 1), 1);
    const passwd* nobody = ::getpwnam("nobody");
    try {
        NetworkClient::connect_unix(path);
        ADD_FAILURE() << "talked to nobody's socket";
    } catch (const UntrustedMasterError& e) {
        EXPECT_EQ(std::string(e.what()),
                  "socket " + path + " is served by nobody's (uid " + std::to_string(nobody->pw_uid) +
                      ") process, pid " + std::to_string(squatter) +
                      ", not by this user's or root's: not trusted; stop that process or remove the socket (sudo rm " +
                      path + "), then start the master again");
    }
    ::close(hold[1]);
    ::close(ready[0]);
    EXPECT_EQ(chimera::test::wait_child(squatter), 0);
}
