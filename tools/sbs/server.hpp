// tools/sbs/server.hpp — the external subsystem interface (thesis §4.4.2): the
// commands of the prompt over a socket, one command per line in, one JSON reply
// per line out (protocol in docs/cli.md).
//
// Control is exclusive, as in the thesis: either the command line has it or a
// single network peer does. hand_over() passes it to the network (the prompt's
// `network` command) and returns it when the peer quits or the connection is
// lost; serve_forever() is the prompt-less master (sbsNetwork alone). Peers that
// connect while control is elsewhere get one error line and are closed.
//
// Everything runs in one ordinary (SCHED_OTHER) thread: nothing here touches the
// real-time tasks except through the commands themselves.
#pragma once

#include "reply.hpp"
#include "token_back_off.hpp"

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

namespace chimera::cli {

/// A socket could not be set up (bind, permissions, address); what() is one line.
class ServerError : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

struct ServerOptions {
    std::string subsystem;          ///< named in the greeting
    std::string unix_path;          ///< Unix socket to create (mode 0600); empty: none
    bool tcp = false;               ///< listen on TCP as well
    std::string tcp_host = "127.0.0.1";  ///< loopback unless an address is given
    std::uint16_t tcp_port = 0;     ///< 0: the kernel picks (see tcp_port())
    std::string token;              ///< required first line `token T` when non-empty;
                                    ///< mandatory whenever TCP is on: loopback is
                                    ///< reachable by every local user
    std::chrono::milliseconds auth_timeout{2000};  ///< a peer that has not sent the
                                    ///< token by then is closed (it never had control);
                                    ///< short, so an idle connection's slot comes back soon
    std::size_t max_request = 4096; ///< longest accepted request line, in bytes
    bool serve = false;             ///< the network has control from start(): no peer is
                                    ///< refused before serve_forever() is called
};

/// The default Unix socket of a subsystem: $XDG_RUNTIME_DIR/chimera/<name>.sock,
/// else /tmp/chimera-<uid>/<name>.sock. The directory is created mode 0700.
std::string default_socket_path(std::string_view subsystem);

/// One request line as a peer sent it (without its newline), parsed: a pure
/// function of the line, so a fuzzer can call it. A plain line is the command;
/// `{"cmd": "...", "id": ...}` is the structured form (the id is echoed).
struct Request {
    enum class Kind { keep_alive, command, malformed };
    Kind kind = Kind::keep_alive;  ///< keep_alive: a blank line, answered by nothing
    std::string command;           ///< Kind::command: free of control characters but tab
    std::string error;             ///< Kind::malformed: why, for the error reply
    nlohmann::json id;             ///< the structured form's "id" (null otherwise)
};
Request parse_request(std::string_view line);

/// A token comparison whose time does not depend on where the first
/// difference is, so the token cannot be guessed byte by byte.
bool same_token(std::string_view a, std::string_view b);

/// True when `host` is a numeric loopback address (127.0.0.0/8, ::1) or "localhost".
bool is_loopback_host(std::string_view host);

class NetworkServer {
public:
    /// Runs one command for the controlling peer. Called only from the server
    /// thread, and only while the network has control.
    using Executor = std::function<Reply(std::string_view command)>;

    enum class SessionEnd {
        peer_quit,    ///< the peer sent quit
        peer_lost,    ///< the connection was closed or broke
        interrupted,  ///< the command line took control back
        finish,       ///< the peer asked for the subsystem to finish
        stopped,      ///< the server was stopped
    };

    NetworkServer(ServerOptions options, Executor executor);
    ~NetworkServer();
    NetworkServer(const NetworkServer&) = delete;
    NetworkServer& operator=(const NetworkServer&) = delete;

    /// Binds the sockets and starts the server thread. Throws ServerError.
    void start();
    /// Closes every socket, removes the Unix socket file, joins the thread.
    void stop();

