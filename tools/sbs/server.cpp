#include "server.hpp"

#include "peer_user.hpp"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netdb.h>
#include <netinet/in.h>
#include <poll.h>
#include <pthread.h>
#include <sched.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <optional>

namespace chimera::cli {

namespace {

std::string errno_text(int err) { return std::strerror(err); }

void set_cloexec_nonblock(int fd) {
    ::fcntl(fd, F_SETFD, FD_CLOEXEC);
    ::fcntl(fd, F_SETFL, ::fcntl(fd, F_GETFL) | O_NONBLOCK);
}

std::string error_line(std::string_view cmd, std::string message) {
    return to_json_line(Reply::failure(std::string(cmd), std::move(message)));
}

}  // namespace

namespace {

// "nobody's (uid 65534), mode 0755, a directory"
std::string describe_entry(const struct stat& st) {
    char mode[8];
    std::snprintf(mode, sizeof mode, "%04o", static_cast<unsigned>(st.st_mode & 07777));
    const char* kind = S_ISDIR(st.st_mode) ? "a directory" : S_ISLNK(st.st_mode) ? "a symbolic link" : "not a directory";
    return user_name(st.st_uid) + "'s (uid " +
           std::to_string(st.st_uid) + "), mode " + mode + ", " + kind;
}

// True when `dir` is a directory (not a symlink) of this user's with mode
// 0700: checked by fstat of the directory opened without following a link.
bool trusted_dir(const std::string& dir) {
    const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_NOFOLLOW | O_CLOEXEC);
    if (fd < 0) return false;
    struct stat st {};
    const bool ok = ::fstat(fd, &st) == 0 && st.st_uid == ::geteuid() && (st.st_mode & 07777) == 0700;
    ::close(fd);
    return ok;
}

// Moves the untrusted `dir` out of the way (root, or its owner, may): a link
// or file is removed, a directory renamed to DIR.squatted-PID with its
// contents untouched (they are its owner's). Says so on stderr.
void move_aside(const std::string& dir, const std::string& what) {
    struct stat st {};
    if (::lstat(dir.c_str(), &st) != 0) return;  // gone meanwhile: mkdir again
    if (S_ISDIR(st.st_mode)) {
        const std::string aside = dir + ".squatted-" + std::to_string(::getpid());
        if (::rename(dir.c_str(), aside.c_str()) != 0)
            throw ServerError("socket directory " + dir + " is " + what + ": cannot move it aside: " + errno_text(errno));
        std::fprintf(stderr, "sbs: socket directory %s was %s: moved aside to %s, using a new one\n", dir.c_str(),
                     what.c_str(), aside.c_str());
    } else {
        if (::unlink(dir.c_str()) != 0)
            throw ServerError("socket directory " + dir + " is " + what + ": cannot remove it: " + errno_text(errno));
        std::fprintf(stderr, "sbs: socket directory %s was %s: removed, using a new one\n", dir.c_str(), what.c_str());
    }
}

}  // namespace

// Any local user may create /tmp/chimera-UID first (issue #29.5): the folder
// is used only when it is this user's, mode 0700 and no symlink; otherwise
// root (or the entry's owner) moves it aside and makes a new one, and anyone
// else is told whose it is and what to do.
std::string default_socket_path(std::string_view subsystem) {
    std::string dir;
    if (const char* xdg = std::getenv("XDG_RUNTIME_DIR"); xdg != nullptr && *xdg == '/') {
        dir = std::string(xdg) + "/chimera";
    } else {
        dir = "/tmp/chimera-" + std::to_string(::getuid());
    }
    for (int attempt = 0;; ++attempt) {
        if (attempt > 2) throw ServerError("socket directory " + dir + " keeps changing: try again");
        if (::mkdir(dir.c_str(), 0700) != 0 && errno != EEXIST) {
            throw ServerError("cannot create socket directory " + dir + ": " + errno_text(errno));
        }
        if (trusted_dir(dir)) break;
        struct stat st {};
        if (::lstat(dir.c_str(), &st) != 0) continue;  // removed meanwhile: make it
        const std::string what = describe_entry(st);
        const bool may_move = ::geteuid() == 0 || st.st_uid == ::geteuid();
        if (!may_move || attempt > 0) {
            // Another user's folder could hold a socket planted by them: refuse rather than talk to it.
            throw ServerError("socket directory " + dir + " must belong to this user with mode 0700, and it is " +
                              what + ": ask its owner or root to remove it (sudo rm -r " + dir +
                              "), or set XDG_RUNTIME_DIR to a folder of your own");
        }
        move_aside(dir, what);
    }
    return dir + "/" + std::string(subsystem) + ".sock";
}

