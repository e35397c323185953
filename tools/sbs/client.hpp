// tools/sbs/client.hpp — the peer side of the network interface: what
// `sbs FILE.sbs` uses to attach to a master that already runs the subsystem,
// and what a remote program can copy.
#pragma once

#include <nlohmann/json.hpp>

#include <cstdint>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>

namespace chimera::cli {

class ClientError : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

/// The process listening on the socket runs as neither this user nor root
/// (issue #29.5): what() names it and what to do.
class UntrustedMasterError : public ClientError {
public:
    using ClientError::ClientError;
};

class NetworkClient {
public:
    /// Connects and reads the greeting line. Throws ClientError when nothing
    /// listens there (the caller may then start the subsystem itself), and
    /// UntrustedMasterError, before reading a word, when another user does.
    static NetworkClient connect_unix(const std::string& path);
    static NetworkClient connect_tcp(const std::string& host, std::uint16_t port);

    NetworkClient(NetworkClient&& other) noexcept;
    NetworkClient& operator=(NetworkClient&& other) noexcept;
    NetworkClient(const NetworkClient&) = delete;
    NetworkClient& operator=(const NetworkClient&) = delete;
    ~NetworkClient();

    /// The server's greeting: {"ok":true,"cmd":"hello",...} or a refusal {"ok":false,...}.
    const nlohmann::json& hello() const noexcept { return hello_; }

    /// Sends one command line and waits for its reply (timeout in ms, -1 forever).
    /// Throws ClientError when the connection is lost or the reply is not JSON.
    nlohmann::json request(std::string_view command, int timeout_ms = -1);

    /// Raw access for tests and odd peers.
    void send_raw(std::string_view bytes);
    /// One line without its newline; nullopt on timeout; throws when closed.
    std::optional<std::string> read_line(int timeout_ms);

    int fd() const noexcept { return fd_; }
    void close();

private:
    explicit NetworkClient(int fd);
    int fd_ = -1;
    std::string buffer_;
    nlohmann::json hello_;
};

}  // namespace chimera::cli
