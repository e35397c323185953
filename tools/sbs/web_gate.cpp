#include "web_gate.hpp"

#include "server.hpp"

#include <arpa/inet.h>
#include <net/if.h>
#include <fcntl.h>
#include <netdb.h>
#include <netinet/in.h>
#include <poll.h>
#include <pthread.h>
#include <sched.h>
#include <sys/eventfd.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <map>
#include <mutex>
#include <utility>
#include <vector>

namespace chimera::cli {

namespace {

constexpr std::size_t kMaxHead = 16384;  // a request head longer than this is refused
constexpr std::size_t kBuffer = 65536;   // per direction: reading stops while full

std::string peer_address(int fd) {
    sockaddr_storage ss{};
    socklen_t len = sizeof ss;
    if (::getpeername(fd, reinterpret_cast<sockaddr*>(&ss), &len) != 0) return "?";
    char text[INET6_ADDRSTRLEN] = {};
    const void* addr = ss.ss_family == AF_INET6 ? static_cast<const void*>(&reinterpret_cast<sockaddr_in6&>(ss).sin6_addr)
                                                : static_cast<const void*>(&reinterpret_cast<sockaddr_in&>(ss).sin_addr);
    return ::inet_ntop(ss.ss_family, addr, text, sizeof text) ? text : "?";
}

// A short plain-text HTTP reply, then the connection is closed: the refused
// see why instead of hanging.
void refuse(int fd, const char* status, const std::string& why) {
    const std::string body = why + "\n";
    const std::string out = std::string("HTTP/1.1 ") + status +
                            "\r\nContent-Type: text/plain; charset=utf-8\r\nConnection: close\r\nContent-Length: " +
                            std::to_string(body.size()) + "\r\n\r\n" + body;
    [[maybe_unused]] auto n = ::send(fd, out.data(), out.size(), MSG_NOSIGNAL | MSG_DONTWAIT);
}

// Brings up the loopback device of the calling thread's network namespace
// (down in a new one). Returns 0 or an errno.
int loopback_up() {
    const int fd = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
    if (fd < 0) return errno;
    ifreq ifr{};
    std::strncpy(ifr.ifr_name, "lo", IFNAMSIZ - 1);
    int rc = ::ioctl(fd, SIOCGIFFLAGS, &ifr);
    if (rc == 0) {
        ifr.ifr_flags = static_cast<short>(ifr.ifr_flags | IFF_UP);
        rc = ::ioctl(fd, SIOCSIFFLAGS, &ifr);
    }
    const int err = rc == 0 ? 0 : errno;
    ::close(fd);
    return err;
}

int connect_backend(std::uint16_t port) {
    const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    sockaddr_in to{};
    to.sin_family = AF_INET;
    to.sin_port = htons(port);
    to.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    // Blocking: civetweb's own listener on loopback answers at once.
    if (fd < 0 || ::connect(fd, reinterpret_cast<sockaddr*>(&to), sizeof to) != 0) {
        if (fd >= 0) ::close(fd);
        return -1;
    }
    ::fcntl(fd, F_SETFL, O_NONBLOCK);
    return fd;
}

std::uint16_t local_port(int fd) {
    sockaddr_in self{};
    socklen_t len = sizeof self;
    return ::getsockname(fd, reinterpret_cast<sockaddr*>(&self), &len) == 0 ? ntohs(self.sin_port) : 0;
}

}  // namespace

struct Conn {
    int client = -1;
    int backend = -1;  // >= 0 once the head has come and is relayed
    std::uint16_t relay_port = 0;  // backend's local port, while relayed
    std::string source;
    std::string head;  // what came before the head ended
    std::chrono::steady_clock::time_point deadline;
    std::string to_client, to_backend;
    bool client_eof = false, backend_eof = false;
    bool relaying() const { return backend >= 0; }
};

struct WebGate::Impl {
    GateOptions o;
    int listen_fd = -1;
    int wake_fd = -1;
    std::thread thread;
    std::atomic<bool> stopping{false};
    std::vector<std::unique_ptr<Conn>> conns;  // in arrival order
    // Relayed connections' sources by relay port, for civetweb's threads.
    mutable std::mutex sources_mu;
    std::map<std::uint16_t, std::string> sources;