bool same_token(std::string_view a, std::string_view b) {
    unsigned char diff = a.size() == b.size() ? 0 : 1;
    const std::size_t n = a.size() > b.size() ? a.size() : b.size();
    for (std::size_t i = 0; i < n; ++i) {
        const unsigned char x = i < a.size() ? static_cast<unsigned char>(a[i]) : 0;
        const unsigned char y = i < b.size() ? static_cast<unsigned char>(b[i]) : 0;
        diff = static_cast<unsigned char>(diff | (x ^ y));
    }
    return diff == 0;
}

bool is_loopback_host(std::string_view host) {
    if (host == "localhost") return true;
    const std::string h(host);
    in_addr v4{};
    if (::inet_pton(AF_INET, h.c_str(), &v4) == 1) {
        return (ntohl(v4.s_addr) >> 24) == 127;
    }
    in6_addr v6{};
    if (::inet_pton(AF_INET6, h.c_str(), &v6) == 1) return IN6_IS_ADDR_LOOPBACK(&v6);
    return false;
}

struct NetworkServer::Peer {
    int fd = -1;
    std::string buffer;
    bool discarding = false;   // inside an oversized line: drop until newline
    bool authenticated = false;
    bool controlling = false;  // this peer's session holds control
    SessionEnd end = SessionEnd::peer_lost;  // why, once handle_input() said to close
    std::chrono::steady_clock::time_point deadline;  // to authenticate by
    std::string source;        // the TCP peer's address; empty for the Unix socket
};

namespace {

// TCP connections waiting for their token at once, from all sources: a flood
// of idle connections cannot run the server out of file descriptors. At the
// bound the oldest one of the busiest source makes room (make_room_for).
constexpr std::size_t kMaxPending = 512;
// ... and from one source address: a flooder churns its own slots only, so
// another address always finds one (issue #29.3).
constexpr std::size_t kMaxPendingPerSource = 4;

// "127.0.0.2" for a TCP peer. Never "": that is the owner's Unix socket,
// which no TCP bound applies to.
std::string peer_address(int fd) {
    sockaddr_storage ss{};
    socklen_t len = sizeof ss;
    if (::getpeername(fd, reinterpret_cast<sockaddr*>(&ss), &len) != 0) return "(unknown address)";
    char text[INET6_ADDRSTRLEN] = {};
    const void* addr = ss.ss_family == AF_INET6 ? static_cast<const void*>(&reinterpret_cast<sockaddr_in6&>(ss).sin6_addr)
                                                : static_cast<const void*>(&reinterpret_cast<sockaddr_in&>(ss).sin_addr);
    if (::inet_ntop(ss.ss_family, addr, text, sizeof text) == nullptr) return "(unknown address)";
    return text;
}

}  // namespace

NetworkServer::NetworkServer(ServerOptions options, Executor executor)
    : options_(std::move(options)), executor_(std::move(executor)) {}

NetworkServer::~NetworkServer() { stop(); }

namespace {

sockaddr_un unix_address(const std::string& path) {
    sockaddr_un addr{};
    addr.sun_family = AF_UNIX;
    std::memcpy(addr.sun_path, path.c_str(), path.size() + 1);
    return addr;
}

}  // namespace

