// sbs — the command-line interface of a subsystem (thesis §4.4.1) and its
// network interface (§4.4.2).
//
//   sbs arm.sbs                          start the subsystem, give the prompt `SBS arm<rmod>`
//   sbs arm.sbs -c 'spawn pid; on pid; status' [--json]
//   sbs arm.sbs --listen [--socket P]    prompt; `network` passes control to a peer
//   sbs arm.sbs --serve [-c 'spawn ...'] no prompt: the network has control (sbsNetwork)
//   sbs arm.sbs --tcp 127.0.0.1:7000 --token T --serve
//
// When the subsystem already runs and its master listens on the default
// socket, `sbs FILE.sbs` attaches to it as a network peer instead; when it
// runs as another user, this sbs only watches it (status, display: issue 16.7).
#include "client.hpp"
#include "peer_user.hpp"
#include "record.hpp"
#include "command_line.hpp"
#include "commands.hpp"
#include "server.hpp"
#include "watcher.hpp"
#ifdef CHIMERA_WEB
#include "web.hpp"
#endif

#include <chimera/ipc/segment.hpp>
#include <chimera/sbs.hpp>

#include "tool_cli.hpp"

#include <CLI/CLI.hpp>
#include <editline/readline.h>

#include <fcntl.h>
#include <poll.h>
#include <sys/stat.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <chrono>
#include <fstream>
#include <functional>
#include <iostream>
#include <memory>
#include <optional>
#include <string>

using namespace chimera;
using chimera::cli::Action;
using chimera::cli::Reply;

