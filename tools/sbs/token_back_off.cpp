#include "token_back_off.hpp"

#include "server.hpp"

#include <algorithm>

namespace chimera::cli {

std::chrono::milliseconds TokenBackOff::after(unsigned failures) {
    const unsigned doublings = failures > 0 ? failures - 1 : 0;
    if (doublings >= 10) return kMax;
    return std::min(kMax, kFirst * (1 << doublings));
}

// While an address is backing off, its tokens are not judged at all, the
// right one included: a guesser gets one try per back-off however many
// connections it opens, and no server thread ever sleeps.
std::string TokenBackOff::refusal_locked(const std::string& source) const {
    const auto it = throttle_.find(source);
    if (source.empty() || it == throttle_.end()) return {};
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(it->second.retry_at -
                                                                            std::chrono::steady_clock::now());
    if (left.count() <= 0) return {};
    return "too many wrong tokens from " + source + ": retry after " + std::to_string(left.count() + 1) + " ms";
}

std::chrono::milliseconds TokenBackOff::note_wrong_locked(const std::string& source) {
    if (source.empty()) return std::chrono::milliseconds(0);  // the owner's Unix socket
    const auto now = std::chrono::steady_clock::now();
    if (throttle_.size() >= kMaxRemembered)
        std::erase_if(throttle_, [&](const auto& e) { return e.second.retry_at + kMax < now; });
    if (throttle_.size() >= kMaxRemembered && !throttle_.contains(source)) return kMax;  // full: not remembered
    Throttle& t = throttle_[source];
    ++t.failures;
    const auto wait = after(t.failures);
    t.retry_at = now + wait;
    return wait;
}

std::optional<Reply> TokenBackOff::judge(const std::string& source, std::string_view command, std::string_view token) {
    const bool is_token = command.substr(0, 6) == "token ";
    if (!is_token) return Reply::failure("token", "authenticate first: token TOKEN");
    std::lock_guard lock(mu_);
    if (std::string refusal = refusal_locked(source); !refusal.empty())
        return Reply::failure("token", std::move(refusal));
    if (!same_token(command.substr(6), token)) {
        Reply refused = Reply::failure("token", "wrong token");
        refused.data = {{"retry_after_ms", note_wrong_locked(source).count()}};
        return refused;
    }
    throttle_.erase(source);  // the right token: that address starts afresh
    return std::nullopt;
}

}  // namespace chimera::cli
