// tools/sbs/reply.hpp — the result of one command, as the prompt prints it and
// as the network protocol sends it (one JSON object per line).
#pragma once

#include <nlohmann/json.hpp>

#include <string>
#include <string_view>

namespace chimera::cli {

/// What the caller of the interpreter must do after a command, beyond printing.
enum class Action {
    none,
    quit,     ///< leave this interface (the prompt, or a network session)
    network,  ///< hand control to a network peer until it quits or is lost (§4.4.2)
    finish,   ///< shut the subsystem down (sbsFinish) and exit
};

struct Reply {
    bool ok = true;
    std::string command;          ///< the command word, e.g. "status"
    std::string text;             ///< what the prompt prints (may be several lines, no final newline)
    nlohmann::json data;          ///< structured result for --json and the network; null when none
    std::string error;            ///< one line, set when !ok
    std::string rmod;             ///< the default RMOD after the command (may be empty)
    Action action = Action::none;

    static Reply failure(std::string command, std::string message) {
        Reply r;
        r.ok = false;
        r.command = std::move(command);
        r.error = std::move(message);
        return r;
    }
};

/// The reply as one JSON object: {"ok":true,"cmd":...,"rmod":...,"text":...,"data":...}
/// or {"ok":false,"cmd":...,"error":...[,"data":...]}; `id` is echoed when the request carried one.
nlohmann::json to_json(const Reply& reply, const nlohmann::json& id = nullptr);

/// to_json() serialised on one line (no newline); never throws on odd bytes
/// (invalid UTF-8 is replaced).
std::string to_json_line(const Reply& reply, const nlohmann::json& id = nullptr);

/// The most one reply to a network client (a TCP peer, a web page) may take,
/// serialised (issue #29.2): a `display all` of a large table would otherwise
/// be as big as the table. The owner's Unix socket and the prompt are not bounded.
inline constexpr std::size_t kMaxClientReplyBytes = std::size_t{1} << 20;

/// to_json_line() for a network client. A reply longer than
/// kMaxClientReplyBytes is not sent, not even in part: a refusal naming the
/// bound, `request` (the command as the client sent it) and how to ask for
/// less takes its place. The command has run all the same.
std::string to_client_line(const Reply& reply, const nlohmann::json& id, std::string_view request);

/// The reply as a prompt shows it: the text, or "error: ..." for a failure.
std::string to_text(const Reply& reply);

}  // namespace chimera::cli