namespace {

std::atomic<bool> g_interrupted{false};

extern "C" void on_interrupt(int) { g_interrupted.store(true); }

void catch_interrupts() {
    struct sigaction sa {};
    sa.sa_handler = on_interrupt;
    sigemptyset(&sa.sa_mask);
    sa.sa_flags = 0;  // no SA_RESTART: a blocking read returns so the flag is seen
    sigaction(SIGINT, &sa, nullptr);
    sigaction(SIGTERM, &sa, nullptr);
    sigaction(SIGHUP, &sa, nullptr);
}

// Ctrl-C at the prompt must give a fresh prompt whenever it comes. libedit
// reads on through an interrupted read(), and a SIGINT that lands while it is
// busy (not blocked in read) would go unseen, so the prompt reads its own keys:
// once SIGINT has been caught it feeds libedit "kill line, accept" — the
// half-typed line is dropped, readline() returns "" and the loop prompts again.
int g_abandon_step = -1;  // -1: reading keys; 0, 1: next key of kAbandon

// The prompt's keys come through a non-blocking descriptor of its own for the
// terminal: libedit's SIGINT handler puts the terminal back in canonical mode,
// and a blocking read() that starts after the signal (poll saw "displ", the
// ^C flushed it) would wait for a whole line that never comes.
int nonblocking_terminal(int fd) {
    static const int own = [fd] {
        const char* path = ttyname(fd);
        return path != nullptr ? ::open(path, O_RDONLY | O_NONBLOCK | O_NOCTTY | O_CLOEXEC) : -1;
    }();
    return own >= 0 ? own : fd;
}

int prompt_getc(FILE* in) {
    static constexpr unsigned char kAbandon[] = {0x15, '\n'};  // Ctrl-U (kill line), Enter
    const int fd = nonblocking_terminal(fileno(in));
    for (;;) {
        if (g_abandon_step < 0 && g_interrupted.load()) g_abandon_step = 0;
        if (g_abandon_step >= 0) {
            const unsigned char key = kAbandon[g_abandon_step++];
            if (g_abandon_step == 2) g_abandon_step = -1;
            return key;
        }
        pollfd p{fd, POLLIN, 0};
        const int rc = poll(&p, 1, 100);  // the timeout re-checks a SIGINT that came just before poll()
        if (rc < 0 && errno != EINTR) return EOF;
        if (rc <= 0) continue;
        unsigned char key = 0;
        const ssize_t n = read(p.fd, &key, 1);
        if (n == 1) return key;
        if (n == 0 || (errno != EINTR && errno != EAGAIN)) return EOF;
    }
}

using cli::Executor;

/// Runs one line (one or more commands separated by `;`): each reply is
/// printed; stops at the first failure. Returns the last reply (the failing
/// one, if any).
Reply run_line(const Executor& exec, std::string_view line, bool json, bool errors_to_stderr) {
    std::vector<std::string> commands;
    try {
        commands = cli::split_commands(line);
    } catch (const cli::SyntaxError& e) {
        commands.clear();
        Reply r = Reply::failure("", e.what());
        if (json) std::cout << cli::to_json_line(r) << std::endl;
        else (errors_to_stderr ? std::cerr : std::cout) << "error: " << r.error << std::endl;
        return r;
    }
    Reply last;
    for (const auto& c : commands) {
        last = cli::is_record(c) ? cli::record(exec, c, &g_interrupted) : exec(c);
        if (json) {
            std::cout << cli::to_json_line(last) << std::endl;
        } else if (last.ok) {
            if (!last.text.empty()) std::cout << last.text << std::endl;
        } else {
            if (!last.text.empty()) std::cout << last.text << std::endl;
            (errors_to_stderr ? std::cerr : std::cout) << "error: " << last.error << std::endl;
        }
        if (!last.ok || last.action != Action::none) break;
    }
    return last;
}

// ----------------------------------------------------------------- line editing

// The TAB candidates for the line so far: the local interpreter's, or the
// master's through `complete LINE` when attached.
std::function<std::vector<std::string>(std::string_view)> g_completer;
std::vector<std::string> g_matches;
std::size_t g_match_index = 0;

char* next_match(const char*, int state) {
    if (state == 0) g_match_index = 0;
    if (g_match_index >= g_matches.size()) return nullptr;
    return ::strdup(g_matches[g_match_index++].c_str());
}

char** complete_line(const char* text, int, int) {
    rl_attempted_completion_over = 1;  // never fall back to file names
    if (!g_completer) return nullptr;
    try {
        g_matches = g_completer(std::string_view(rl_line_buffer, static_cast<std::size_t>(rl_point)));
    } catch (const std::exception&) {
        g_matches.clear();  // completion offers nothing rather than failing the prompt
    }
    // The candidates are for the whole last word; libedit passes that word as `text`.
    std::vector<std::string> keep;
    for (auto& m : g_matches)
        if (m.compare(0, std::strlen(text), text) == 0) keep.push_back(std::move(m));
    g_matches = std::move(keep);
    return rl_completion_matches(text, next_match);
}

std::string history_file() {
    const char* home = std::getenv("HOME");
    return home != nullptr && *home != '\0' ? std::string(home) + "/.chimera_sbs_history" : std::string();
}

/// libedit at a terminal, for the master's prompt and an attached one alike:
/// completion from `completer`, history in ~/.chimera_sbs_history.
class LineEditor {
public:
    explicit LineEditor(std::function<std::vector<std::string>(std::string_view)> completer)
        : hist_(history_file()) {
        g_completer = std::move(completer);
        rl_readline_name = const_cast<char*>("sbs");
        rl_getc_function = prompt_getc;
        rl_attempted_completion_function = complete_line;
        rl_completion_append_character = ' ';
        using_history();
        if (!hist_.empty()) read_history(hist_.c_str());
    }
    ~LineEditor() {
        if (!hist_.empty()) write_history(hist_.c_str());
        g_completer = nullptr;
    }
    LineEditor(const LineEditor&) = delete;
    LineEditor& operator=(const LineEditor&) = delete;