// The socket is bound and listening under a name of this process's own
// (PATH.PID) and appears at PATH only then (publish_unix_socket): a peer that
// finds the file can always connect — at bind() the file exists while a
// connect is still refused until listen().
void NetworkServer::open_unix_socket() {
    const std::string& path = options_.unix_path;
    unix_staging_path_ = path + "." + std::to_string(::getpid());
    if (unix_staging_path_.size() >= sizeof(sockaddr_un::sun_path)) {
        stop();
        throw ServerError("socket path too long: " + path);
    }
    sockaddr_un addr = unix_address(path);
    struct stat st {};
    if (::lstat(path.c_str(), &st) == 0) {
        if (!S_ISSOCK(st.st_mode)) {
            stop();
            throw ServerError(path + " exists and is not a socket");
        }
        // A socket file left by a master that died: remove it, but never
        // one somebody still answers on.
        const int probe = ::socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
        const bool alive = probe >= 0 && ::connect(probe, reinterpret_cast<sockaddr*>(&addr), sizeof addr) == 0;
        if (probe >= 0) ::close(probe);
        if (alive) {
            stop();
            throw ServerError("another master already serves " + path);
        }
        ::unlink(path.c_str());
    }
    unix_fd_ = ::socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
    if (unix_fd_ < 0) {
        const int err = errno;
        stop();
        throw ServerError("socket: " + errno_text(err));
    }
    ::unlink(unix_staging_path_.c_str());  // left by a killed master of this pid
    addr = unix_address(unix_staging_path_);
    const mode_t old = ::umask(0177);  // owner read/write only from the start
    const int rc = ::bind(unix_fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr);
    const int err = errno;
    ::umask(old);
    if (rc != 0) {
        stop();
        throw ServerError("cannot bind " + unix_staging_path_ + ": " + errno_text(err));
    }
    if (::listen(unix_fd_, SOMAXCONN) != 0) {
        const int listen_err = errno;
        stop();
        throw ServerError("listen: " + errno_text(listen_err));
    }
    set_cloexec_nonblock(unix_fd_);
}

// A hard link, not rename(): it fails where another master published PATH
// since open_unix_socket() looked, instead of replacing its socket.
void NetworkServer::publish_unix_socket() {
    const int rc = ::link(unix_staging_path_.c_str(), options_.unix_path.c_str());
    const int err = errno;
    if (rc != 0) {
        stop();
        throw ServerError(err == EEXIST ? "another master already serves " + options_.unix_path
                                        : "cannot create " + options_.unix_path + ": " + errno_text(err));
    }
    ::unlink(unix_staging_path_.c_str());
    unix_published_ = true;
}

