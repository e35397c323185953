// tools/sbs/token_back_off.hpp — wrong tokens slow their source address down
// (issue #29.3), the one rule the TCP server and the web console share: the
// n-th wrong token from an address makes it wait kFirst * 2^(n-1), at most
// kMax, and a token it sends sooner is refused unjudged, the right one
// included; the right token, once judged, starts the address afresh.
#pragma once

#include "reply.hpp"

#include <chrono>
#include <cstddef>
#include <map>
#include <mutex>
#include <optional>
#include <string>
#include <string_view>

namespace chimera::cli {

class TokenBackOff {
public:
    static constexpr std::chrono::milliseconds kFirst{100};
    static constexpr std::chrono::milliseconds kMax{10000};
    /// Addresses remembered at most; expired ones are forgotten first.
    static constexpr std::size_t kMaxRemembered = 4096;

    /// The wait after `failures` wrong tokens in a row.
    static std::chrono::milliseconds after(unsigned failures);

    /// Judges a connection's first request, `command`, as its token, from
    /// `source` ("" is the owner's Unix socket: never throttled). nullopt:
    /// the right token; else the refusal to send, after which the connection
    /// is closed (one try each): "authenticate first: token TOKEN",
    /// "too many wrong tokens from ADDR: retry after N ms", or "wrong token"
    /// with data {"retry_after_ms": N}. Safe from several threads.
    std::optional<Reply> judge(const std::string& source, std::string_view command, std::string_view token);

private:
    std::string refusal_locked(const std::string& source) const;  // "" or the refusal
    std::chrono::milliseconds note_wrong_locked(const std::string& source);

    struct Throttle {
        unsigned failures = 0;
        std::chrono::steady_clock::time_point retry_at;  // no token is judged before
    };
    mutable std::mutex mu_;  // the web console judges on civetweb's threads
    std::map<std::string, Throttle> throttle_;
};

}  // namespace chimera::cli