    /// One edited line; "" after Ctrl-C (the line is dropped); nullopt at end of input.
    std::optional<std::string> read(const std::string& prompt) {
        g_interrupted = false;
        char* raw = readline(prompt.c_str());
        if (g_interrupted.exchange(false)) {
            std::free(raw);
            return std::string();
        }
        if (raw == nullptr) {
            std::cout << std::endl;
            return std::nullopt;
        }
        std::string line = raw;
        std::free(raw);
        if (line.find_first_not_of(" \t") != std::string::npos) add_history(line.c_str());
        return line;
    }

private:
    std::string hist_;
};

struct NetworkSetup {
    bool listen = false;
    std::string unix_path;  // empty: the default
    std::string tcp;        // [host:]port
    std::string http;       // [host:]port of the web console
    std::string token;
    double auth_timeout_s = 2.0;  // to send the token, then the connection is closed
};

/// The token from --token-file: its first line, so it never shows in `ps`.
/// The file must not be readable by others, or anyone could read the token.
std::string read_token_file(const std::string& path) {
    struct stat st {};
    if (::stat(path.c_str(), &st) != 0) throw std::runtime_error(path + ": " + std::strerror(errno));
    if (!S_ISREG(st.st_mode)) throw std::runtime_error(path + ": not a regular file");
    if ((st.st_mode & 0077) != 0)
        throw std::runtime_error(path + ": readable or writable by others (chmod 600 it)");
    std::ifstream in(path);
    std::string token;
    std::getline(in, token);
    if (!token.empty() && token.back() == '\r') token.pop_back();
    if (token.empty()) throw std::runtime_error(path + ": empty first line (expected the token)");
    return token;
}

/// "[HOST:]PORT" (HOST may be [v6]): the host (`host` unchanged when none is
/// given) and the port; throws ServerError naming `option`.
std::uint16_t parse_host_port(const std::string& text, const std::string& option, std::string& host) {
    std::string port = text;
    if (const auto colon = text.rfind(':'); colon != std::string::npos) {
        host = text.substr(0, colon);
        if (host.size() > 2 && host.front() == '[' && host.back() == ']') host = host.substr(1, host.size() - 2);
        port = text.substr(colon + 1);
    }
    char* end = nullptr;
    const long p = std::strtol(port.c_str(), &end, 10);
    if (port.empty() || *end != '\0' || p < 0 || p > 65535)
        throw cli::ServerError(option + ": '" + port + "' is not a port number (0-65535)");
    return static_cast<std::uint16_t>(p);
}

#ifdef CHIMERA_WEB
/// Where the page's files are: CHIMERA_WEB_DIR in the environment, the
/// source tree's while this sbs runs from its build tree, else the installed ones.
std::string web_asset_dir() {
    if (const char* env = std::getenv("CHIMERA_WEB_DIR"); env != nullptr && *env != '\0') return env;
    char exe[4096];
    const ssize_t n = ::readlink("/proc/self/exe", exe, sizeof exe - 1);
    const std::string root = std::string(CHIMERA_BUILD_ROOT) + "/";
    if (n > 0 && std::string(exe, static_cast<std::size_t>(n)).rfind(root, 0) == 0) return CHIMERA_WEB_SOURCE_DIR;
    return CHIMERA_WEB_DIR;
}
#endif

class Master {
public:
    Master(sbs::Subsystem& subsystem, cli::Interpreter& interp, NetworkSetup net, bool serve)
        : sbs_(subsystem), interp_(interp), net_(std::move(net)), serve_(serve) {}

    /// Starts the server if asked for on the command line (or by `network`).
    cli::NetworkServer& server() {
        if (!server_) {
            cli::ServerOptions o;
            o.subsystem = sbs_.name();
            o.serve = serve_;
            if (net_.listen || net_.tcp.empty())
                o.unix_path = net_.unix_path.empty() ? cli::default_socket_path(sbs_.name()) : net_.unix_path;
            if (!net_.tcp.empty()) {
                o.tcp = true;
                o.tcp_port = parse_host_port(net_.tcp, "--tcp", o.tcp_host);
                o.token = net_.token;
                o.auth_timeout = std::chrono::milliseconds(static_cast<long>(net_.auth_timeout_s * 1000));
            }
            server_ = std::make_unique<cli::NetworkServer>(
                o, [this](std::string_view line) { return execute_network(line); });
            server_->start();
            std::string where;
            if (!server_->unix_path().empty()) where = "unix socket " + server_->unix_path();
            if (server_->tcp_port() != 0)
                where += (where.empty() ? "" : " and ") + std::string("TCP ") + o.tcp_host + ":" +
                         std::to_string(server_->tcp_port());
            std::cerr << "sbs: subsystem " << sbs_.name() << " listening on " << where << std::endl;
        }
        return *server_;
    }