void NetworkServer::start() {
    if (options_.tcp && !options_.token.empty() && options_.token.find_first_of(" \t\r\n") != std::string::npos) {
        throw ServerError("the token must not contain white space");
    }
    if (options_.tcp && options_.token.empty()) {
        // Loopback is no protection: every local user can connect to it, and
        // control of a root master means loading code as root.
        throw ServerError("TCP on " + options_.tcp_host +
                          " needs a token (--token or --token-file): every local user can reach a TCP port, "
                          "loopback included; the owner-only Unix socket (--listen) needs none");
    }
    wake_fd_ = ::eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK);
    if (wake_fd_ < 0) throw ServerError("eventfd: " + errno_text(errno));

    if (!options_.unix_path.empty()) open_unix_socket();
    if (options_.tcp) {
        addrinfo hints{};
        hints.ai_family = AF_UNSPEC;
        hints.ai_socktype = SOCK_STREAM;
        hints.ai_flags = AI_PASSIVE | AI_NUMERICSERV;
        addrinfo* res = nullptr;
        const std::string port = std::to_string(options_.tcp_port);
        const int gai = ::getaddrinfo(options_.tcp_host.c_str(), port.c_str(), &hints, &res);
        if (gai != 0) {
            stop();
            throw ServerError("TCP address " + options_.tcp_host + ": " + ::gai_strerror(gai));
        }
        std::unique_ptr<addrinfo, decltype(&::freeaddrinfo)> guard(res, ::freeaddrinfo);
        int err = 0;
        for (addrinfo* ai = res; ai != nullptr; ai = ai->ai_next) {
            const int fd = ::socket(ai->ai_family, ai->ai_socktype | SOCK_CLOEXEC, ai->ai_protocol);
            if (fd < 0) {
                err = errno;
                continue;
            }
            const int one = 1;
            ::setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
            if (::bind(fd, ai->ai_addr, ai->ai_addrlen) == 0 && ::listen(fd, SOMAXCONN) == 0) {
                tcp_fd_ = fd;
                break;
            }
            err = errno;
            ::close(fd);
        }
        if (tcp_fd_ < 0) {
            stop();
            throw ServerError("cannot listen on " + options_.tcp_host + ":" + port + ": " +
                              errno_text(err));
        }
        sockaddr_storage ss{};
        socklen_t len = sizeof ss;
        ::getsockname(tcp_fd_, reinterpret_cast<sockaddr*>(&ss), &len);
        bound_port_ = ss.ss_family == AF_INET6
                          ? ntohs(reinterpret_cast<sockaddr_in6*>(&ss)->sin6_port)
                          : ntohs(reinterpret_cast<sockaddr_in*>(&ss)->sin_port);
        set_cloexec_nonblock(tcp_fd_);
    }
    if (!options_.unix_path.empty()) publish_unix_socket();
    stopping_ = false;
    if (options_.serve) {
        std::lock_guard lock(mutex_);
        offered_ = true;
        persistent_ = true;
    }
    thread_ = std::thread([this] { run(); });
}

void NetworkServer::stop() {
    stopping_ = true;
    wake();
    if (thread_.joinable()) thread_.join();
    if (unix_fd_ >= 0) {
        ::close(unix_fd_);
        unix_fd_ = -1;
        // Only a path this server published: until then it may be another master's.
        ::unlink(unix_published_ ? options_.unix_path.c_str() : unix_staging_path_.c_str());
        unix_published_ = false;
    }
    if (tcp_fd_ >= 0) {
        ::close(tcp_fd_);
        tcp_fd_ = -1;
    }
    if (wake_fd_ >= 0) {
        ::close(wake_fd_);
        wake_fd_ = -1;
    }
    std::lock_guard lock(mutex_);
    changed_.notify_all();
}

void NetworkServer::wake() {
    if (wake_fd_ >= 0) {
        const std::uint64_t one = 1;
        [[maybe_unused]] const auto n = ::write(wake_fd_, &one, sizeof one);
    }
}

std::uint64_t NetworkServer::sessions_ended() const {
    std::lock_guard lock(mutex_);
    return sessions_ended_;
}

bool NetworkServer::send_line(int fd, const std::string& line) {
    std::string out = line;
    out += '\n';
    std::size_t done = 0;
    // The peer socket is non-blocking; a peer that stops reading gets two
    // seconds before it is dropped, so it cannot wedge the server.
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(2);
    while (done < out.size()) {
        const ssize_t n = ::send(fd, out.data() + done, out.size() - done, MSG_NOSIGNAL);
        if (n > 0) {
            done += static_cast<std::size_t>(n);
            continue;
        }
        if (n < 0 && errno == EINTR) continue;
        if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
            const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
                deadline - std::chrono::steady_clock::now());
            if (left.count() <= 0) return false;
            pollfd p{fd, POLLOUT, 0};
            ::poll(&p, 1, static_cast<int>(left.count()));
            continue;
        }
        return false;
    }
    return true;
}

