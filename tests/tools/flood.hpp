// tests/tools/flood.hpp — a token-less connection flood from another loopback
// address (issue #29.3), and a detector of the machine's own stalls, shared
// by the TCP test (test_server.cpp) and the web one (test_sbs_network.cpp).
//
// The flood comes from 127.0.0.2 (Linux routes all of 127/8 to lo) so the
// server's per-address bounds can tell it from the operator at 127.0.0.1.
#pragma once

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <unistd.h>

#include <gtest/gtest.h>

#include <algorithm>
#include <cstdio>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <deque>
#include <functional>
#include <string>
#include <thread>
#include <vector>

namespace flood_test {

using namespace std::chrono_literals;

/// A non-blocking TCP connect to 127.0.0.1:port from `source`; -1 on failure.
inline int connect_from(const char* source, std::uint16_t port) {
    const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
    if (fd < 0) return -1;
    sockaddr_in from{};
    from.sin_family = AF_INET;
    ::inet_pton(AF_INET, source, &from.sin_addr);
    sockaddr_in to{};
    to.sin_family = AF_INET;
    to.sin_port = htons(port);
    to.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    if (::bind(fd, reinterpret_cast<sockaddr*>(&from), sizeof from) != 0 ||
        (::connect(fd, reinterpret_cast<sockaddr*>(&to), sizeof to) != 0 && errno != EINPROGRESS)) {
        ::close(fd);
        return -1;
    }
    return fd;
}

/// The flood holds hundreds of sockets, the server (in-process) as many.
inline void raise_fd_limit() {
    rlimit r{};
    ::getrlimit(RLIMIT_NOFILE, &r);
    r.rlim_cur = std::min<rlim_t>(r.rlim_max, 16384);
    ::setrlimit(RLIMIT_NOFILE, &r);
}

/// Two threads that, until stopped, each connect to `port` from 127.0.0.2
/// every 2 ms, send `payload` on every third connection (a wrong token, a
/// half request) and nothing on the others, keep the newest `held` sockets
/// open idle and close the oldest: an attacker with no token, holding far
/// more connections than the old global bound (512) at once.
class Flood {
public:
    Flood(std::uint16_t port, std::string payload, std::size_t held = 500) {
        for (int t = 0; t < 2; ++t)
            threads_.emplace_back([this, port, payload, held] { run(port, payload, held); });
    }
    ~Flood() { stop(); }
    void stop() {
        stopping_ = true;
        for (auto& t : threads_)
            if (t.joinable()) t.join();
    }
    std::uint64_t connections() const { return connections_; }

private:
    void run(std::uint16_t port, const std::string& payload, std::size_t held) {
        std::deque<int> open;
        for (std::uint64_t i = 0; !stopping_; ++i) {
            if (const int fd = connect_from("127.0.0.2", port); fd >= 0) {
                ++connections_;
                if (i % 3 == 0) {
                    std::this_thread::sleep_for(1ms);  // let the connect complete before the payload
                    [[maybe_unused]] auto n = ::send(fd, payload.data(), payload.size(), MSG_NOSIGNAL);
                }
                open.push_back(fd);
            }
            while (open.size() > held) {
                ::close(open.front());
                open.pop_front();
            }
            std::this_thread::sleep_for(2ms);
        }
        for (int fd : open) ::close(fd);
    }

    std::atomic<bool> stopping_{false};
    std::atomic<std::uint64_t> connections_{0};
    std::vector<std::thread> threads_;
};

/// Sleeps 10 ms at a time and remembers the longest oversleep: when a thread
/// that asks for 10 ms got none for longer than `stalled_over`, the machine
/// itself stalled (other builds on the shared cores), not the server.
class StallDetector {
public:
    StallDetector() : thread_([this] { run(); }) {}
    ~StallDetector() {
        stopping_ = true;
        thread_.join();
    }
    /// The longest oversleep since the last call, in ms; resets it.
    long take_worst_ms() { return worst_ms_.exchange(0); }

private:
    void run() {
        while (!stopping_) {
            const auto before = std::chrono::steady_clock::now();
            std::this_thread::sleep_for(10ms);
            const long over = std::chrono::duration_cast<std::chrono::milliseconds>(std::chrono::steady_clock::now() -
                                                                                   before - 10ms).count();
            long seen = worst_ms_.load();
            while (over > seen && !worst_ms_.compare_exchange_weak(seen, over)) {
            }
        }
    }
    std::atomic<bool> stopping_{false};
    std::atomic<long> worst_ms_{0};
    std::thread thread_;
};

/// One legitimate connect's outcome: it got control, and how long it took.
struct Attempt {
    bool got_control = false;
    std::chrono::milliseconds took{0};
    std::string detail;  // the refusal or error when it did not
};

/// Runs `attempt` `count` times, `spacing` apart. An attempt slower than
/// `limit` during which the stall detector saw the machine stall by more
/// than `stalled_over` is retried (at most `retries` times in all) and
/// reported through `note`; every other outcome is kept as it is.
inline std::vector<Attempt> timed_attempts(int count, std::chrono::milliseconds spacing,
                                           std::chrono::milliseconds limit, StallDetector& stalls,
                                           const std::function<Attempt()>& attempt,
                                           const std::function<void(const std::string&)>& note,
                                           int retries = 3, long stalled_over = 300) {
    std::vector<Attempt> kept;
    while (static_cast<int>(kept.size()) < count) {
        stalls.take_worst_ms();
        Attempt a = attempt();
        const long stall = stalls.take_worst_ms();
        if (a.took > limit && stall > stalled_over && retries > 0) {
            --retries;
            note("attempt " + std::to_string(kept.size() + 1) + " took " + std::to_string(a.took.count()) +
                 " ms while the machine itself stalled " + std::to_string(stall) + " ms: retried");
            continue;
        }
        kept.push_back(a);
        std::this_thread::sleep_for(spacing);
    }
    return kept;
}

/// The check of the operator's connects under a flood: each got
/// control within `limit`; prints how many did and the slowest.
inline void expect_each_in_control(const std::vector<Attempt>& tries, std::chrono::milliseconds limit,
                                   std::uint64_t flooded) {
    int in_control = 0;
    long worst = 0;
    for (const auto& a : tries) {
        in_control += a.got_control ? 1 : 0;
        worst = std::max<long>(worst, a.took.count());
        EXPECT_TRUE(a.got_control) << a.detail;
        EXPECT_LE(a.took, limit);
    }
    std::printf("[ flood ] %llu token-less connections from 127.0.0.2; operator: %d of %zu in control, slowest %ld ms\n",
                static_cast<unsigned long long>(flooded), in_control, tries.size(), worst);
}

}  // namespace flood_test
