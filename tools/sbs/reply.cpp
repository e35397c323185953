#include "reply.hpp"

namespace chimera::cli {

nlohmann::json to_json(const Reply& reply, const nlohmann::json& id) {
    nlohmann::json j = nlohmann::json::object();
    if (!id.is_null()) j["id"] = id;
    j["ok"] = reply.ok;
    j["cmd"] = reply.command;
    if (reply.ok) {
        j["rmod"] = reply.rmod;
        j["text"] = reply.text;
        if (!reply.data.is_null()) j["data"] = reply.data;
    } else {
        j["error"] = reply.error;
        if (!reply.text.empty()) j["text"] = reply.text;
        if (!reply.data.is_null()) j["data"] = reply.data;  // e.g. what a reconfig applied
    }
    return j;
}

std::string to_json_line(const Reply& reply, const nlohmann::json& id) {
    return to_json(reply, id).dump(-1, ' ', false, nlohmann::json::error_handler_t::replace);
}

std::string to_client_line(const Reply& reply, const nlohmann::json& id, std::string_view request) {
    std::string line = to_json_line(reply, id);
    if (line.size() <= kMaxClientReplyBytes) return line;
    return to_json_line(Reply::failure(reply.command,
                                       "the reply to '" + std::string(request) + "' is " + std::to_string(line.size()) +
                                           " bytes, over the " + std::to_string(kMaxClientReplyBytes) +
                                           " (1 MiB) one reply to a network client may take, so none of it is "
                                           "sent; ask for less, e.g. display VAR... (names, or patterns such as "
                                           "Q*) rather than display all"),
                        id);
}

std::string to_text(const Reply& reply) {
    if (reply.ok) return reply.text;
    std::string out = reply.text;
    if (!out.empty()) out += '\n';
    out += "error: " + reply.error;
    return out;
}

}  // namespace chimera::cli