void NetworkServer::end_session(SessionEnd why) {
    std::lock_guard lock(mutex_);
    session_active_ = false;
    last_end_ = why;
    ++sessions_ended_;
    offered_ = persistent_ && why != SessionEnd::finish && why != SessionEnd::interrupted;
    take_back_ = false;
    changed_.notify_all();
}

NetworkServer::SessionEnd NetworkServer::hand_over(const std::atomic<bool>* interrupt,
                                                   const std::function<void()>& offered) {
    return wait_session(interrupt, false, offered);
}

NetworkServer::SessionEnd NetworkServer::serve_forever(const std::atomic<bool>* interrupt) {
    return wait_session(interrupt, true, {});
}

NetworkServer::SessionEnd NetworkServer::wait_session(const std::atomic<bool>* interrupt, bool forever,
                                                      const std::function<void()>& offered) {
    std::unique_lock lock(mutex_);
    // With options_.serve the network had control since start(): sessions
    // that ended before this call count (a peer may already have sent finish).
    const std::uint64_t start = options_.serve && forever ? 0 : sessions_ended_;
    offered_ = true;
    persistent_ = forever;
    if (offered) {
        lock.unlock();
        offered();
        lock.lock();
    }
    for (;;) {
        if (stopping_) {
            offered_ = false;
            return SessionEnd::stopped;
        }
        if (sessions_ended_ != start) {
            if (!forever || last_end_ == SessionEnd::finish) {
                offered_ = false;
                persistent_ = false;
                return last_end_;
            }
        }
        if (interrupt != nullptr && interrupt->load()) {
            offered_ = false;
            persistent_ = false;
            if (!session_active_) return SessionEnd::interrupted;
            // Take control back from a connected peer: the server thread
            // tells it and closes the connection between two commands.
            take_back_ = true;
            lock.unlock();
            wake();
            lock.lock();
            changed_.wait(lock, [&] { return !session_active_ || stopping_; });
            return SessionEnd::interrupted;
        }
        changed_.wait_for(lock, std::chrono::milliseconds(50));
    }
}

void NetworkServer::accept_from(int listen_fd) {
    // Drain the queue: a burst of connections must not wait one poll round each.
    for (;;) {
        const int fd = ::accept4(listen_fd, nullptr, nullptr, SOCK_CLOEXEC | SOCK_NONBLOCK);
        if (fd < 0) {
            if (errno == EINTR || errno == ECONNABORTED) continue;
            return;
        }
        if (listen_fd == unix_fd_) {
            // File permissions keep other users out; root gets past them, so the
            // peer's credentials are checked as well.
            ucred cred{};
            if (!peer_credentials(fd, cred) || !trusted_user(cred.uid)) {
                send_line(fd, error_line("hello", "permission denied"));
                ::close(fd);
                continue;
            }
        }
        const bool had_control = peer_ != nullptr;
        // The Unix socket is the owner's alone: it is never counted against
        // the TCP bounds, so no flood can keep the owner out.
        admit(fd, !options_.token.empty(), listen_fd == unix_fd_ ? std::string() : peer_address(fd));
        // Once a peer got control, the rest wait for the next round, after its
        // input: a peer that closed and at once reconnected must find its old
        // session over, not be refused by it.
        if (!had_control && peer_) return;
    }
}

void NetworkServer::admit(int fd, bool needs_token, std::string source) {
    if (needs_token && !source.empty()) make_room_for(source);
    auto peer = std::make_unique<Peer>();
    peer->fd = fd;
    peer->source = std::move(source);
    peer->authenticated = !needs_token;
    peer->deadline = std::chrono::steady_clock::now() + options_.auth_timeout;
    // A peer that must authenticate first gets control only once it has: it
    // waits among the pending ones and blocks nobody meanwhile.
    if (peer->authenticated && !take_control(*peer)) {
        ::close(fd);
        return;
    }
    nlohmann::json hello = {{"ok", true},
                            {"cmd", "hello"},
                            {"protocol", 1},
                            {"subsystem", options_.subsystem},
                            {"pid", ::getpid()},
                            {"auth", needs_token ? "token" : "none"},
                            {"max_request", options_.max_request}};
    if (needs_token) hello["auth_timeout_ms"] = options_.auth_timeout.count();
    if (!send_line(fd, hello.dump())) {
        close_peer(*peer, SessionEnd::peer_lost);
        return;
    }
    if (peer->controlling) {
        peer_ = std::move(peer);  // the session runs in run() from here on
    } else {
        pending_.push_back(std::move(peer));
    }
}

