// Global error handling (see include/chimera/err.hpp).
#include "chimera/err.hpp"

#include <algorithm>
#include <atomic>
#include <charconv>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <mutex>
#include <vector>

namespace chimera::err {

namespace {

struct Installed {
    HandlerId id;
    Match match;
    Handler handler;
};

// Each thread (each task) has its own chain and its own marks; nothing here is
// shared between tasks, so no lock is taken on invoke().
struct ThreadState {
    std::vector<std::shared_ptr<const Installed>> chain;  // oldest first; searched from the back
    std::vector<int> marks;        // active err::mark() ids, innermost last
    int depth = 0;                 // > 0 while a handler runs
    bool aborting = false;         // `abort` holds the pending abort
    Abort abort;                   // the abort slot: fixed, so recording allocates nothing
    ThreadPrinter printer = nullptr;  // the default handler's line on this thread
    void* printer_context = nullptr;
};

// Held through a pointer, made on the thread's first use (a task thread's is
// its task handler's install, before any cycle): libchimera's TLS block is
// static (ipc's initial-exec owner id), so a program that dlopens it (Python)
// takes that block from glibc's small static surplus, and the 1.4 KB abort slot
// there left no room for other libraries' (libgomp: "cannot allocate memory in
// static TLS block").
// Initial-exec, with its guard: src/err/meson.build.
thread_local std::unique_ptr<ThreadState> t_state;

ThreadState& state() {
    if (!t_state) t_state = std::make_unique<ThreadState>();
    return *t_state;
}
std::atomic<HandlerId> g_next_id{1};

bool initial_debug() {
    if (const char* e = std::getenv("CHIMERA_ERR_DEBUG")) return e[0] == '1';
#ifdef NDEBUG
    return false;
#else
    return true;
#endif
}
std::atomic<bool> g_debug{initial_debug()};

std::mutex g_printer_mutex;
std::function<void(std::string_view)> g_printer;

// Copies `from` into `to` (N bytes with the NUL) after `used` bytes; a text
// that does not fit is cut and ends with kCutMark. Returns the new length.
std::size_t append_cut(char* to, std::size_t n, std::size_t used, std::string_view from) noexcept {
    if (n == 0 || used >= n - 1) return used;
    const std::size_t room = n - 1 - used;
    if (from.size() <= room) {
        used += from.copy(to + used, from.size());
    } else {
        const std::size_t mark = std::min(kCutMark.size(), room);
        used += from.copy(to + used, room - mark);
        used += kCutMark.copy(to + used, mark);
    }
    to[used] = '\0';
    return used;
}

template <std::size_t N>
void copy_cut(char (&to)[N], std::string_view from) noexcept {
    append_cut(to, N, 0, from);
}

// The default handler's line, off the real-time path: through the process's
// printer (or stderr) under its lock.
void print_locked(std::string_view line) {
    std::lock_guard<std::mutex> lock(g_printer_mutex);
    if (g_printer) {
        g_printer(line);
    } else {
        std::fprintf(stderr, "%.*s\n", static_cast<int>(line.size()), line.data());
        std::fflush(stderr);
    }
}

// Records the abort (the first one while one is pending) and answers false.
bool record_abort(ThreadState& st, const Error& e, Outcome::Action action, int mark_id,
                  std::string_view reason = {}) noexcept {
    if (st.aborting) return false;
    Abort& a = st.abort;
    a.action = action;
    a.mark = mark_id;
    a.code = e.code;
    a.line = e.line;
    copy_cut(a.module, e.module);
    const std::size_t n = append_cut(a.message, sizeof a.message, 0, e.message);
    append_cut(a.message, sizeof a.message, n, reason);
    copy_cut(a.file, e.file ? std::string_view(e.file) : std::string_view{});
    st.aborting = true;
    return false;
}

// The newest handler whose filter matches `e`.
std::shared_ptr<const Installed> find_handler(const ThreadState& st, const Error& e) noexcept {
    for (auto it = st.chain.rbegin(); it != st.chain.rend(); ++it)
        if ((*it)->match.matches(e)) return *it;
    return nullptr;
}

}  // namespace

HandlerId install(Match match, Handler handler) {
    const HandlerId id = g_next_id.fetch_add(1, std::memory_order_relaxed);
    state().chain.push_back(std::make_shared<const Installed>(Installed{id, std::move(match), std::move(handler)}));
    return id;
}

void remove(HandlerId id) noexcept {
    if (!t_state) return;
    auto& chain = t_state->chain;
    for (auto it = chain.begin(); it != chain.end(); ++it) {
        if ((*it)->id == id) {
            chain.erase(it);
            return;
        }
    }
}

std::size_t chain_size() noexcept { return t_state ? t_state->chain.size() : 0; }

void set_debug(bool on) noexcept { g_debug.store(on, std::memory_order_relaxed); }
bool debug() noexcept { return g_debug.load(std::memory_order_relaxed); }

void set_printer(std::function<void(std::string_view)> printer) {
    std::lock_guard<std::mutex> lock(g_printer_mutex);
    g_printer = std::move(printer);
}

// The parts of the default handler's line, in order, to `sink`.
template <typename Sink>
void format_parts(const Error& e, bool with_location, Sink&& sink) {
    char num[16];
    auto number = [&num](int v) {
        const auto [end, ec] = std::to_chars(num, num + sizeof num, v);
        return std::string_view(num, static_cast<std::size_t>(end - num));
    };
    sink("ERROR> ");
    if (!e.module.empty()) {
        sink(e.module);
        sink(": ");
    }
    sink(e.message);
    sink(" (code ");
    sink(number(e.code));
    sink(")");
    if (with_location && e.file) {
        sink(" [");
        sink(e.file);
        sink(":");
        sink(number(e.line));
        sink("]");
    }
}

std::string format(const Error& e, bool with_location) {
    std::string s;
    format_parts(e, with_location, [&s](std::string_view part) { s += part; });
    return s;
}

std::size_t format_to(char* buffer, std::size_t size, const Error& e, bool with_location) noexcept {
    if (size == 0) return 0;
    buffer[0] = '\0';
    std::size_t n = 0;
    bool cut = false;
    // The mark goes at the end of the whole line, not of the part that did not fit.
    format_parts(e, with_location, [&](std::string_view part) noexcept {
        if (cut) return;
        if (n + part.size() > size - 1) cut = true;
        n = append_cut(buffer, size, n, part);
    });
    return n;
}

Outcome default_handler(const Error& e) {
    const ThreadState& st = state();
    if (st.printer) {
        char line[Abort::kMessageSize + Abort::kModuleSize + Abort::kFileSize + 64];
        const std::size_t n = format_to(line, sizeof line, e, debug());
        st.printer(st.printer_context, std::string_view(line, n));
    } else {
        print_locked(format(e, debug()));
    }
    return Outcome::abort();
}

void set_thread_printer(ThreadPrinter printer, void* context) noexcept {
    if (!t_state && printer == nullptr) return;
    ThreadState& st = state();  // a task thread's exists already (its handler is installed first)
    st.printer = printer;
    st.printer_context = context;
}

const Abort* pending() noexcept { return t_state && t_state->aborting ? &t_state->abort : nullptr; }
void clear_pending() noexcept {
    if (t_state) t_state->aborting = false;
}

namespace detail {
void push_mark(int id) noexcept {
    // A failed push would lose the mark; marks are few and set up off the
    // real-time path, so reserve generously once.
    auto& m = state().marks;
    if (m.capacity() == 0) m.reserve(16);
    m.push_back(id);
}
void pop_mark() noexcept {
    if (t_state && !t_state->marks.empty()) t_state->marks.pop_back();
}
}  // namespace detail

bool invoke(int code, std::string_view module, std::string_view message, const char* file, int line) {
    const Error e{code, module, message, file, line};
    ThreadState& st = state();
    if (st.aborting) return false;  // the caller went on after an abort: the first error stands

    Outcome outcome = Outcome::abort();
    if (st.depth > 0) {
        outcome = default_handler(e);  // an error while handling an error: no second chance
    } else if (std::shared_ptr<const Installed> chosen = find_handler(st, e)) {  // held: it may remove itself
        ++st.depth;
        struct Depth {
            int& d;
            ~Depth() { --d; }
        } depth{st.depth};
        outcome = chosen->handler(e);
    } else {
        outcome = default_handler(e);
    }
    if (st.aborting) return false;  // the handler raised an error of its own: it aborts this one too

    switch (outcome.action) {
        case Outcome::Action::Continue:
            return true;
        case Outcome::Action::Jump: {
            for (int m : st.marks)
                if (m == outcome.mark) return record_abort(st, e, Outcome::Action::Jump, outcome.mark);
            char reason[96];
            std::size_t n = append_cut(reason, sizeof reason, 0, " (handler asked to jump to mark ");
            char num[16];
            const auto [end, ec] = std::to_chars(num, num + sizeof num, outcome.mark);
            n = append_cut(reason, sizeof reason, n, std::string_view(num, static_cast<std::size_t>(end - num)));
            n = append_cut(reason, sizeof reason, n, ", which is not set: aborting)");
            return record_abort(st, e, Outcome::Action::Abort, 0, std::string_view(reason, n));
        }
        case Outcome::Action::Abort:
            break;
    }
    return record_abort(st, e, Outcome::Action::Abort, 0);
}

}  // namespace chimera::err