    /// Starts the web console (--http) beside the network server, whose
    /// control slot its pages share.
    void start_web() {
#ifdef CHIMERA_WEB
        cli::WebOptions o;
        o.subsystem = sbs_.name();
        o.port = parse_host_port(net_.http, "--http", o.host);
        o.token = net_.token;
        o.auth_timeout = std::chrono::milliseconds(static_cast<long>(net_.auth_timeout_s * 1000));
        o.asset_dir = web_asset_dir();
        o.chart_js = CHIMERA_CHART_JS;
        web_ = std::make_unique<cli::WebConsole>(
            o, [this](std::string_view line) { return execute(line, cli::Origin::web); }, server());
        web_->start();
        const bool v6 = o.host.find(':') != std::string::npos;
        std::cerr << "sbs: web console of subsystem " << sbs_.name() << " on http://"
                  << (v6 ? "[" + o.host + "]" : o.host) << ":" << web_->port() << "/ (the page asks for the token)"
                  << std::endl;
#endif
    }

    /// `network`: control goes to one peer until it quits or is lost (§4.4.2).
    /// Returns false when the peer asked for the subsystem to finish.
    bool hand_over() {
        auto& s = server();
        g_interrupted = false;
        const auto end = s.hand_over(&g_interrupted, [] {
            std::cout << "control passed to the network; Ctrl-C takes it back" << std::endl;
        });
        g_interrupted = false;
        switch (end) {
            case cli::NetworkServer::SessionEnd::peer_quit: std::cout << "network peer quit: control is back" << std::endl; break;
            case cli::NetworkServer::SessionEnd::peer_lost: std::cout << "network connection lost: control is back" << std::endl; break;
            case cli::NetworkServer::SessionEnd::interrupted: std::cout << "control taken back from the network" << std::endl; break;
            case cli::NetworkServer::SessionEnd::finish: std::cout << "network peer asked to finish" << std::endl; return false;
            case cli::NetworkServer::SessionEnd::stopped: return false;
        }
        return true;
    }

    void stop() {
#ifdef CHIMERA_WEB
        if (web_) web_->stop();
#endif
        if (server_) server_->stop();
    }

private:
    Reply execute_network(std::string_view line) { return execute(line, cli::Origin::network); }

    /// One request of a network peer or a web page: exactly one command.
    Reply execute(std::string_view line, cli::Origin origin) {
        std::vector<std::string> commands;
        try {
            commands = cli::split_commands(line);
        } catch (const cli::SyntaxError& e) {
            return Reply::failure("", e.what());
        }
        if (commands.size() > 1)
            return Reply::failure("", "one command per request line (found " + std::to_string(commands.size()) +
                                          " separated by ';')");
        if (commands.empty()) {
            Reply r;
            r.rmod = interp_.default_rmod();
            return r;
        }
        return interp_.execute(commands[0], origin);
    }