// A newcomer is never refused for want of a slot: the oldest waiting
// connection of its own address gives way (a flooder evicts only itself), and
// at the global bound the oldest of the address with the most waiting does.
void NetworkServer::make_room_for(const std::string& source) {
    std::map<std::string, std::size_t> waiting;
    std::size_t tcp_waiting = 0;
    for (const auto& p : pending_) {
        if (p->fd < 0 || p->source.empty()) continue;
        ++waiting[p->source];
        ++tcp_waiting;
    }
    if (waiting[source] >= kMaxPendingPerSource) {
        evict_oldest_from(source, "a newer connection from " + source + " is waiting to authenticate (at most " +
                                      std::to_string(kMaxPendingPerSource) + " per address)");
        return;
    }
    if (tcp_waiting < kMaxPending) return;
    const auto busiest = std::max_element(waiting.begin(), waiting.end(),
                                          [](const auto& a, const auto& b) { return a.second < b.second; });
    evict_oldest_from(busiest->first, "too many connections waiting to authenticate; " + busiest->first +
                                          " has the most");
}

void NetworkServer::evict_oldest_from(const std::string& source, const std::string& why) {
    // pending_ is in arrival order: the first match is the oldest.
    const auto it = std::find_if(pending_.begin(), pending_.end(),
                                 [&](const auto& p) { return p->fd >= 0 && p->source == source; });
    if (it == pending_.end()) return;
    send_line((*it)->fd, error_line("token", "connection closed: " + why));
    close_peer(**it, SessionEnd::peer_lost);
    pending_.erase(it);
}

std::string NetworkServer::claim_locked() {
    if (session_active_) return "another network peer has control of subsystem " + options_.subsystem;
    if (!offered_)
        return "the command line of subsystem " + options_.subsystem + " has control (pid " +
               std::to_string(::getpid()) + "); type 'network' at its prompt to pass control";
    session_active_ = true;
    return {};
}

bool NetworkServer::take_control(Peer& peer) {
    std::unique_lock lock(mutex_);
    const std::string refusal = claim_locked();
    if (!refusal.empty()) {
        lock.unlock();
        send_line(peer.fd, error_line("hello", refusal));
        return false;
    }
    peer.controlling = true;
    return true;
}

std::string NetworkServer::acquire_control() {
    std::lock_guard lock(mutex_);
    return claim_locked();
}

void NetworkServer::release_control(SessionEnd why) { end_session(why); }

bool NetworkServer::control_wanted_back() const {
    std::lock_guard lock(mutex_);
    return take_back_;
}

void NetworkServer::close_peer(Peer& peer, SessionEnd why) {
    ::close(peer.fd);
    peer.fd = -1;
    if (peer.controlling) {
        peer.controlling = false;
        end_session(why);
    }
}

void NetworkServer::expire_pending() {
    const auto now = std::chrono::steady_clock::now();
    for (auto& p : pending_) {
        if (p->fd >= 0 && now >= p->deadline) {
            send_line(p->fd, error_line("token", "no token within " +
                                                     std::to_string(options_.auth_timeout.count()) +
                                                     " ms: connection closed"));
            close_peer(*p, SessionEnd::peer_lost);
        }
    }
    std::erase_if(pending_, [](const auto& p) { return p->fd < 0; });
}

