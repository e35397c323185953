#include "client.hpp"

#include "peer_user.hpp"

#include <netdb.h>
#include <poll.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>
#include <memory>

namespace chimera::cli {

NetworkClient::NetworkClient(int fd) : fd_(fd) {}

NetworkClient::NetworkClient(NetworkClient&& other) noexcept
    : fd_(other.fd_), buffer_(std::move(other.buffer_)), hello_(std::move(other.hello_)) {
    other.fd_ = -1;
}

NetworkClient& NetworkClient::operator=(NetworkClient&& other) noexcept {
    if (this != &other) {
        close();
        fd_ = other.fd_;
        other.fd_ = -1;
        buffer_ = std::move(other.buffer_);
        hello_ = std::move(other.hello_);
    }
    return *this;
}

NetworkClient::~NetworkClient() { close(); }

void NetworkClient::close() {
    if (fd_ >= 0) ::close(fd_);
    fd_ = -1;
}

namespace {

nlohmann::json read_hello(NetworkClient& c) {
    const auto line = c.read_line(5000);
    if (!line) throw ClientError("no greeting from the server");
    auto j = nlohmann::json::parse(*line, nullptr, false);
    if (j.is_discarded() || !j.is_object()) throw ClientError("server greeting is not JSON");
    return j;
}

}  // namespace

NetworkClient NetworkClient::connect_unix(const std::string& path) {
    sockaddr_un addr{};
    addr.sun_family = AF_UNIX;
    if (path.size() >= sizeof addr.sun_path) throw ClientError("socket path too long: " + path);
    std::memcpy(addr.sun_path, path.c_str(), path.size() + 1);
    const int fd = ::socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
    if (fd < 0) throw ClientError(std::string("socket: ") + std::strerror(errno));
    if (::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
        const int err = errno;
        ::close(fd);
        throw ClientError("cannot connect to " + path + ": " + std::strerror(err));
    }
    NetworkClient c(fd);  // closes fd on a throw
    if (const std::string why = untrusted_master(fd, path); !why.empty()) throw UntrustedMasterError(why);
    c.hello_ = read_hello(c);
    return c;
}

NetworkClient NetworkClient::connect_tcp(const std::string& host, std::uint16_t port) {
    addrinfo hints{};
    hints.ai_family = AF_UNSPEC;
    hints.ai_socktype = SOCK_STREAM;
    addrinfo* res = nullptr;
    const std::string service = std::to_string(port);
    if (const int gai = ::getaddrinfo(host.c_str(), service.c_str(), &hints, &res); gai != 0) {
        throw ClientError(host + ": " + ::gai_strerror(gai));
    }
    std::unique_ptr<addrinfo, decltype(&::freeaddrinfo)> guard(res, ::freeaddrinfo);
    int err = ECONNREFUSED;
    for (addrinfo* ai = res; ai != nullptr; ai = ai->ai_next) {
        const int fd = ::socket(ai->ai_family, ai->ai_socktype | SOCK_CLOEXEC, ai->ai_protocol);
        if (fd < 0) continue;
        if (::connect(fd, ai->ai_addr, ai->ai_addrlen) == 0) {
            NetworkClient c(fd);
            c.hello_ = read_hello(c);
            return c;
        }
        err = errno;
        ::close(fd);
    }
    throw ClientError("cannot connect to " + host + ":" + service + ": " + std::strerror(err));
}

void NetworkClient::send_raw(std::string_view bytes) {
    std::size_t done = 0;
    while (done < bytes.size()) {
        const ssize_t n = ::send(fd_, bytes.data() + done, bytes.size() - done, MSG_NOSIGNAL);
        if (n < 0 && errno == EINTR) continue;
        if (n <= 0) throw ClientError(std::string("connection lost: ") + std::strerror(errno));
        done += static_cast<std::size_t>(n);
    }
}

std::optional<std::string> NetworkClient::read_line(int timeout_ms) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
    for (;;) {
        if (const auto nl = buffer_.find('\n'); nl != std::string::npos) {
            std::string line = buffer_.substr(0, nl);
            buffer_.erase(0, nl + 1);
            return line;
        }
        int wait = -1;
        if (timeout_ms >= 0) {
            const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
                deadline - std::chrono::steady_clock::now());
            if (left.count() <= 0) return std::nullopt;
            wait = static_cast<int>(left.count());
        }
        pollfd p{fd_, POLLIN, 0};
        const int rc = ::poll(&p, 1, wait);
        if (rc < 0 && errno == EINTR) continue;
        if (rc == 0) return std::nullopt;
        char buf[4096];
        const ssize_t n = ::recv(fd_, buf, sizeof buf, 0);
        if (n < 0 && errno == EINTR) continue;
        if (n <= 0) throw ClientError("connection closed by the server");
        buffer_.append(buf, static_cast<std::size_t>(n));
    }
}

nlohmann::json NetworkClient::request(std::string_view command, int timeout_ms) {
    std::string line(command);
    line += '\n';
    send_raw(line);
    const auto reply = read_line(timeout_ms);
    if (!reply) throw ClientError("no reply within " + std::to_string(timeout_ms) + " ms");
    auto j = nlohmann::json::parse(*reply, nullptr, false);
    if (j.is_discarded()) throw ClientError("reply is not JSON: " + *reply);
    return j;
}

}  // namespace chimera::cli
