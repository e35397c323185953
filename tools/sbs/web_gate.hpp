// tools/sbs/web_gate.hpp — the front door of the web console (issue #29.3).
//
// civetweb gives every connection a worker thread from the moment it is
// accepted, so idle or half-sent connections without the token could hold all
// workers and keep the operator's page out. The gate listens on the public
// address instead, in one poll() thread: a connection reaches civetweb (on a
// private loopback port) only once its request head has fully arrived, within
// a short deadline; at most a few per source address wait at once (a newer
// one evicts that address's oldest), and a source may hold only a few
// civetweb workers at once. Bytes are relayed unchanged both ways after that.
// Where the process may (root), civetweb's port is in a network namespace of
// its own that only the gate's thread joins, so no local user can dial it and
// go round the gate (PrivateNetwork).
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <string>
#include <thread>

namespace chimera::cli {

struct GateOptions {
    std::string host;                        ///< public address to listen on
    std::uint16_t port = 0;                  ///< 0: the kernel picks
    std::uint16_t backend_port = 0;          ///< civetweb, on 127.0.0.1
    int backend_netns = -1;                  ///< civetweb's network namespace (PrivateNetwork::fd()); -1: this one
    std::chrono::milliseconds head_timeout{2000};  ///< to send the request head
    std::size_t waiting_per_source = 4;      ///< connections still sending their head
    std::size_t relayed_per_source = 8;      ///< civetweb workers one address may hold
    std::size_t max_connections = 512;       ///< all connections, all sources
};

/// A network namespace of its own with only loopback up, which the calling
/// thread is in from enter() to leave(): the sockets it makes meanwhile (and
/// the threads it starts) live there, out of every other process's reach.
/// Making one needs CAP_SYS_ADMIN: without it made() is false, why_not()
/// says why, and the thread stays where it was.
class PrivateNetwork {
public:
    static PrivateNetwork enter();
    PrivateNetwork(PrivateNetwork&& other) noexcept;
    PrivateNetwork& operator=(PrivateNetwork&&) = delete;
    ~PrivateNetwork();
    /// Back to the namespace the thread was in; throws ServerError if it cannot.
    void leave();
    bool made() const noexcept { return fd_ >= 0; }
    const std::string& why_not() const noexcept { return why_not_; }
    /// The namespace, for another thread's setns(); -1 where none was made.
    int fd() const noexcept { return fd_; }

private:
    PrivateNetwork() = default;
    int fd_ = -1, home_fd_ = -1;
    std::string why_not_;
};

class WebGate {
public:
    explicit WebGate(GateOptions options);  ///< binds and listens; throws ServerError
    ~WebGate();
    WebGate(const WebGate&) = delete;
    WebGate& operator=(const WebGate&) = delete;

    void start();
    void stop();
    std::uint16_t port() const noexcept { return port_; }
    /// The public address of the client whose request the gate relays from
    /// its local port `relay_port` (the remote port civetweb sees), while it
    /// relays it; "" otherwise. civetweb sees every page come from 127.0.0.1,
    /// so this is how the console bounds a page's address (wrong tokens).
    std::string source_of(std::uint16_t relay_port) const;

    struct Impl;

private:
    std::unique_ptr<Impl> impl_;
    std::uint16_t port_ = 0;
};

}  // namespace chimera::cli
