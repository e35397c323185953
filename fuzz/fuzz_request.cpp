// fuzz/fuzz_request.cpp — the network request parser, parse_request(line)
// (tools/sbs/server.hpp; protocol in docs/cli.md), on arbitrary lines.
//
// Invariants: no exception; a blank line (spaces and tabs) and only that is
// a keep-alive; a command holds no control character but tab, and a plain
// (non-JSON) line is the command as sent; a malformed line says why; and the
// reply the server sends for it is one line of JSON that echoes the
// request's id unchanged.
#include <string>

#include "harness.hpp"
#include "server.hpp"

using namespace chimera;
using fuzz::require;

namespace {

void check_reply_line(const cli::Request& r) {
    const cli::Reply reply = r.kind == cli::Request::Kind::malformed ? cli::Reply::failure("", r.error)
                                                                      : cli::Reply::failure(r.command, "refused");
    const std::string line = cli::to_json_line(reply, r.id);
    require(line.find('\n') == std::string::npos && line.find('\r') == std::string::npos,
            "a reply of more than one line: " + line);
    const auto back = nlohmann::json::parse(line, nullptr, false);
    require(!back.is_discarded() && back.is_object(), "a reply that is not a JSON object: " + line);
    require(r.id.is_null() ? !back.contains("id") : back.contains("id") && back["id"] == r.id,
            "the reply does not echo the id " + r.id.dump() + ": " + line);
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const std::string_view line = fuzz::text_of(data, size);
    const cli::Request r = cli::parse_request(line);
    const bool blank = line.find_first_not_of(" \t") == std::string_view::npos;
    require(blank == (r.kind == cli::Request::Kind::keep_alive), "keep-alive is not exactly a blank line");
    switch (r.kind) {
        case cli::Request::Kind::keep_alive:
            return 0;
        case cli::Request::Kind::malformed:
            require(!r.error.empty() && r.command.empty(), "malformed without a reason, or with a command");
            break;
        case cli::Request::Kind::command:
            for (unsigned char c : r.command)
                require(c >= 0x20 || c == '\t', "a command with a control character");
            if (line[line.find_first_not_of(" \t")] != '{')
                require(r.command == line && r.id.is_null(), "a plain line is not its own command");
            break;
    }
    check_reply_line(r);
    return 0;
}