    const std::string& unix_path() const noexcept { return options_.unix_path; }
    /// The bound TCP port (the real one when 0 was asked for), 0 without TCP.
    std::uint16_t tcp_port() const noexcept { return bound_port_; }

    /// Gives control to the network until one session ends, or until
    /// `*interrupt` becomes true while waiting (the operator pressed Ctrl-C).
    /// `offered` (if given) runs once the network may take control, e.g. to
    /// tell the operator so without racing a quick peer.
    SessionEnd hand_over(const std::atomic<bool>* interrupt, const std::function<void()>& offered = {});
    /// Gives control to the network for good; returns when a peer asks for
    /// finish, when `*interrupt` becomes true, or when the server stops.
    SessionEnd serve_forever(const std::atomic<bool>* interrupt);

    /// Another front end of the same master (the web console, tools/sbs/web.hpp)
    /// takes the one control slot as a peer would, under the same rules:
    /// refused while another peer has control or while the command line has
    /// it. Returns "" when granted, else the refusal (the words a peer gets).
    std::string acquire_control();
    /// Ends that session: control returns as when a peer's session ends.
    void release_control(SessionEnd why);
    /// True while the command line wants control back (Ctrl-C after
    /// `network`): the holder is to release it with SessionEnd::interrupted.
    bool control_wanted_back() const;

    /// Wrong tokens per source address: the web console judges its pages'
    /// tokens with this one too, so an address guessing the one token has one
    /// back-off whichever door it knocks at.
    TokenBackOff& token_back_off() noexcept { return back_off_; }

    /// Number of sessions that have ended so far (for tests and the prompt).
    std::uint64_t sessions_ended() const;

private:
    struct Peer;
    void run();
    void accept_from(int listen_fd);
    void admit(int fd, bool needs_token, std::string source);
    void make_room_for(const std::string& source);
    void evict_oldest_from(const std::string& source, const std::string& why);
    bool take_control(Peer& peer);   // false: refused, the peer is to be closed
    std::string claim_locked();      // mutex_ held: "" and the session is on, or the refusal
    void close_peer(Peer& peer, SessionEnd why);
    void expire_pending();
    bool handle_input(Peer& peer);   // false: the peer is to be closed
    bool handle_line(Peer& peer, std::string_view line);
    bool authenticate(Peer& peer, std::string_view command, const nlohmann::json& id);
    bool send_line(int fd, const std::string& line);
    void end_session(SessionEnd why);
    void wake();
    SessionEnd wait_session(const std::atomic<bool>* interrupt, bool forever, const std::function<void()>& offered);

    void open_unix_socket();     // bound and listening under a staging name
    void publish_unix_socket();  // then linked to its path

    ServerOptions options_;
    Executor executor_;
    int unix_fd_ = -1;
    std::string unix_staging_path_;  // where the socket is bound until it listens
    bool unix_published_ = false;    // at options_.unix_path: stop() removes it
    int tcp_fd_ = -1;
    int wake_fd_ = -1;
    std::uint16_t bound_port_ = 0;
    std::thread thread_;
    std::atomic<bool> stopping_{false};
    std::unique_ptr<Peer> peer_;    // the controlling peer; touched by the server thread only
    // Connected peers that have not sent the token yet: they have no control
    // and are closed at their deadline, so an idle connection blocks nobody.
    std::vector<std::unique_ptr<Peer>> pending_;
    // Wrong tokens per TCP source address, to slow a guesser down (issue #29.3).
    TokenBackOff back_off_;

    mutable std::mutex mutex_;
    std::condition_variable changed_;
    bool offered_ = false;          // the network may take control
    bool persistent_ = false;       // serve_forever: offered again after each session
    bool session_active_ = false;
    bool take_back_ = false;        // the command line wants control back now
    std::uint64_t sessions_ended_ = 0;
    SessionEnd last_end_ = SessionEnd::peer_lost;
};

}  // namespace chimera::cli
