#include "web.hpp"

#include "command_line.hpp"
#include "command_table.hpp"
#include "scope_stream.hpp"
#include "web_gate.hpp"

#include <civetweb.h>

#include <arpa/inet.h>
#include <pthread.h>
#include <sched.h>
#include <unistd.h>

#include <atomic>
#include <condition_variable>
#include <cstdio>
#include <deque>
#include <fstream>
#include <future>
#include <map>
#include <mutex>
#include <optional>
#include <sstream>
#include <thread>
#include <vector>

namespace chimera::cli {

namespace {

// The host part of a Host header: "[::1]:8080" -> "::1", "h:80" -> "h".
std::string_view host_part(std::string_view host_header) {
    if (!host_header.empty() && host_header.front() == '[') {
        const auto close = host_header.find(']');
        return close == std::string_view::npos ? std::string_view() : host_header.substr(1, close - 1);
    }
    return host_header.substr(0, host_header.find(':'));
}

bool is_numeric_address(std::string_view host) {
    const std::string h(host);
    in_addr v4{};
    in6_addr v6{};
    return ::inet_pton(AF_INET, h.c_str(), &v4) == 1 || ::inet_pton(AF_INET6, h.c_str(), &v6) == 1;
}

std::vector<std::string> words_of(std::string_view command) {
    try {
        return split_words(command);
    } catch (const SyntaxError&) {
        return {};
    }
}

std::string read_file(const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    if (!in) return {};
    std::ostringstream s;
    s << in.rdbuf();
    return s.str();
}

Reply simple(std::string cmd, std::string text, nlohmann::json data = nullptr) {
    Reply r;
    r.command = std::move(cmd);
    r.text = std::move(text);
    r.data = std::move(data);
    return r;
}

// Runs the master's commands for the pages, one at a time (the interpreter
// serialises them anyway), on a thread of its own with an ordinary stack:
// civetweb's workers have small ones (Debian builds them with 100 KB), too
// small for a spawn (the module loader, the rmod parser) under
// AddressSanitizer and tight without it.
class CommandThread {
public:
    explicit CommandThread(NetworkServer::Executor execute) : execute_(std::move(execute)) {
        thread_ = std::thread([this] { serve(); });
    }
    ~CommandThread() {
        {
            std::lock_guard lock(mu_);
            stopping_ = true;
        }
        wake_.notify_all();
        thread_.join();
    }
    CommandThread(const CommandThread&) = delete;
    CommandThread& operator=(const CommandThread&) = delete;

    /// The command's reply (or its exception), from the command thread.
    Reply run(std::string_view command) {
        std::packaged_task<Reply()> job([this, c = std::string(command)] { return execute_(c); });
        std::future<Reply> reply = job.get_future();
        {
            std::lock_guard lock(mu_);
            jobs_.push_back(std::move(job));
        }
        wake_.notify_all();
        return reply.get();
    }

private:
    void serve() {
        std::unique_lock lock(mu_);
        for (;;) {
            wake_.wait(lock, [&] { return stopping_ || !jobs_.empty(); });
            if (jobs_.empty()) return;  // stopping, and every caller answered
            std::packaged_task<Reply()> job = std::move(jobs_.front());
            jobs_.pop_front();
            lock.unlock();
            job();
            lock.lock();
        }
    }

    NetworkServer::Executor execute_;
    std::mutex mu_;
    std::condition_variable wake_;
    std::deque<std::packaged_task<Reply()>> jobs_;
    bool stopping_ = false;
    std::thread thread_;
};

}  // namespace

bool web_host_allowed(std::string_view host_header, std::string_view bound_host) {
    const std::string_view host = host_part(host_header);
    if (host.empty()) return false;
    // A DNS name other than localhost may be an attacker's that now resolves
    // to this machine (DNS rebinding): only addresses and localhost pass.
    return host == "localhost" || is_numeric_address(host) || host == bound_host;
}

bool web_origin_allowed(std::string_view origin, std::string_view host_header) {
    if (origin.empty()) return true;  // not a browser: it has no cookies or page to abuse
    const std::string h(host_header);
    return origin == "http://" + h || origin == "https://" + h;
}

struct Page {
    mg_connection* conn = nullptr;
    bool authenticated = false;
    bool controlling = false;
    bool closing = false;       // a close frame was sent: ignore what comes
    bool discarding = false;    // inside an oversized message
    std::string partial;        // a fragmented message so far
    std::chrono::steady_clock::time_point deadline;
    std::string source;         // the browser's address, as the gate saw it
    // The page's scope (issue 17.5): its own sampler task and the thread that
    // streams its ring. Touched only by this connection's civetweb thread.
    std::unique_ptr<ScopeStream> scope;
};

struct WebConsole::Impl {
    WebOptions o;
    CommandThread commands;
    NetworkServer::Executor execute;  // runs on `commands`
    NetworkServer& control;
    mg_context* ctx = nullptr;
    std::unique_ptr<PrivateNetwork> backend_net;  // civetweb's network namespace, where one could be made
    std::unique_ptr<WebGate> gate;  // the public address; civetweb is behind it
    std::map<std::string, std::pair<std::string, std::string>> assets;  // path -> (mime, body)

