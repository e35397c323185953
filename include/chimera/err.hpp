// chimera/err.hpp — global error handling (thesis §8.2).
//
// Code that detects an error calls err::invoke() (the thesis's errInvoke) instead
// of checking and printing return values itself. invoke() walks the calling
// thread's handler chain — every task is a thread, so every task has its own
// chain — newest handler first, and runs the first one whose filter matches the
// error's code and module. The handler ends with one of three outcomes:
//
//   continue       invoke() returns and execution goes on at the line after it;
//   abort          invoke() throws err::Aborted; the task runtime catches it at
//                  the method boundary and aborts the method (§3.6: routed to the
//                  task's error() method), a plain thread unwinds like any throw;
//   jump to mark   invoke() throws err::MarkJump, caught by the err::mark() call
//                  with that id further up the stack (the setjmp/longjmp of §8.2.1,
//                  done with unwinding so destructors run).
//
// With no matching handler the default handler prints a detailed message — with
// the source file and line when debug mode is on — and aborts: the task, never
// the process.
//
// Handlers are installed per error code, per module, or for a scope (an RAII
// HandlerScope that removes itself at the end of the block), or any combination.
// Installing allocates; invoke() on a `continue` path allocates nothing.
#pragma once

#include "chimera/export.hpp"

#include <cstdint>
#include <exception>
#include <functional>
#include <optional>
#include <string>
#include <string_view>

namespace chimera::err {

/// Error codes used by the services themselves; user codes start at `user`.
namespace code {
inline constexpr int generic = 1;         ///< unspecified failure
inline constexpr int exception = 2;       ///< a C++ exception escaped a module method
inline constexpr int method_failed = 3;   ///< a module method returned ERROR
inline constexpr int fault = 4;           ///< a processor fault (SIGSEGV, SIGFPE, ...) in a method
inline constexpr int timeout = 5;         ///< a lock or a wait timed out
inline constexpr int config = 6;          ///< bad configuration (file, verification)
inline constexpr int user = 1000;         ///< first code free for modules
}  // namespace code

/// One error as the handlers see it. The views point at the invoker's data and
/// are valid only during the handler call.
struct Error {
    int code = code::generic;
    std::string_view module;    ///< who raised it (module or service name)
    std::string_view message;
    const char* file = nullptr;  ///< source location, when known
    int line = 0;
};

/// How a handler ends.
struct Outcome {
    enum class Action : std::uint8_t { Continue, Abort, Jump };
    Action action = Action::Abort;
    int mark = 0;  ///< for Jump: the id given to err::mark()

    static Outcome resume() noexcept { return {Action::Continue, 0}; }  ///< continue after invoke()
    static Outcome abort() noexcept { return {Action::Abort, 0}; }
    static Outcome jump(int mark_id) noexcept { return {Action::Jump, mark_id}; }
};

using Handler = std::function<Outcome(const Error&)>;

/// Which errors a handler catches: empty fields match anything.
struct Match {
    std::optional<int> code;
    std::string module;

    bool matches(const Error& e) const noexcept {
        return (!code || *code == e.code) && (module.empty() || module == e.module);
    }
};

/// Thrown by invoke() when the handler (or the default) aborts. Owns a copy of
/// the error so it survives unwinding.
class CHIMERA_API Aborted : public std::exception {
public:
    Aborted(const Error& e);
    const char* what() const noexcept override { return text_.c_str(); }
    int code() const noexcept { return code_; }
    const std::string& module() const noexcept { return module_; }
    const std::string& message() const noexcept { return message_; }
    const std::string& file() const noexcept { return file_; }
    int line() const noexcept { return line_; }
    /// The error again, as a view into this object.
    Error error() const noexcept { return {code_, module_, message_, file_.empty() ? nullptr : file_.c_str(), line_}; }

private:
    int code_;
    std::string module_, message_, file_;
    int line_;
    std::string text_;
};

/// Thrown by invoke() for a jump-to-mark outcome; caught by err::mark().
class CHIMERA_API MarkJump : public Aborted {
public:
    MarkJump(const Error& e, int mark_id) : Aborted(e), mark_(mark_id) {}
    int mark() const noexcept { return mark_; }

private:
    int mark_;
};

/// Handle of an installed handler.
using HandlerId = std::uint64_t;

/// Installs `handler` at the head of the calling thread's chain (it takes
/// precedence over every handler installed before it). Per-code: set
/// match.code; per-module: set match.module.
CHIMERA_API HandlerId install(Match match, Handler handler);
/// Removes a handler installed by this thread; unknown ids are ignored.
CHIMERA_API void remove(HandlerId id) noexcept;
/// Number of handlers on the calling thread's chain (for tests and diagnostics).
CHIMERA_API std::size_t chain_size() noexcept;

/// A handler for the lifetime of a C++ scope (the thesis's per-scope handler).
class HandlerScope {
public:
    HandlerScope(Match match, Handler handler) : id_(install(std::move(match), std::move(handler))) {}
    explicit HandlerScope(Handler handler) : HandlerScope(Match{}, std::move(handler)) {}
    ~HandlerScope() { remove(id_); }
    HandlerScope(const HandlerScope&) = delete;
    HandlerScope& operator=(const HandlerScope&) = delete;

private:
    HandlerId id_;
};

/// Raises an error (errInvoke). Returns only when the chosen handler says
/// continue; otherwise throws Aborted or MarkJump. A jump to a mark that is not
/// active on this thread becomes an abort (the message says so). An error
/// raised from inside a handler goes straight to the default handler.
CHIMERA_API void invoke(int code, std::string_view module, std::string_view message, const char* file = nullptr,
                        int line = 0);

/// Runs `body` under a mark: a handler returning Outcome::jump(id) unwinds to
/// here. Returns true when body completed, false when it was left by a jump.
/// Marks nest; a jump goes to the innermost mark with that id.
template <typename F>
[[nodiscard]] bool mark(int id, F&& body);

/// Debug mode: the default handler prints FILE:LINE with the message (§8.2).
/// Initially on in builds without NDEBUG and when CHIMERA_ERR_DEBUG=1.
CHIMERA_API void set_debug(bool on) noexcept;
CHIMERA_API bool debug() noexcept;

/// Where the default handler prints (stderr when unset). Process-wide; set it
/// before starting tasks.
CHIMERA_API void set_printer(std::function<void(std::string_view line)> printer);

/// The default handler's text: "ERROR> module: message (code N)" plus
/// " [file:line]" when `with_location`.
CHIMERA_API std::string format(const Error& e, bool with_location);

/// The default handler itself: prints, then returns Outcome::abort().
CHIMERA_API Outcome default_handler(const Error& e);

namespace detail {
CHIMERA_API void push_mark(int id) noexcept;
CHIMERA_API void pop_mark() noexcept;
struct MarkGuard {
    explicit MarkGuard(int id) noexcept { push_mark(id); }
    ~MarkGuard() { pop_mark(); }
    MarkGuard(const MarkGuard&) = delete;
    MarkGuard& operator=(const MarkGuard&) = delete;
};
}  // namespace detail

template <typename F>
bool mark(int id, F&& body) {
    try {
        detail::MarkGuard guard(id);
        body();
        return true;
    } catch (const MarkJump& j) {
        if (j.mark() != id) throw;
        return false;
    }
}

}  // namespace chimera::err

/// errInvoke with the caller's file and line.
#define CHIMERA_ERR(code, module, message) ::chimera::err::invoke((code), (module), (message), __FILE__, __LINE__)