void NetworkServer::run() {
    // The server is an ordinary thread whatever the process was started with:
    // a flood of requests must never compete with the real-time tasks.
    sched_param sp{};
    sp.sched_priority = 0;
    ::pthread_setschedparam(::pthread_self(), SCHED_OTHER, &sp);

    std::vector<pollfd> fds;
    while (!stopping_) {
        fds.clear();
        fds.push_back({wake_fd_, POLLIN, 0});
        if (unix_fd_ >= 0) fds.push_back({unix_fd_, POLLIN, 0});
        if (tcp_fd_ >= 0) fds.push_back({tcp_fd_, POLLIN, 0});
        const std::size_t listeners = fds.size();
        if (peer_) fds.push_back({peer_->fd, POLLIN, 0});
        for (const auto& p : pending_) fds.push_back({p->fd, POLLIN, 0});
        const int rc = ::poll(fds.data(), fds.size(), 200);
        if (rc < 0 && errno != EINTR) break;
        if (stopping_) break;
        std::uint64_t drained = 0;
        [[maybe_unused]] const auto r = ::read(wake_fd_, &drained, sizeof drained);

        bool take_back = false;
        {
            std::lock_guard lock(mutex_);
            take_back = take_back_;
        }
        if (peer_ && take_back) {
            send_line(peer_->fd, error_line("", "control taken back by the command line"));
            close_peer(*peer_, SessionEnd::interrupted);
            peer_.reset();
            continue;
        }
        expire_pending();
        if (rc <= 0) continue;
        // Peers first, then new connections (see accept_from).
        for (std::size_t i = listeners; i < fds.size(); ++i) {
            if (fds[i].revents == 0) continue;
            if (peer_ && fds[i].fd == peer_->fd) {
                if (!handle_input(*peer_)) {
                    close_peer(*peer_, peer_->end);
                    peer_.reset();
                }
                continue;
            }
            for (auto& p : pending_) {
                // A peer given control earlier in this round left its place
                // empty (erased below): skip it, do not look through it.
                if (!p || p->fd != fds[i].fd) continue;
                if (!handle_input(*p)) {
                    close_peer(*p, p->end);
                } else if (p->controlling) {
                    peer_ = std::move(p);  // authenticated and given control
                }
                break;
            }
        }
        std::erase_if(pending_, [](const auto& p) { return !p || p->fd < 0; });
        for (std::size_t i = 1; i < listeners; ++i) {
            if (fds[i].revents != 0) accept_from(fds[i].fd);
        }
    }
    for (auto& p : pending_) close_peer(*p, SessionEnd::peer_lost);
    pending_.clear();
    if (peer_) {
        send_line(peer_->fd, error_line("", "subsystem " + options_.subsystem + " is shutting down"));
        close_peer(*peer_, SessionEnd::stopped);
        peer_.reset();
    }
}

bool NetworkServer::handle_input(Peer& peer) {
    char buf[4096];
    for (;;) {
        const ssize_t got = ::recv(peer.fd, buf, sizeof buf, 0);
        if (got == 0 || (got < 0 && errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR)) {
            // Lost connection (possibly in the middle of a request): the
            // unfinished line is dropped and control goes back (§4.4.2).
            peer.end = SessionEnd::peer_lost;
            return false;
        }
        if (got < 0) {
            if (errno == EINTR) continue;
            return true;
        }
        std::string_view chunk(buf, static_cast<std::size_t>(got));
        while (!chunk.empty()) {
            const auto nl = chunk.find('\n');
            const std::string_view part = chunk.substr(0, nl);
            if (peer.discarding) {
                if (nl != std::string_view::npos) peer.discarding = false;
            } else if (peer.buffer.size() + part.size() > options_.max_request) {
                peer.buffer.clear();
                peer.discarding = nl == std::string_view::npos;
                const bool sent = send_line(peer.fd, error_line(peer.authenticated ? "" : "token",
                                                                "request longer than " +
                                                                    std::to_string(options_.max_request) +
                                                                    " bytes"));
                // An unauthenticated peer gets one try per connection.
                if (!sent || !peer.authenticated) {
                    peer.end = SessionEnd::peer_lost;
                    return false;
                }
            } else {
                peer.buffer.append(part);
                if (nl != std::string_view::npos) {
                    std::string line = std::move(peer.buffer);
                    peer.buffer.clear();
                    if (!line.empty() && line.back() == '\r') line.pop_back();
                    if (!handle_line(peer, line)) return false;
                }
            }
            if (nl == std::string_view::npos) break;
            chunk.remove_prefix(nl + 1);
        }
    }
}

