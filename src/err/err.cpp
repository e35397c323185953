// Global error handling (see include/chimera/err.hpp).
#include "chimera/err.hpp"

#include <atomic>
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
};

thread_local ThreadState t_state;
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

void print(const std::string& line) {
    std::lock_guard<std::mutex> lock(g_printer_mutex);
    if (g_printer) {
        g_printer(line);
    } else {
        std::fprintf(stderr, "%s\n", line.c_str());
        std::fflush(stderr);
    }
}

std::string make_text(const Error& e) { return format(e, e.file != nullptr); }

}  // namespace

Aborted::Aborted(const Error& e)
    : code_(e.code),
      module_(e.module),
      message_(e.message),
      file_(e.file ? e.file : ""),
      line_(e.line),
      text_(make_text(e)) {}

HandlerId install(Match match, Handler handler) {
    const HandlerId id = g_next_id.fetch_add(1, std::memory_order_relaxed);
    t_state.chain.push_back(std::make_shared<const Installed>(Installed{id, std::move(match), std::move(handler)}));
    return id;
}

void remove(HandlerId id) noexcept {
    auto& chain = t_state.chain;
    for (auto it = chain.begin(); it != chain.end(); ++it) {
        if ((*it)->id == id) {
            chain.erase(it);
            return;
        }
    }
}

std::size_t chain_size() noexcept { return t_state.chain.size(); }

void set_debug(bool on) noexcept { g_debug.store(on, std::memory_order_relaxed); }
bool debug() noexcept { return g_debug.load(std::memory_order_relaxed); }

void set_printer(std::function<void(std::string_view)> printer) {
    std::lock_guard<std::mutex> lock(g_printer_mutex);
    g_printer = std::move(printer);
}

std::string format(const Error& e, bool with_location) {
    std::string s = "ERROR> ";
    if (!e.module.empty()) {
        s += e.module;
        s += ": ";
    }
    s += e.message;
    s += " (code ";
    s += std::to_string(e.code);
    s += ")";
    if (with_location && e.file) {
        s += " [";
        s += e.file;
        s += ":";
        s += std::to_string(e.line);
        s += "]";
    }
    return s;
}

Outcome default_handler(const Error& e) {
    print(format(e, debug()));
    return Outcome::abort();
}

namespace detail {
void push_mark(int id) noexcept {
    // A failed push would lose the mark; marks are few and set up off the
    // real-time path, so reserve generously once.
    auto& m = t_state.marks;
    if (m.capacity() == 0) m.reserve(16);
    m.push_back(id);
}
void pop_mark() noexcept {
    if (!t_state.marks.empty()) t_state.marks.pop_back();
}
}  // namespace detail

void invoke(int code, std::string_view module, std::string_view message, const char* file, int line) {
    const Error e{code, module, message, file, line};
    ThreadState& st = t_state;

    Outcome outcome = Outcome::abort();
    if (st.depth > 0) {
        // An error while handling an error: no second chance.
        outcome = default_handler(e);
    } else {
        std::shared_ptr<const Installed> chosen;
        for (auto it = st.chain.rbegin(); it != st.chain.rend(); ++it) {
            if ((*it)->match.matches(e)) {
                chosen = *it;  // held: the handler may remove itself
                break;
            }
        }
        if (chosen) {
            ++st.depth;
            try {
                outcome = chosen->handler(e);
            } catch (...) {
                --st.depth;
                throw;
            }
            --st.depth;
        } else {
            outcome = default_handler(e);
        }
    }

    switch (outcome.action) {
        case Outcome::Action::Continue:
            return;
        case Outcome::Action::Jump: {
            for (int m : st.marks)
                if (m == outcome.mark) throw MarkJump(e, outcome.mark);
            std::string msg = std::string(message) + " (handler asked to jump to mark " +
                              std::to_string(outcome.mark) + ", which is not set: aborting)";
            throw Aborted(Error{code, module, msg, file, line});
        }
        case Outcome::Action::Abort:
            break;
    }
    throw Aborted(e);
}

}  // namespace chimera::err