    void run();
    void accept_all();
    void make_room_for(const std::string& source);
    bool evict_oldest_waiting(const std::string& source);
    void on_head_data(Conn& c);
    void promote(Conn& c);
    void pump(Conn& c, short client_events, short backend_events);
    void close(Conn& c);
    std::size_t count(const std::string& source, bool relayed) const;
};

std::size_t WebGate::Impl::count(const std::string& source, bool relayed) const {
    return static_cast<std::size_t>(std::count_if(conns.begin(), conns.end(), [&](const auto& c) {
        return c->client >= 0 && c->source == source && c->relaying() == relayed;
    }));
}

void WebGate::Impl::close(Conn& c) {
    if (c.relay_port != 0) {
        std::lock_guard lock(sources_mu);
        sources.erase(c.relay_port);
        c.relay_port = 0;
    }
    if (c.client >= 0) ::close(c.client);
    if (c.backend >= 0) ::close(c.backend);
    c.client = c.backend = -1;
}

bool WebGate::Impl::evict_oldest_waiting(const std::string& source) {
    for (auto& c : conns) {
        if (c->client < 0 || c->relaying() || c->source != source) continue;
        refuse(c->client, "503 Service Unavailable", "closed: a newer connection from " + source + " is waiting");
        close(*c);
        return true;
    }
    return false;
}

// As the TCP server does: the newcomer is never refused for want of a slot
// while someone who has not sent a request yet can give way.
void WebGate::Impl::make_room_for(const std::string& source) {
    if (count(source, false) >= o.waiting_per_source) {
        evict_oldest_waiting(source);
        return;
    }
    std::map<std::string, std::size_t> waiting;
    std::size_t open = 0;
    for (const auto& c : conns) {
        if (c->client < 0) continue;
        ++open;
        if (!c->relaying()) ++waiting[c->source];
    }
    if (open < o.max_connections || waiting.empty()) return;
    const auto busiest = std::max_element(waiting.begin(), waiting.end(),
                                          [](const auto& a, const auto& b) { return a.second < b.second; });
    evict_oldest_waiting(busiest->first);
}

void WebGate::Impl::accept_all() {
    for (;;) {
        const int fd = ::accept4(listen_fd, nullptr, nullptr, SOCK_CLOEXEC | SOCK_NONBLOCK);
        if (fd < 0) {
            if (errno == EINTR || errno == ECONNABORTED) continue;
            return;
        }
        auto c = std::make_unique<Conn>();
        c->client = fd;
        c->source = peer_address(fd);
        c->deadline = std::chrono::steady_clock::now() + o.head_timeout;
        make_room_for(c->source);
        std::erase_if(conns, [](const auto& x) { return x->client < 0; });
        if (conns.size() >= o.max_connections) {  // every one of them is relayed
            refuse(fd, "503 Service Unavailable", "too many connections: try again later");
            ::close(fd);
            continue;
        }
        conns.push_back(std::move(c));
    }
}

void WebGate::Impl::on_head_data(Conn& c) {
    char buf[4096];
    const ssize_t got = ::recv(c.client, buf, sizeof buf, 0);
    if (got == 0 || (got < 0 && errno != EAGAIN && errno != EINTR)) return close(c);
    if (got < 0) return;
    c.head.append(buf, static_cast<std::size_t>(got));
    if (c.head.find("\r\n\r\n") != std::string::npos) return promote(c);
    if (c.head.size() > kMaxHead) {
        refuse(c.client, "431 Request Header Fields Too Large", "request head longer than 16384 bytes");
        close(c);
    }
}

// The head is complete: the connection may now hold a civetweb worker, if its
// address does not hold too many already.
void WebGate::Impl::promote(Conn& c) {
    if (count(c.source, true) >= o.relayed_per_source) {
        refuse(c.client, "503 Service Unavailable",
               "too many connections from " + c.source + " in use (" + std::to_string(o.relayed_per_source) +
                   "): close a page and reload");
        return close(c);
    }
    c.backend = connect_backend(o.backend_port);
    if (c.backend < 0) {
        refuse(c.client, "503 Service Unavailable", "the web console is not answering");
        return close(c);
    }
    c.relay_port = local_port(c.backend);  // before civetweb can see the head
    if (c.relay_port != 0) {
        std::lock_guard lock(sources_mu);
        sources[c.relay_port] = c.source;
    }
    c.to_backend = std::move(c.head);
    c.head.clear();
}

namespace {

// Moves what `from` has into `into` (up to kBuffer); false when `from` ended.
bool read_into(int from, std::string& into) {
    char buf[16384];
    const std::size_t room = std::min(sizeof buf, kBuffer - std::min(kBuffer, into.size()));
    if (room == 0) return true;
    const ssize_t got = ::recv(from, buf, room, 0);
    if (got > 0) into.append(buf, static_cast<std::size_t>(got));
    return got != 0 && !(got < 0 && errno != EAGAIN && errno != EINTR);
}

// Sends what it can of `out`; false on a broken connection.
bool write_from(int to, std::string& out) {
    if (out.empty()) return true;
    const ssize_t sent = ::send(to, out.data(), out.size(), MSG_NOSIGNAL | MSG_DONTWAIT);
    if (sent > 0) out.erase(0, static_cast<std::size_t>(sent));
    return sent >= 0 || errno == EAGAIN || errno == EINTR;
}

}  // namespace

void WebGate::Impl::pump(Conn& c, short client_events, short backend_events) {
    bool ok = true;
    if (client_events & (POLLIN | POLLHUP | POLLERR)) c.client_eof = !read_into(c.client, c.to_backend);
    if (backend_events & (POLLIN | POLLHUP | POLLERR)) c.backend_eof = !read_into(c.backend, c.to_client);
    ok = write_from(c.backend, c.to_backend) && write_from(c.client, c.to_client);
    // Either side gone and what it sent delivered: both are closed (no
    // keep-alive here, and civetweb closes after each reply anyway).
    if (!ok || (c.client_eof && c.to_backend.empty()) || (c.backend_eof && c.to_client.empty())) close(c);
}

void WebGate::Impl::run() {
    sched_param sp{};
    ::pthread_setschedparam(::pthread_self(), SCHED_OTHER, &sp);  // never competes with real-time tasks
    // Into civetweb's namespace: the backend connections are made there. The
    // public socket was made in this one, and accepts here still.
    if (o.backend_netns >= 0 && ::setns(o.backend_netns, CLONE_NEWNET) != 0)
        std::fprintf(stderr, "web console: cannot join civetweb's network namespace: %s\n", std::strerror(errno));
    std::vector<pollfd> fds;
    std::vector<Conn*> owner;  // fds[i]'s connection, from index 2
    while (!stopping) {
        fds.assign({{wake_fd, POLLIN, 0}, {listen_fd, POLLIN, 0}});
        owner.assign(2, nullptr);
        for (auto& c : conns) {
            const short in_client = c->to_backend.size() < kBuffer && !c->client_eof ? POLLIN : 0;
            fds.push_back({c->client, static_cast<short>(in_client | (c->to_client.empty() ? 0 : POLLOUT)), 0});
            owner.push_back(c.get());
            if (!c->relaying()) continue;
            const short in_backend = c->to_client.size() < kBuffer && !c->backend_eof ? POLLIN : 0;
            fds.push_back({c->backend, static_cast<short>(in_backend | (c->to_backend.empty() ? 0 : POLLOUT)), 0});
            owner.push_back(c.get());
        }
        if (::poll(fds.data(), fds.size(), 100) < 0 && errno != EINTR) break;
        for (std::size_t i = 2; i < fds.size(); ++i) {
            Conn& c = *owner[i];
            if (c.client < 0 || fds[i].fd != c.client) continue;  // handled with its pair
            if (!c.relaying()) {
                if (fds[i].revents != 0) on_head_data(c);
                continue;
            }
            const bool has_pair = i + 1 < fds.size() && owner[i + 1] == &c;
            pump(c, fds[i].revents, has_pair ? fds[i + 1].revents : 0);
        }
        const auto now = std::chrono::steady_clock::now();
        for (auto& c : conns) {
            if (c->client < 0 || c->relaying() || now < c->deadline) continue;
            refuse(c->client, "408 Request Timeout",
                   "no request within " + std::to_string(o.head_timeout.count()) + " ms");
            close(*c);
        }
        std::erase_if(conns, [](const auto& c) { return c->client < 0; });
        if (fds[1].revents != 0) accept_all();
    }
    for (auto& c : conns) close(*c);
    conns.clear();
}

PrivateNetwork PrivateNetwork::enter() {
    PrivateNetwork net;
    net.home_fd_ = ::open("/proc/thread-self/ns/net", O_RDONLY | O_CLOEXEC);
    if (net.home_fd_ < 0) {
        net.why_not_ = std::string("cannot open /proc/thread-self/ns/net: ") + std::strerror(errno);
        return net;
    }
    if (::unshare(CLONE_NEWNET) != 0) {
        net.why_not_ = std::string("cannot make a network namespace: ") + std::strerror(errno);
        return net;
    }
    const int err = loopback_up();
    net.fd_ = ::open("/proc/thread-self/ns/net", O_RDONLY | O_CLOEXEC);
    if (err != 0 || net.fd_ < 0) {
        net.why_not_ = std::string("cannot bring up its loopback: ") + std::strerror(err != 0 ? err : errno);
        net.leave();
    }
    return net;
}

PrivateNetwork::PrivateNetwork(PrivateNetwork&& other) noexcept
    : fd_(std::exchange(other.fd_, -1)), home_fd_(std::exchange(other.home_fd_, -1)),
      why_not_(std::move(other.why_not_)) {}

PrivateNetwork::~PrivateNetwork() {
    if (fd_ >= 0) ::close(fd_);
    if (home_fd_ >= 0) ::close(home_fd_);
}

void PrivateNetwork::leave() {
    if (home_fd_ < 0) return;
    if (::setns(home_fd_, CLONE_NEWNET) != 0)
        throw ServerError(std::string("web console: cannot leave civetweb's network namespace: ") +
                          std::strerror(errno));
    ::close(home_fd_);
    home_fd_ = -1;
    if (!why_not_.empty() && fd_ >= 0) {
        ::close(fd_);
        fd_ = -1;
    }
}

WebGate::WebGate(GateOptions options) : impl_(std::make_unique<Impl>()) {
    Impl& im = *impl_;
    im.o = std::move(options);
    addrinfo hints{};
    hints.ai_socktype = SOCK_STREAM;
    hints.ai_flags = AI_NUMERICHOST | AI_PASSIVE;
    addrinfo* res = nullptr;
    const std::string port = std::to_string(im.o.port);
    if (::getaddrinfo(im.o.host.c_str(), port.c_str(), &hints, &res) != 0 || res == nullptr)
        throw ServerError("--http: " + im.o.host + " is not a numeric address");
    im.listen_fd = ::socket(res->ai_family, SOCK_STREAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
    const int one = 1;
    ::setsockopt(im.listen_fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    const bool bound = im.listen_fd >= 0 && ::bind(im.listen_fd, res->ai_addr, res->ai_addrlen) == 0 &&
                       ::listen(im.listen_fd, 1024) == 0;
    const int err = errno;
    ::freeaddrinfo(res);
    if (!bound) {
        if (im.listen_fd >= 0) ::close(im.listen_fd);
        throw ServerError("--http: cannot listen on " + im.o.host + ":" + port + ": " + std::strerror(err));
    }
    sockaddr_storage ss{};
    socklen_t len = sizeof ss;
    ::getsockname(im.listen_fd, reinterpret_cast<sockaddr*>(&ss), &len);
    port_ = ntohs(ss.ss_family == AF_INET6 ? reinterpret_cast<sockaddr_in6&>(ss).sin6_port
                                           : reinterpret_cast<sockaddr_in&>(ss).sin_port);
    im.wake_fd = ::eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK);
}

WebGate::~WebGate() {
    stop();
    if (impl_->listen_fd >= 0) ::close(impl_->listen_fd);
    if (impl_->wake_fd >= 0) ::close(impl_->wake_fd);
}

std::string WebGate::source_of(std::uint16_t relay_port) const {
    std::lock_guard lock(impl_->sources_mu);
    const auto it = impl_->sources.find(relay_port);
    return it == impl_->sources.end() ? std::string() : it->second;
}

void WebGate::start() {
    impl_->thread = std::thread([this] { impl_->run(); });
}

void WebGate::stop() {
    if (!impl_->thread.joinable()) return;
    impl_->stopping = true;
    const std::uint64_t one = 1;
    [[maybe_unused]] auto n = ::write(impl_->wake_fd, &one, sizeof one);
    impl_->thread.join();
}

}  // namespace chimera::cli