    sbs::Subsystem& sbs_;
    cli::Interpreter& interp_;
    NetworkSetup net_;
    bool serve_;
    std::unique_ptr<cli::NetworkServer> server_;
#ifdef CHIMERA_WEB
    std::unique_ptr<cli::WebConsole> web_;  // declared after server_: stopped and destroyed first
#endif
};

/// The prompt, with libedit when stdin is a terminal, plain lines otherwise.
/// Returns the exit status.
int interactive(sbs::Subsystem& subsystem, cli::Interpreter& interp, Master& master) {
    const bool tty = ::isatty(STDIN_FILENO) != 0;
    std::optional<LineEditor> editor;
    if (tty) {
        editor.emplace([&interp](std::string_view l) { return interp.complete(l); });
        std::cout << "Chimera subsystem " << subsystem.name() << " (" << subsystem.file().path
                  << "): type help for the commands, quit to finish" << std::endl;
    }
    int status = 0;
    for (;;) {
        std::string line;
        if (tty) {
            auto got = editor->read(interp.prompt());
            if (!got) break;  // end of input
            line = std::move(*got);
            if (line.empty()) continue;  // Ctrl-C or an empty line: a fresh prompt
        } else {
            if (!std::getline(std::cin, line)) break;
        }
        const Reply r = run_line([&](std::string_view c) { return interp.execute(c); }, line, false, false);
        if (!r.ok) status = 1;
        if (r.action == Action::quit || r.action == Action::finish) break;
        if (r.action == Action::network) {
            try {
                if (!master.hand_over()) break;
            } catch (const std::exception& e) {
                std::cout << "error: network: " << e.what() << std::endl;
                status = 1;
            }
        }
    }
    return tty ? 0 : status;
}

// ----------------------------------------------------------------- attach mode

/// A command sent to a master that already runs the subsystem.
Reply remote_execute(cli::NetworkClient& client, std::string_view command) {
    const auto j = client.request(command, 60000);
    Reply r;
    r.ok = j.value("ok", false);
    r.command = j.value("cmd", "");
    r.text = j.value("text", "");
    r.error = j.value("error", "");
    r.rmod = j.value("rmod", "");
    if (j.contains("data")) r.data = j["data"];
    if (r.command == "quit" && r.ok) r.action = Action::quit;
    return r;
}

int attached(cli::NetworkClient& client, const std::string& script, bool json) {
    const auto& hello = client.hello();
    if (!hello.value("ok", false)) {
        std::cerr << "sbs: " << hello.value("error", std::string("refused by the master")) << std::endl;
        return 1;
    }
    Executor exec = [&](std::string_view c) -> Reply {
        try {
            return remote_execute(client, c);
        } catch (const std::exception& e) {
            return Reply::failure("", e.what());
        }
    };
    if (!script.empty()) {
        const Reply r = run_line(exec, script, json, true);
        exec("quit");
        return r.ok ? 0 : 1;
    }
    std::cerr << "sbs: attached to the master of subsystem " << hello.value("subsystem", std::string("?"))
              << " (pid " << hello.value("pid", 0) << ")" << std::endl;
    std::string line;
    std::string rmod;
    int status = 0;
    const bool tty = ::isatty(STDIN_FILENO) != 0;
    std::optional<LineEditor> editor;
    if (tty) {
        // Ctrl-C drops the line being typed, as at the master's prompt (SIGTERM still ends sbs).
        struct sigaction sa {};
        sa.sa_handler = on_interrupt;
        sigemptyset(&sa.sa_mask);
        sigaction(SIGINT, &sa, nullptr);
    }
    if (tty)
        editor.emplace([&client](std::string_view l) {
            const auto j = client.request("complete " + std::string(l), 5000);
            return j.value("data", nlohmann::json::object()).value("candidates", std::vector<std::string>());
        });
    for (;;) {
        const std::string prompt = "SBS " + hello.value("subsystem", std::string()) + "<" + rmod + "> ";
        if (tty) {
            auto got = editor->read(prompt);
            if (!got) break;
            line = std::move(*got);
            if (line.empty()) continue;
        } else if (!std::getline(std::cin, line)) {
            break;
        }
        const Reply r = run_line(exec, line, json, false);
        if (!r.ok) status = 1;
        if (r.ok) rmod = r.rmod;  // an error reply carries no RMOD: the prompt keeps its own
        if (r.action == Action::quit || r.command == "finish") break;
    }
    return tty ? 0 : status;  // commands on a pipe: 1 when one failed, as at the master's prompt
}

/// The user `subsystem` runs as when that is not this user ("" otherwise):
/// its master is then not ours to command, only to watch (issue 16.7).
std::string other_owner(const std::string& subsystem) {
    struct stat st {};
    const std::string path = "/dev/shm" + ipc::segment_name(subsystem, "status");
    if (::stat(path.c_str(), &st) != 0 || st.st_uid == ::geteuid()) return "";
    // A squatted name is nobody's subsystem: starting one replaces it or says whose it is.
    if (!ipc::squatted(ipc::segment_name(subsystem, "status")).empty()) return "";
    return cli::user_name(st.st_uid);
}

/// sbs as a watcher of another user's subsystem: `status` and `display`
/// read-only, every other command refused (tools/sbs/watcher.hpp).
int watch(const std::string& subsystem, const std::string& owner, const std::string& sbs_path,
          const std::string& script, bool json) {
    std::optional<cli::Watcher> watcher;
    const std::string command_it = std::string(owner == "root" ? "sudo " : "") + "sbs " + sbs_path;
    try {
        watcher.emplace(subsystem, owner, sbs_path);
    } catch (const std::exception& e) {
        std::cerr << "sbs: subsystem " << subsystem << " runs as " << owner << ": only " << owner
                  << " may command it (" << command_it << "), and this user may not watch it either: " << e.what()
                  << std::endl;
        return 1;
    }
    const Executor exec = [&](std::string_view c) { return watcher->execute(c); };
    if (!script.empty()) return run_line(exec, script, json, true).ok ? 0 : 1;
    std::cerr << "sbs: subsystem " << subsystem << " runs as " << owner << " (pid " << watcher->master_pid()
              << "): watching it read-only (status, display, help); only " << owner << " may command it ("
              << command_it << ")" << std::endl;
    const bool tty = ::isatty(STDIN_FILENO) != 0;
    std::optional<LineEditor> editor;
    if (tty) editor.emplace([](std::string_view) { return std::vector<std::string>{}; });
    int status = 0;
    for (;;) {
        std::string line;
        if (tty) {
            auto got = editor->read(watcher->prompt());
            if (!got) break;
            line = std::move(*got);
            if (line.empty()) continue;
        } else if (!std::getline(std::cin, line)) {
            break;
        }
        const Reply r = run_line(exec, line, json, false);
        if (!r.ok) status = 1;
        if (r.action == Action::quit) break;
    }
    return tty ? 0 : status;
}

}  // namespace

