// chimera/err.hpp — global error handling (thesis §8.2).
//
// Code that detects an error calls err::invoke() (the thesis's errInvoke) instead
// of checking and printing return values itself. invoke() walks the calling
// thread's handler chain — every task is a thread, so every task has its own
// chain — newest handler first, and runs the first one whose filter matches the
// error's code and module. The handler ends with one of three outcomes:
//
//   continue       invoke() returns true and execution goes on at the line after it;
//   abort          invoke() records the error in the calling thread's abort slot
//                  (err::pending()) and returns false: the caller returns at once,
//                  and so does every caller up to the boundary that takes the
//                  abort — the task runtime at the module method's boundary, which
//                  aborts the method (§3.6: routed to the task's error() method);
//   jump to mark   the same, up to the err::mark() call with that id, which takes
//                  it and reports MarkExit::jumped (the setjmp/longjmp of §8.2.1,
//                  done with ordinary returns so destructors and locks are released).
//
// invoke() never throws and allocates nothing once the thread has used err (see
// below; a handler may allocate, and a handler's own exception passes through):
// an error on a real-time thread costs no heap, no unwinding, no stdio. The slot is fixed storage per thread; text too long for
// it is cut and ends with kCutMark. A thread with no boundary of its own (not a
// task) reads the abort with pending() and clears it with clear_pending().
//
// With no matching handler the default handler prints a detailed message — with
// the source file and line when debug mode is on — and aborts: the task, never
// the process. On a thread that set a thread printer (a task thread: the line
// goes to the subsystem's report ring) it prints there, without stdio or lock.
//
// Handlers are installed per error code, per module, or for a scope (an RAII
// HandlerScope that removes itself at the end of the block), or any combination.
// Installing allocates, and so does a thread's first use of err (its chain and
// abort slot are made then: a task thread's when the runtime installs the task's
// handler, before any method runs); after that invoke() allocates nothing.
#pragma once

#include "chimera/export.hpp"

#include <cstdint>
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

/// Ends a text that was cut to fit a fixed buffer (an abort slot, a report line).
inline constexpr std::string_view kCutMark = "[...]";

/// The error that aborted the calling thread's current operation, kept in fixed
/// storage so that recording it allocates nothing (the abort slot). Texts are
/// NUL-terminated; one cut to fit ends with kCutMark.
struct Abort {
    static constexpr std::size_t kModuleSize = 64;
    static constexpr std::size_t kMessageSize = 1024;
    static constexpr std::size_t kFileSize = 256;

    Outcome::Action action = Outcome::Action::Abort;  ///< Abort, or Jump to `mark`
    int mark = 0;
    int code = 0;
    int line = 0;
    char module[kModuleSize] = {};
    char message[kMessageSize] = {};
    char file[kFileSize] = {};  ///< "" when unknown

    /// The error again, as views into this object.
    Error error() const noexcept {
        return {code, module, message, file[0] != '\0' ? file : nullptr, line};
    }
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

/// Raises an error (errInvoke). Returns true when the chosen handler says
/// continue. Otherwise records the error in the thread's abort slot and returns
/// false: return at once (see the header comment). A jump to a mark that is not
/// active on this thread becomes an abort (the message says so). An error raised
/// from inside a handler goes straight to the default handler, and the outer
/// error aborts too, whatever the handler answers. While an abort is pending on
/// the thread (the caller went on instead of returning), invoke() returns false
/// at once and keeps the first error: it is the cause. Never throws (but a
/// handler may), and allocates nothing once the thread has used err.
[[nodiscard]] CHIMERA_API bool invoke(int code, std::string_view module, std::string_view message,
                                      const char* file = nullptr, int line = 0);

/// The calling thread's pending abort or jump; nullptr when there is none.
CHIMERA_API const Abort* pending() noexcept;
/// Forgets the calling thread's pending abort (the boundary took it).
CHIMERA_API void clear_pending() noexcept;

/// How err::mark() ended.
enum class [[nodiscard]] MarkExit : std::uint8_t {
    completed,  ///< the body returned and nothing is pending
    jumped,     ///< a handler's jump to this mark ended the body; nothing is pending
    aborting,   ///< an abort (or a jump to an outer mark) is pending: return at once
};

/// Runs `body` under a mark: a handler answering Outcome::jump(id) makes
/// invoke() return false, the body returns (as every caller between does), and
/// mark() takes the jump. Marks nest; a jump goes to the innermost mark with
/// that id.
template <typename F>
MarkExit mark(int id, F&& body);

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

/// Where the default handler prints on the calling thread instead of the
/// process's printer: a plain function (so setting it allocates nothing) that
/// must not block — a task thread's sends the line to its subsystem's report
/// ring. `line` is valid during the call only. nullptr: back to the printer.
using ThreadPrinter = void (*)(void* context, std::string_view line) noexcept;
CHIMERA_API void set_thread_printer(ThreadPrinter printer, void* context) noexcept;

/// format() into a fixed buffer: writes at most size - 1 bytes and a NUL; a
/// line cut to fit ends with kCutMark. Returns the length written.
CHIMERA_API std::size_t format_to(char* buffer, std::size_t size, const Error& e, bool with_location) noexcept;

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
MarkExit mark(int id, F&& body) {
    {
        detail::MarkGuard guard(id);
        body();
    }
    const Abort* p = pending();
    if (!p) return MarkExit::completed;
    if (p->action == Outcome::Action::Jump && p->mark == id) {
        clear_pending();
        return MarkExit::jumped;
    }
    return MarkExit::aborting;
}

}  // namespace chimera::err

/// errInvoke with the caller's file and line.
#define CHIMERA_ERR(code, module, message) ::chimera::err::invoke((code), (module), (message), __FILE__, __LINE__)
