// tools/sbs/web.hpp — the web console (`sbs FILE.sbs --http [HOST:]PORT`,
// issue 17): the modern heir of Onika (thesis §4.4.3). One page and a
// WebSocket that speaks the network protocol of docs/cli.md (greeting, token
// first, one request per message, one JSON reply each), plus pushed streams.
//
// Built on civetweb (HTTP and WebSocket parsing are not ours to write). The
// rules are the TCP interface's: a token always, sent as the socket's first
// message; control is the one slot the network server hands out (a page that
// sends `control` holds it as a peer would, the others watch read-only);
// Host and Origin are checked so a web site cannot drive the master through
// the engineer's browser (DNS rebinding, cross-site WebSocket).
#pragma once

#include "server.hpp"

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <string_view>

namespace chimera::cli {

struct WebOptions {
    std::string subsystem;
    std::string host = "127.0.0.1";  ///< loopback unless an address is given
    std::uint16_t port = 0;          ///< 0: the kernel picks (see port())
    std::string token;               ///< required, as for --tcp
    std::chrono::milliseconds auth_timeout{5000};
    std::size_t max_request = 4096;
    std::string asset_dir;           ///< index.html, console.js, console.css
    std::string chart_js;            ///< Debian's chart.umd/min js (libjs-chart.js); empty: none
    std::chrono::milliseconds graph_period{200};  ///< how often the port graph is checked for changes
    int threads = 24;                ///< civetweb workers: each open page holds one
};

/// True when `name` (a Host header's host part, without port) may address
/// this server: a loopback name or address, or the address it is bound to.
/// Anything else is a DNS-rebinding attempt.
bool web_host_allowed(std::string_view host_header, std::string_view bound_host);
/// True when a WebSocket's Origin header is absent (not a browser) or names
/// the same host and port as its Host header (the page this server served).
bool web_origin_allowed(std::string_view origin, std::string_view host_header);

class WebConsole {
public:
    /// `execute`: the master's request handler (the one the TCP server calls).
    /// `control`: the network server whose control slot the pages share.
    WebConsole(WebOptions options, NetworkServer::Executor execute, NetworkServer& control);
    ~WebConsole();
    WebConsole(const WebConsole&) = delete;
    WebConsole& operator=(const WebConsole&) = delete;

    /// Starts listening; throws ServerError (no token, bad address, no assets).
    void start();
    void stop();
    std::uint16_t port() const noexcept { return port_; }

    struct Impl;  // public for the C callbacks of civetweb

private:
    std::unique_ptr<Impl> impl_;
    std::uint16_t port_ = 0;
};

}  // namespace chimera::cli