Request parse_request(std::string_view line) {
    Request r;
    const std::size_t first = line.find_first_not_of(" \t");
    if (first == std::string_view::npos) return r;  // blank lines are keep-alives
    auto malformed = [&r](std::string why) {
        r.kind = Request::Kind::malformed;
        r.command.clear();
        r.error = std::move(why);
        return r;
    };
    if (line[first] == '{') {
        // The structured form: {"cmd": "status", "id": 7}.
        const auto j = nlohmann::json::parse(line, nullptr, false);
        if (j.is_discarded() || !j.is_object()) return malformed("malformed JSON request");
        if (j.contains("id")) r.id = j["id"];
        if (!j.contains("cmd") || !j["cmd"].is_string()) return malformed("JSON request needs a string member \"cmd\"");
        r.command = j["cmd"].get<std::string>();
    } else {
        r.command.assign(line);
    }
    for (unsigned char c : r.command) {
        if (c < 0x20 && c != '\t') return malformed("request contains control characters");
    }
    r.kind = Request::Kind::command;
    return r;
}

bool NetworkServer::handle_line(Peer& peer, std::string_view line) {
    const Request request = parse_request(line);
    const nlohmann::json& id = request.id;
    const std::string& command = request.command;
    if (request.kind == Request::Kind::keep_alive) return true;
    if (request.kind == Request::Kind::malformed) {
        const bool sent = send_line(peer.fd, to_json_line(Reply::failure("", request.error), id));
        // Before the token, any bad line ends the connection: one try each.
        if (sent && peer.authenticated) return true;
        peer.end = SessionEnd::peer_lost;
        return false;
    }
    if (!peer.authenticated) return authenticate(peer, command, id);
    Reply reply;
    try {
        reply = executor_(command);
    } catch (const std::exception& e) {
        reply = Reply::failure("", e.what());
    }
    if (reply.action == Action::network) {
        reply = Reply::failure(reply.command, "the network already has control");
    }
    // Bounded for TCP peers; the owner's Unix socket (no source) gets it all.
    const std::string out = peer.source.empty() ? to_json_line(reply, id) : to_client_line(reply, id, command);
    if (!send_line(peer.fd, out)) {
        peer.end = SessionEnd::peer_lost;
        return false;
    }
    if (reply.action == Action::quit) {
        peer.end = SessionEnd::peer_quit;
        return false;
    }
    if (reply.action == Action::finish) {
        peer.end = SessionEnd::finish;
        return false;
    }
    return true;
}

bool NetworkServer::authenticate(Peer& peer, std::string_view command, const nlohmann::json& id) {
    // The first request must carry the token; anything else ends the
    // connection so a guesser gets one try per connection.
    if (std::optional<Reply> refused = back_off_.judge(peer.source, command, options_.token)) {
        send_line(peer.fd, to_json_line(*refused, id));
        peer.end = SessionEnd::peer_lost;
        return false;
    }
    peer.authenticated = true;
    if (!take_control(peer)) {
        peer.end = SessionEnd::peer_lost;
        return false;
    }
    Reply ok;
    ok.command = "token";
    ok.text = "authenticated";
    if (!send_line(peer.fd, to_json_line(ok, id))) {
        peer.end = SessionEnd::peer_lost;
        return false;
    }
    return true;
}

}  // namespace chimera::cli