    std::mutex mu;  // pages and their flags; held while the ticker writes to them
    std::map<const mg_connection*, std::unique_ptr<Page>> pages;
    std::string graph;  // the last port graph pushed, as JSON text
    std::condition_variable wake;
    bool poke = false;
    std::atomic<bool> stopping{false};
    std::thread ticker;

    Impl(WebOptions opts, NetworkServer::Executor ex, NetworkServer& ctl)
        : o(std::move(opts)),
          commands(std::move(ex)),
          execute([this](std::string_view c) { return commands.run(c); }),
          control(ctl) {}

    static void write(mg_connection* conn, const std::string& text) {
        // civetweb serialises writes to one connection (it locks it).
        mg_websocket_write(conn, MG_WEBSOCKET_OPCODE_TEXT, text.data(), text.size());
    }
    static void write_close(mg_connection* conn) {
        mg_websocket_write(conn, MG_WEBSOCKET_OPCODE_CONNECTION_CLOSE, "\x03\xe8", 2);  // 1000: normal
    }

    int serve_http(mg_connection* conn);
    int accept_socket(const mg_connection* conn);
    void ready(mg_connection* conn);
    int data(mg_connection* conn, int bits, char* bytes, std::size_t len);
    void closed(const mg_connection* conn);
    bool handle_message(Page& page, std::string_view line);
    Reply run_command(Page& page, const std::string& command);
    Reply scope_command(Page& page, const std::vector<std::string>& w);
    Reply start_scope(Page& page, const std::vector<std::string>& w);
    void stop_scope(Page& page);
    void kill_sampler(const std::string& rmod);
    void tick();
    void run_ticker();
};

int WebConsole::Impl::serve_http(mg_connection* conn) {
    const mg_request_info* ri = mg_get_request_info(conn);
    const char* host = mg_get_header(conn, "Host");
    if (host == nullptr || !web_host_allowed(host, o.host)) {
        mg_send_http_error(conn, 403, "Host %s not served: use the address or localhost (DNS rebinding guard)",
                           host == nullptr ? "(none)" : host);
        return 403;
    }
    if (std::string_view(ri->request_method) != "GET" && std::string_view(ri->request_method) != "HEAD") {
        mg_send_http_error(conn, 405, "only GET");
        return 405;
    }
    const std::string path = ri->local_uri == nullptr ? "" : ri->local_uri;
    const auto it = assets.find(path == "/" ? "/index.html" : path);
    if (it == assets.end()) {
        mg_send_http_error(conn, 404, "no such page: %s", path.c_str());
        return 404;
    }
    const auto& [mime, body] = it->second;
    // The page may talk to this server only, and may not be framed by another site.
    mg_printf(conn,
              "HTTP/1.1 200 OK\r\nContent-Type: %s\r\nContent-Length: %zu\r\nCache-Control: no-store\r\n"
              "X-Content-Type-Options: nosniff\r\nX-Frame-Options: DENY\r\nReferrer-Policy: no-referrer\r\n"
              "Content-Security-Policy: default-src 'self'; connect-src 'self' ws://%s wss://%s; "
              "img-src 'self' data: blob:; frame-ancestors 'none'\r\nConnection: close\r\n\r\n",
              mime.c_str(), body.size(), host, host);
    if (std::string_view(ri->request_method) == "GET") mg_write(conn, body.data(), body.size());
    return 200;
}

int WebConsole::Impl::accept_socket(const mg_connection* conn) {
    const char* host = mg_get_header(conn, "Host");
    const char* origin = mg_get_header(conn, "Origin");
    // Refused before the handshake: civetweb closes the connection.
    if (host == nullptr || !web_host_allowed(host, o.host)) return 1;
    if (!web_origin_allowed(origin == nullptr ? "" : origin, host)) return 1;
    // Each page holds a civetweb worker: beyond the bound a page is told so
    // at once rather than left waiting for a worker. Two stay for GETs.
    std::size_t open = 0;
    {
        std::lock_guard lock(mu);
        open = pages.size();
    }
    if (open + 2 >= static_cast<std::size_t>(o.threads)) {
        mg_printf(const_cast<mg_connection*>(conn),
                  "HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain\r\nConnection: close\r\n\r\n"
                  "%zu pages are open, the most this console serves: close one\n",
                  open);
        return 1;
    }
    return 0;
}

void WebConsole::Impl::ready(mg_connection* conn) {
    auto page = std::make_unique<Page>();
    page->conn = conn;
    page->deadline = std::chrono::steady_clock::now() + o.auth_timeout;
    // Never "" (the unthrottled Unix socket's): a page the gate no longer relays is about to close anyway.
    page->source = gate->source_of(static_cast<std::uint16_t>(mg_get_request_info(conn)->remote_port));
    if (page->source.empty()) page->source = "(unknown address)";
    nlohmann::json hello = {{"ok", true},           {"cmd", "hello"},
                            {"protocol", 1},        {"subsystem", o.subsystem},
                            {"pid", ::getpid()},    {"auth", "token"},
                            {"max_request", o.max_request}, {"auth_timeout_ms", o.auth_timeout.count()},
                            {"control", false}};
    {
        std::lock_guard lock(mu);
        pages[conn] = std::move(page);
    }
    write(conn, hello.dump());
}

int WebConsole::Impl::data(mg_connection* conn, int bits, char* bytes, std::size_t len) {
    Page* page = nullptr;
    {
        std::lock_guard lock(mu);
        const auto it = pages.find(conn);
        if (it == pages.end()) return 0;
        page = it->second.get();  // lives until closed(), which runs on this thread
        if (page->closing) return 0;
    }
    const int opcode = bits & 0x0f;
    const bool fin = (bits & 0x80) != 0;
    if (opcode == MG_WEBSOCKET_OPCODE_CONNECTION_CLOSE) return 0;
    if (opcode == MG_WEBSOCKET_OPCODE_PING || opcode == MG_WEBSOCKET_OPCODE_PONG) return 1;
    if (opcode == MG_WEBSOCKET_OPCODE_BINARY) {
        write(conn, to_json_line(Reply::failure("", "text messages only")));
        return page->authenticated ? 1 : 0;
    }
    if (!page->discarding) {
        if (page->partial.size() + len > o.max_request) {
            page->partial.clear();
            page->discarding = !fin;
            write(conn, to_json_line(Reply::failure(page->authenticated ? "" : "token",
                                                    "request longer than " + std::to_string(o.max_request) + " bytes")));
            return page->authenticated ? 1 : 0;  // one try before the token
        }
        page->partial.append(bytes, len);
    } else if (fin) {
        page->discarding = false;
        return 1;
    }
    if (!fin) return 1;
    std::string message = std::move(page->partial);
    page->partial.clear();
    // One message is one request line; a trailing newline is allowed.
    while (!message.empty() && (message.back() == '\n' || message.back() == '\r')) message.pop_back();
    if (message.find('\n') != std::string::npos) {
        write(conn, to_json_line(Reply::failure("", "one request per message")));
        return page->authenticated ? 1 : 0;
    }
    return handle_message(*page, message) ? 1 : 0;
}

bool WebConsole::Impl::handle_message(Page& page, std::string_view line) {
    const Request request = parse_request(line);
    if (request.kind == Request::Kind::keep_alive) return true;
    if (request.kind == Request::Kind::malformed) {
        write(page.conn, to_json_line(Reply::failure("", request.error), request.id));
        return page.authenticated;  // before the token, any bad line ends it
    }
    if (!page.authenticated) {
        // The TCP server's back-off: one per address for both doors (issue #29.3).
        if (std::optional<Reply> refused = control.token_back_off().judge(page.source, request.command, o.token)) {
            write(page.conn, to_json_line(*refused, request.id));
            return false;  // one try per page
        }
        std::string graph_now;
        {
            std::lock_guard lock(mu);
            page.authenticated = true;
            graph_now = graph;
        }
        write(page.conn, to_json_line(simple("token", "authenticated (watching: send control to command)",
                                             {{"control", false}}),
                                      request.id));
        if (!graph_now.empty()) write(page.conn, graph_now);
        return true;
    }
    const Reply reply = run_command(page, request.command);
    write(page.conn, to_client_line(reply, request.id, request.command));
    if (page.scope) page.scope->start();  // a new scope streams after its reply
    {
        std::lock_guard lock(mu);
        poke = true;  // a command may have changed the graph: look now
    }
    wake.notify_all();
    if (reply.ok && (reply.action == Action::quit || reply.action == Action::finish)) {
        write_close(page.conn);
        return false;
    }
    return true;
}

Reply WebConsole::Impl::run_command(Page& page, const std::string& command) {
    const std::vector<std::string> w = words_of(command);
    const std::string word = w.empty() ? std::string() : w[0];
    bool controlling = false;
    {
        std::lock_guard lock(mu);
        controlling = page.controlling;
    }
    // Decided here, before any command (the page's scope included) is dispatched.
    if (!controlling)
        if (const std::string why = watcher_refusal(w); !why.empty())
            return Reply::failure(word, "read-only: this page is watching, and " + why + "; send 'control' first");
    if (word == "control" && w.size() == 1) {
        if (controlling) return simple("control", "this page has control", {{"control", true}});
        const std::string refusal = control.acquire_control();
        if (!refusal.empty()) return Reply::failure("control", refusal);
        std::lock_guard lock(mu);
        page.controlling = true;
        return simple("control", "this page has control of subsystem " + o.subsystem, {{"control", true}});
    }
    if (word == "release" && w.size() == 1) {
        if (controlling) {
            {
                std::lock_guard lock(mu);
                page.controlling = false;
            }
            control.release_control(NetworkServer::SessionEnd::peer_quit);
        }
        return simple("release", "watching (read-only)", {{"control", false}});
    }
    if (word == "scope") return scope_command(page, w);
    if (!controlling && word == "quit") {  // a watcher leaves; the interpreter is not asked
        Reply r = simple("quit", "");
        r.action = Action::quit;
        return r;
    }
    Reply reply;
    try {
        reply = execute(command);
    } catch (const std::exception& e) {
        reply = Reply::failure("", e.what());
    }
    if (reply.action == Action::network) reply = Reply::failure(reply.command, "the network already has control");
    if (controlling && (reply.action == Action::quit || reply.action == Action::finish)) {
        {
            std::lock_guard lock(mu);
            page.controlling = false;
        }
        control.release_control(reply.action == Action::finish ? NetworkServer::SessionEnd::finish
                                                               : NetworkServer::SessionEnd::peer_quit);
    }
    return reply;
}

// ------------------------------------------------------------------ the scope

namespace {

// A channel word or an option of `sample`: nothing that could end the
// command or start another.
bool scope_word(const std::string& w) {
    return !w.empty() && w.find_first_of(";'\"#\\ \t") == std::string::npos;
}

constexpr const char* kScopeUsage =
    "usage: scope start VAR[IDX]... [--rate HZ] [--rtpu RTPU] [--capacity N] | scope stop | scope ack BATCH";

}  // namespace

// Starting a scope spawns a sampler task, so it needs control (issue #29.1);
// the task is the page's own: killed when the page stops the scope, starts
// another, or closes, whether or not the page still has control.
Reply WebConsole::Impl::scope_command(Page& page, const std::vector<std::string>& w) {
    const std::string sub = w.size() > 1 ? w[1] : "";
    if (sub == "ack" && w.size() == 3) {
        if (!page.scope) return Reply::failure("scope", "scope ack: no scope running");
        char* end = nullptr;
        const unsigned long long batch = std::strtoull(w[2].c_str(), &end, 10);
        if (end == w[2].c_str() || *end != '\0') return Reply::failure("scope", "scope ack: " + w[2] + " is not a batch number");
        page.scope->ack(batch);
        return simple("scope", "");
    }
    if (sub == "stop" && w.size() == 2) {
        const std::string rmod = page.scope ? page.scope->rmod() : "";
        stop_scope(page);
        return simple("scope", rmod.empty() ? "no scope running" : "scope stopped, " + rmod + " killed",
                      {{"rmod", rmod}});
    }
    if (sub == "start" && w.size() > 2) return start_scope(page, w);
    return Reply::failure("scope", kScopeUsage);
}

// `sample` for the page, then a stream of its ring; the stream starts
// sending once the reply (naming the channels) has gone (handle_message).
Reply WebConsole::Impl::start_scope(Page& page, const std::vector<std::string>& w) {
    stop_scope(page);
    std::string sample = "sample";
    for (std::size_t i = 2; i < w.size(); ++i) {
        if (!scope_word(w[i])) return Reply::failure("scope", "scope: " + w[i] + " is not a variable or an option");
        sample += " " + w[i];
    }
    Reply started;
    try {
        started = execute(sample);
    } catch (const std::exception& e) {
        started = Reply::failure("sample", e.what());
    }
    if (!started.ok) return Reply::failure("scope", started.error);
    const std::string rmod = started.data.value("rmod", "");
    mg_connection* conn = page.conn;
    try {
        page.scope = std::make_unique<ScopeStream>(rmod, started.data.value("ring", ""),
                                                   [conn](const std::string& text) { write(conn, text); });
    } catch (const std::exception& e) {
        kill_sampler(rmod);  // nothing left half-built
        return Reply::failure("scope", "scope: " + std::string(e.what()));
    }
    Reply r = started;
    r.command = "scope";
    r.text = "scope: " + started.text;
    return r;
}

void WebConsole::Impl::kill_sampler(const std::string& rmod) {
    try {
        (void)execute("kill " + rmod);  // already gone (killed by hand, master finishing): nothing to do
    } catch (const std::exception&) {
    }
}

void WebConsole::Impl::stop_scope(Page& page) {
    if (!page.scope) return;
    const std::string rmod = page.scope->rmod();
    page.scope->stop();  // no batch is written after this
    page.scope.reset();
    kill_sampler(rmod);
}

void WebConsole::Impl::closed(const mg_connection* conn) {
    bool was_controlling = false;
    std::unique_ptr<Page> page;
    {
        std::lock_guard lock(mu);
        const auto it = pages.find(conn);
        if (it == pages.end()) return;
        was_controlling = it->second->controlling;
        page = std::move(it->second);
        pages.erase(it);
    }
    stop_scope(*page);  // the page's sampler task dies with it
    // A page closed or lost holding control: control returns (§4.4.2).
    if (was_controlling)
        control.release_control(stopping ? NetworkServer::SessionEnd::stopped : NetworkServer::SessionEnd::peer_lost);
}

void WebConsole::Impl::tick() {
    // Outside the lock: a command may be running (the interpreter serialises).
    Reply g;
    try {
        g = execute("show graph");
    } catch (const std::exception& e) {
        g = Reply::failure("show", e.what());
    }
    const std::string line =
        g.ok ? nlohmann::json({{"stream", "graph"}, {"data", g.data}}).dump(-1, ' ', false,
                                                                            nlohmann::json::error_handler_t::replace)
             : std::string();
    const bool take_back = control.control_wanted_back();
    const auto now = std::chrono::steady_clock::now();
    bool released = false;
    {
        std::lock_guard lock(mu);
        for (auto& [conn, page] : pages) {
            if (page->closing) continue;
            if (!page->authenticated && now >= page->deadline) {
                write(page->conn, to_json_line(Reply::failure("token", "no token within " +
                                                                           std::to_string(o.auth_timeout.count()) +
                                                                           " ms: connection closed")));
                write_close(page->conn);
                page->closing = true;
                continue;
            }
            if (take_back && page->controlling) {
                write(page->conn, to_json_line(Reply::failure("", "control taken back by the command line")));
                page->controlling = false;
                released = true;
            }
            if (!line.empty() && line != graph && page->authenticated) write(page->conn, line);
        }
        if (!line.empty()) graph = line;
    }
    if (released) control.release_control(NetworkServer::SessionEnd::interrupted);
}

void WebConsole::Impl::run_ticker() {
    sched_param sp{};
    ::pthread_setschedparam(::pthread_self(), SCHED_OTHER, &sp);
    while (!stopping) {
        tick();
        std::unique_lock lock(mu);
        wake.wait_for(lock, o.graph_period, [&] { return poke || stopping.load(); });
        poke = false;
    }
}

namespace {

int on_http(mg_connection* conn, void* impl) { return static_cast<WebConsole::Impl*>(impl)->serve_http(conn); }
int on_ws_connect(const mg_connection* conn, void* impl) {
    return static_cast<WebConsole::Impl*>(impl)->accept_socket(conn);
}
void on_ws_ready(mg_connection* conn, void* impl) { static_cast<WebConsole::Impl*>(impl)->ready(conn); }
int on_ws_data(mg_connection* conn, int bits, char* data, std::size_t len, void* impl) {
    return static_cast<WebConsole::Impl*>(impl)->data(conn, bits, data, len);
}
void on_ws_close(const mg_connection* conn, void* impl) { static_cast<WebConsole::Impl*>(impl)->closed(conn); }
int on_log(const mg_connection*, const char*) { return 1; }  // civetweb's own log lines stay quiet

}  // namespace

WebConsole::WebConsole(WebOptions options, NetworkServer::Executor execute, NetworkServer& control)
    : impl_(std::make_unique<Impl>(std::move(options), std::move(execute), control)) {}

WebConsole::~WebConsole() { stop(); }

void WebConsole::start() {
    Impl& im = *impl_;
    if (im.o.token.empty())
        throw ServerError("--http needs a token (--token or --token-file): every local user can reach a TCP port, "
                          "loopback included, as for --tcp");
    if (im.o.token.find_first_of(" \t\r\n") != std::string::npos)
        throw ServerError("the token must not contain white space");
    if (mg_check_feature(16) == 0) throw ServerError("this civetweb has no WebSocket support");
    const std::pair<const char*, const char*> files[] = {
        {"/index.html", "text/html; charset=utf-8"},
        {"/console.js", "text/javascript; charset=utf-8"},
        {"/scope.js", "text/javascript; charset=utf-8"},
        {"/console.css", "text/css; charset=utf-8"},
    };
    for (const auto& [name, mime] : files) {
        std::string body = read_file(im.o.asset_dir + name);
        if (body.empty()) throw ServerError("web console: cannot read " + im.o.asset_dir + name);
        im.assets[name] = {mime, std::move(body)};
    }
    if (!im.o.chart_js.empty()) {
        std::string body = read_file(im.o.chart_js);
        if (!body.empty()) im.assets["/chart.js"] = {"text/javascript; charset=utf-8", std::move(body)};
    }

    // civetweb listens on a private loopback port; the public address is the
    // gate's (web_gate.hpp), which lets a connection reach a civetweb worker
    // only with its request head complete, and bounds each source address.
    // Where the process may, that port is in a network namespace of its own
    // (civetweb's threads start in it), so no local user can dial it.
    const std::string listen = "127.0.0.1:0";
    const std::string threads = std::to_string(im.o.threads);
    const char* opts[] = {"listening_ports", listen.c_str(),
                          "num_threads", threads.c_str(),
                          "request_timeout_ms", "10000",
                          "websocket_timeout_ms", "10000",
                          "enable_websocket_ping_pong", "yes",
                          "enable_directory_listing", "no",
                          nullptr};
    mg_callbacks callbacks{};
    callbacks.log_message = on_log;
    mg_init_library(0);
    im.backend_net = std::make_unique<PrivateNetwork>(PrivateNetwork::enter());
    im.ctx = mg_start(&callbacks, nullptr, opts);
    im.backend_net->leave();
    if (im.ctx == nullptr) throw ServerError("--http: cannot listen on " + listen);
    mg_server_port ports[4]{};
    if (mg_get_server_ports(im.ctx, 4, ports) <= 0) throw ServerError("--http: civetweb has no port");
    if (!im.backend_net->made())
        std::fprintf(stderr, "web console: civetweb's port 127.0.0.1:%d is on this machine's loopback (%s): local "
                     "users can reach it past the gate\n", ports[0].port, im.backend_net->why_not().c_str());
    GateOptions gate;
    gate.host = im.o.host;
    gate.port = im.o.port;
    gate.backend_port = static_cast<std::uint16_t>(ports[0].port);
    gate.backend_netns = im.backend_net->fd();
    gate.head_timeout = im.o.auth_timeout;
    im.gate = std::make_unique<WebGate>(gate);
    // The handlers only now: a page (even one dialling civetweb's port
    // directly) finds the gate to ask for its address.
    mg_set_request_handler(im.ctx, "/", on_http, &im);
    mg_set_websocket_handler(im.ctx, "/ws", on_ws_connect, on_ws_ready, on_ws_data, on_ws_close, &im);
    im.gate->start();
    port_ = im.gate->port();
    im.ticker = std::thread([&im] { im.run_ticker(); });
}

void WebConsole::stop() {
    Impl& im = *impl_;
    if (im.ctx == nullptr) return;
    {
        std::lock_guard lock(im.mu);
        im.stopping = true;
    }
    im.wake.notify_all();
    if (im.ticker.joinable()) im.ticker.join();
    if (im.gate) im.gate->stop();
    mg_stop(im.ctx);
    im.ctx = nullptr;
    mg_exit_library();
}

}  // namespace chimera::cli