int main(int argc, char** argv) {
    CLI::App app{"sbs: command line and network interface of a Chimera subsystem (thesis §4.4)"};
    std::string sbs_path, script;
    bool json = false, serve = false, no_attach = false;
    NetworkSetup net;
    std::vector<std::string> module_dirs;
    app.add_option("file", sbs_path, "the subsystem's .sbs file")->required()->check(CLI::ExistingFile);
    app.add_option("-c,--command", script, "run these commands (separated by ; or newlines) and exit");
    app.add_flag("--json", json, "print every reply as one JSON object per line (for -c)");
    app.add_flag("--listen", net.listen,
                 "listen on a Unix socket, owner only (default $XDG_RUNTIME_DIR/chimera/NAME.sock, "
                 "else /tmp/chimera-UID/NAME.sock)");
    app.add_option("--socket", net.unix_path, "the Unix socket path for --listen (implies --listen)");
    app.add_option("--tcp", net.tcp, "listen on TCP [host:]port as well (host: loopback unless given)");
    app.add_option("--http", net.http,
                   "serve the web console on [host:]port (host: loopback unless given; needs --token or "
                   "--token-file, as --tcp)");
    std::string token_file;
    app.add_option("--token", net.token, "token a TCP peer or web page must send first (required with --tcp, --http)");
    app.add_option("--token-file", token_file,
                   "read the token from the first line of this file (mode 0600; keeps it out of ps)");
    app.add_option("--auth-timeout", net.auth_timeout_s,
                   "seconds a TCP peer has to send its token before it is disconnected (default 2)")
        ->check(CLI::Range(0.1, 600.0));
    app.add_flag("--serve", serve,
                 "no prompt: the network has control from the start (after -c), until a peer sends finish");
    app.add_option("--module-path", module_dirs, "a folder with modules and .rmod files (repeatable)");
    app.add_flag("--no-attach", no_attach, "never attach to a running master; start the subsystem here");
    chimera::tools::add_version(app, "sbs");
    if (const int status = chimera::tools::parse(app, argc, argv); status >= 0) return status;
    if (!net.unix_path.empty()) net.listen = true;
    if (!token_file.empty()) {
        if (!net.token.empty()) {
            std::cerr << "sbs: give --token or --token-file, not both" << std::endl;
            return 2;
        }
        try {
            net.token = read_token_file(token_file);
        } catch (const std::exception& e) {
            std::cerr << "sbs: --token-file " << e.what() << std::endl;
            return 2;
        }
    }
#ifndef CHIMERA_WEB
    if (!net.http.empty()) {
        std::cerr << "sbs: --http: this sbs was built without the web console (civetweb not found at configure "
                     "time: install libcivetweb-dev and reconfigure with -Dweb=enabled)"
                  << std::endl;
        return 2;
    }
#endif
    if (!net.token.empty() && net.tcp.empty() && net.http.empty()) {
        std::cerr << "sbs: --token is for --tcp and --http" << std::endl;
        return 2;
    }
    if (!net.http.empty() && net.token.empty()) {
        std::cerr << "sbs: --http needs --token or --token-file (every local user can reach a TCP port, "
                     "loopback included)"
                  << std::endl;
        return 2;
    }
    if (!net.tcp.empty() && net.token.empty()) {
        // Every local user can connect to a TCP port, loopback included, and
        // control of the master is control of the machine it runs as.
        std::cerr << "sbs: --tcp needs --token or --token-file (every local user can reach a TCP port, "
                     "loopback included); the owner-only Unix socket (--listen) needs no token"
                  << std::endl;
        return 2;
    }

    std::unique_ptr<sbs::Subsystem> subsystem;
    try {
        const SbsFile file = read_sbs(sbs_path);
        if (!no_attach) {
            if (const std::string owner = other_owner(file.subsystem); !owner.empty())
                return watch(file.subsystem, owner, sbs_path, script, json);
        }
        // Already running: talk to its master over the network interface.
        if (!no_attach && ipc::Segment::exists(ipc::segment_name(file.subsystem, "svar"))) {
            std::string path;
            try {
                path = net.unix_path.empty() ? cli::default_socket_path(file.subsystem) : net.unix_path;
            } catch (const std::exception&) {
            }
            if (!path.empty() && ::access(path.c_str(), F_OK) == 0) {
                try {
                    auto client = cli::NetworkClient::connect_unix(path);
                    return attached(client, script, json);
                } catch (const cli::UntrustedMasterError& e) {
                    std::cerr << "sbs: subsystem " << file.subsystem << ": " << e.what() << std::endl;
                    return 1;
                } catch (const cli::ClientError& e) {
                    std::cerr << "sbs: subsystem " << file.subsystem << " is running but its master does not answer on "
                              << path << ": " << e.what() << std::endl;
                    return 1;
                }
            }
        }
        subsystem = sbs::Subsystem::init(file);
    } catch (const std::exception& e) {
        std::cerr << "sbs: " << e.what() << std::endl;
        return 1;
    }
    for (const auto& d : module_dirs) subsystem->add_module_path(d);

    cli::Interpreter interp(*subsystem, module_dirs);
    Master master(*subsystem, interp, net, serve);
    int status = 0;
    try {
        // With --serve the sockets open once the script has run, so a peer
        // never finds them while the script still has control.
        // The .sbs's TASK lines first: the script, the prompt and the network
        // find the configured tasks there (and none when one failed).
        if (!subsystem->file().tasks.empty()) {
            const Reply started = interp.start_tasks();
            if (!started.ok) throw std::runtime_error(started.error);
            if (!json && !started.text.empty()) std::cout << started.text << std::endl;
        }
        if ((net.listen || !net.tcp.empty()) && !serve) master.server();
        // With --serve the pages, like the sockets, open once the script has run.
        if (!net.http.empty() && !serve) master.start_web();
        if (serve || !script.empty() || net.listen || !net.tcp.empty() || !net.http.empty() || ::isatty(STDIN_FILENO))
            catch_interrupts();
        if (!script.empty()) {
            const Reply r = run_line([&](std::string_view c) { return interp.execute(c); }, script, json, true);
            if (!r.ok) status = 1;
            if (r.action == Action::quit || r.action == Action::finish) serve = false;
            if (r.action == Action::network && !serve) {
                if (!master.hand_over()) serve = false;
            }
        }
        if (serve && status == 0) {
            if (!net.http.empty()) master.start_web();
            const auto end = master.server().serve_forever(&g_interrupted);
            if (end == cli::NetworkServer::SessionEnd::interrupted)
                std::cerr << "sbs: interrupted: finishing subsystem " << subsystem->name() << std::endl;
        } else if (script.empty()) {
            status = interactive(*subsystem, interp, master);
        }
    } catch (const std::exception& e) {
        std::cerr << "sbs: " << e.what() << std::endl;
        status = 1;
    }
    master.stop();
    interp.detach();
    try {
        subsystem->finish();
    } catch (const std::exception& e) {
        std::cerr << "sbs: finish: " << e.what() << std::endl;
        status = 1;
    }
    return status;
}
