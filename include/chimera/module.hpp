// chimera/module.hpp — port-based objects (control modules), thesis §3.5–3.6.
//
// A control module is a class deriving from chimera::Module that overrides the
// methods it needs, exported with one macro so the subsystem finds it by name:
//
//     #include <chimera/module.hpp>
//
//     class Diff : public chimera::Module {
//     public:
//         chimera::Result init(chimera::Task& t) override {
//             z_ = t.translate<float>("Z");           // ports translated once, in init
//             zdot_ = t.translate<float>("Z^");
//             gain_ = t.local().number("GAIN", 1.0);  // LOCAL section of the .rmod
//             return chimera::Result::OK;
//         }
//         chimera::Result cycle(chimera::Task& t) override {
//             *zdot_ = gain_ * (*z_ - last_) * float(t.freq());  // algorithm only
//             last_ = *z_;
//             return chimera::Result::OK;
//         }
//     private:
//         float* z_ = nullptr; float* zdot_ = nullptr; float last_ = 0; double gain_ = 1;
//     };
//     CHIMERA_MODULE(diff, Diff)
//
// Built as a shared object named `diff.so` or `libdiff.so`, it is loaded when a
// .rmod says `MODULE diff` (see sbs.hpp for the module path). One instance of the
// class is created per task, so several .rmod files (SVARALIAS, LOCAL) can use
// the same code side by side.
//
// What the runtime does around each method (Figure 3.10):
//   spawn:  in-consts -> init -> out-consts                 => OFF
//           an error in init calls kill and the task stays NOT-CREATED
//   on:     in-vars AND out-vars -> on -> out-vars          => ON  (on() == OFF: stays OFF)
//   wakeup: in-vars -> cycle -> out-vars                    (every period / event)
//   off:    off -> out-vars                                 => OFF
//   kill:   (off -> out-vars when ON) -> kill               => NOT-CREATED
//   error:  an error in on/cycle/off/sync/reinit calls error(); its result:
//           OFF => OFF (off() is not called), CONTINUE => carry on,
//           ERROR => ERROR: suspended until clear(); clear() returns OFF or ERROR
//   reinit: in-consts -> reinit, when a task producing one of this task's
//           in-consts is replaced by one producing a different value
// A method reports an error by returning Result::ERROR, by calling
// task.error(...) (global error handling, err.hpp; a handler may let it
// continue), or by throwing. Signals and other commands are applied only
// between method calls, never inside one.
//
// task.error() never throws: when the error aborts (error() answers ERROR or
// OFF, a module's own err handler answers abort or jumps to a mark that is not
// set, or an error is raised inside a handler) it records the abort in the
// thread's fixed abort slot and returns Result::ERROR, and the method must
// return at once — `return t.error(code, "what failed");`. Code after it runs
// only when it returns CONTINUE. Returning runs the method's destructors and
// releases its locks as any return does; the runtime then takes the recorded
// abort at the method's boundary and it decides the outcome, whatever the
// method returned. The task ends as error() said: ERROR halts it in ERROR (the
// message in its status, sig::ERROR, the illegal-configuration flag), OFF turns
// it off; an abort decided by a module's own handler, or by the default handler
// for an error raised inside a handler, is routed to error() then. The runtime's
// part allocates nothing, takes no lock but priority-inheriting ones and writes
// nothing on the task thread: the ERROR> lines (the default handler's too) go
// through the subsystem's report ring (tests/sbs/test_task_io.cpp counts it).
//
// Real-time path: cycle() (and sync() for synchronous tasks) should not allocate,
// block, or take locks other than through the runtime.
//
// A cycle() that throws: the runtime catches it on the task thread and calls
// error() with code err::code::exception and message "exception: WHAT" (what()
// of a std::exception, "unknown exception" otherwise). error()'s answer decides,
// as for any error: ERROR (the default) halts the task in ERROR with that
// message in its status, sends sig::ERROR to the master and raises the
// illegal-configuration flag; OFF turns it off (off() is not called); CONTINUE
// carries on. The cycle's out-vars are not written unless error() says CONTINUE,
// and a cycle that failed is not counted. The other tasks run on. The ERROR>
// line goes through the subsystem's report ring and is printed by its reporter
// thread, never from the task thread. The runtime's part of this path — the
// catch, the message (cut at 1023 bytes), the record for status, the ERROR>
// line, the state change and its idle scheduling policy, the signal —
// allocates nothing and throws nothing on the task thread, for a throw as for
// a cycle that returns ERROR (tests/sbs/test_task_io.cpp counts it: 0
// allocations for ERROR; for `throw std::runtime_error("...")` exactly the 2
// the C++ runtime makes for the module's own throw, the exception object and
// the runtime_error's copy of its message). Throwing still allocates those and
// unwinds: it is an error path, not a way to return from a cycle. A module's
// error() that throws counts as answering ERROR.
// Task::warning() is real-time safe: no allocation, no stdio, no wait.
//
// Timing failures (thesis §6.3, docs/architecture.md §10). The scheduler
// watches every periodic cycle: DEADLINE (not done by the end of its period),
// MAXEXEC (more CPU time than the .rmod's WCET, or EFFECTIVE) and MINEXEC. A
// module opts in by overriding timing_failure(): it runs in the task's own
// thread, from a signal handler, so it may only do async-signal-safe work
// (atomics, the chimera::muf task API such as set_criticality; no allocation,
// no locks, no stdio, no Task methods other than the const accessors).
// Its answer:
//   FailureAction::resume       carry on (the default; the failure is counted)
//   FailureAction::skip_next    carry on, and skip the next release
//   FailureAction::abort_cycle  abandon the cycle: the runtime jumps back to the
//                               mark it set just before cycle(); the out-vars of
//                               that cycle are not written and it counts as missed
// Handlers are held off while the runtime holds the SVAR table lock and run as
// soon as it is released, so an aborted cycle never leaves the lock held. The
// jump skips destructors: a module whose cycle owns resources that must be
// released (heap memory, a mutex, an err::HandlerScope, ...) says so with
// abortable() == false, and its cycle (and every cycle of a combined task it is
// part of) is then never aborted — abort_cycle acts as resume. The runtime's
// own locks (warnings, signals, the flags) hold handlers off too, and a cycle
// that raises an error is not abandoned once its error handling has begun.
#pragma once

#include "chimera/export.hpp"

#include <chimera/err.hpp>
#include <chimera/muf/rt.hpp>
#include <chimera/sbs_files.hpp>

#include <cstddef>
#include <cstdint>
#include <limits>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include <chimera/svar.hpp>

namespace chimera {

namespace sbs::detail {
class TaskCore;
}

/// Return code of every module method (the thesis's I_OK, SBS_OFF, SBS_CONTINUE, SBS_ERROR).
enum class [[nodiscard]] Result : int {
    OK = 0,        ///< success
    OFF = 1,       ///< on(): cannot start yet, stay OFF; error()/clear(): go to OFF;
                   ///< cycle(): goal reached, turn myself off (SIG_OFF to the master)
    CONTINUE = 2,  ///< error(): cleared, continue where the error happened
    ERROR = 3,     ///< failure; from error()/clear(): suspend in the ERROR state
};

/// Task states of Figure 3.10.
enum class State : std::uint8_t { NOT_CREATED = 0, OFF = 1, ON = 2, ERROR = 3 };
CHIMERA_API std::string_view to_string(State s) noexcept;   ///< "NOT-CREATED", "OFF", "ON", "ERROR"
CHIMERA_API std::string_view to_string(Result r) noexcept;  ///< "OK", "OFF", "CONTINUE", "ERROR"

/// SBS signals, task -> master (§4.5.3): 32 in all, a bitmap; bit n = 1u << n.
namespace sig {
inline constexpr int OFF = 0;       ///< task reached its goal and shut itself off
inline constexpr int FINISH = 1;    ///< task reached its goal and continues to cycle
inline constexpr int ERROR = 2;     ///< task entered the ERROR state
inline constexpr int WARNING = 3;   ///< task generated a warning and continues
inline constexpr int SHUTDOWN = 4;  ///< task hit a fatal error and began a graceful shutdown
inline constexpr int ILLEGAL = 5;   ///< task set the illegal-configuration flag
inline constexpr int LEGAL = 6;     ///< task cleared the illegal-configuration flag
inline constexpr int USER = 7;      ///< first user-defined signal (USER .. 31)
inline constexpr int COUNT = 32;
inline constexpr std::uint32_t ALL = 0xffffffffu;
constexpr std::uint32_t bit(int s) noexcept { return s >= 0 && s < COUNT ? (1u << s) : 0u; }
CHIMERA_API std::string_view name(int s) noexcept;  ///< "OFF", ..., "USER7", ...; "" when out of range
}  // namespace sig

/// The task as its module sees it (the thesis's sbsTask_t). Passed to every
/// method; valid for the task's whole life. All fields are always available,
/// whichever method runs. For a combined task (several objects, §3.8.1) each
/// object gets its own view (its own rmod, aliases and LOCAL), sharing the task.
class CHIMERA_API Task {
public:
    // --- identity and configuration -------------------------------------
    std::string_view rmod() const noexcept;    ///< rmod name (file stem)
    std::string_view module() const noexcept;  ///< MODULE name
    std::string_view rtpu() const noexcept;    ///< RTPU name
    /// SUBSYSTEM name of the .sbs (e.g. a module's per-subsystem output folder).
    std::string_view subsystem() const noexcept;
    TaskType type() const noexcept;
    /// The LOCAL section of this object's .rmod (updated by sbsSet).
    const LocalConfig& local() const noexcept;
    /// This object's parsed .rmod.
    const RmodFile& rmod_file() const noexcept;

    // --- state -----------------------------------------------------------
    State state() const noexcept;       ///< state while this method runs
    State next_state() const noexcept;  ///< state after it returns, if it succeeds
    int crit() const noexcept;          ///< criticality (scheduler priority)
    std::uint64_t cycle_count() const noexcept;  ///< cycles since the task was turned on
    std::uint32_t warnings() const noexcept;     ///< warnings since the task was turned on
    double freq() const noexcept;    ///< Hz (0 for an event-driven task without one)
    double period() const noexcept;  ///< seconds
    /// Last error or warning: number (0 when none) and message.
    int error_number() const noexcept;
    std::string_view error_message() const noexcept;

    // --- local state-variable table ---------------------------------------
    /// A typed pointer into the local table for a port name (SVARALIAS applied).
    /// Fails (throws, at init time — never in the cycle) on an unknown name, a
    /// name that is not one of this task's ports, or a wrong type.
    template <typename T, typename Table = svar::LocalTable>
    T* translate(std::string_view port) const {
        Table& table = *static_cast<Table*>(local_table_ptr());
        return table.template translate<T>(global_name(port));
    }
    /// The global name a port name stands for.
    std::string global_name(std::string_view port) const;
    /// The task's local table (shared by all objects of a combined task).
    svar::LocalTable& local_table() const noexcept { return *static_cast<svar::LocalTable*>(local_table_ptr()); }

    // --- signals, arguments, flags -----------------------------------------
    std::uint32_t signals() const noexcept;  ///< bitmap of signals this task has sent
    std::uint32_t signal_mask() const noexcept;  ///< bitmap the master catches from this task (not `sigmask`: a glibc macro)
    /// Sends an SBS signal to the master (sbsSigSend); masked signals are
    /// dropped. Real-time safe: no allocation.
    void send_signal(int signal) noexcept;
    /// Argument of the current set/get/control call (text; empty when none).
    std::string_view arg() const noexcept;
    /// Answer of get(); the default answer is the LOCAL value of the key asked.
    void reply(std::string text);
    /// The illegal-configuration flag (§3.10): a reconfiguration is in progress
    /// or a task has halted on an error. Critical modules read it each cycle and
    /// run their local-stability loop while it is set.
    bool illegal_configuration() const noexcept;
    /// Sets/clears the flag and sends sig::ILLEGAL / sig::LEGAL.
    void set_illegal_configuration(bool illegal) noexcept;
    /// True when the master has a signal waiting for this task; a blocking
    /// sync() should poll it and return so the signal can be applied.
    bool command_pending() const noexcept;

    // --- errors and warnings -------------------------------------------------
    /// Raises an error through global error handling (errInvoke) with this
    /// module's name. Returns CONTINUE when a handler (or error()) says
    /// continue: go on after the call. Returns ERROR when the error aborts the
    /// method: return at once (`return t.error(...);` reads well) — the runtime
    /// acts on the recorded abort whatever the method then returns. Nothing is
    /// thrown and nothing allocated (err.hpp); the message is kept up to 1023
    /// bytes (cut with err::kCutMark).
    Result error(int code, std::string_view message, const char* file = nullptr, int line = 0) const;
    /// Records a warning (count, message), sends sig::WARNING, prints it when
    /// the RTPU's ERRPRINT asks for warnings. The task carries on.
    void warning(std::string_view message) noexcept;

    /// For the runtime only.
    Task(sbs::detail::TaskCore* core, std::size_t object) noexcept : core_(core), object_(object) {}

private:
    void* local_table_ptr() const noexcept;
    sbs::detail::TaskCore* core_;
    std::size_t object_;
};

/// LOCAL keys a module accepts (issue #16.2). A module declares every key it
/// reads from its .rmod's LOCAL section by overriding Module::local_keys():
///
///     static constexpr chimera::LocalKey kKeys[] = {
///         {"KP", chimera::LocalType::numbers, 0, 1e6, true, "proportional gain per joint"},
///         {"FILE", chimera::LocalType::output_file, 0, 0, false, "CSV file written"},
///     };
///     std::span<const chimera::LocalKey> local_keys() const noexcept override { return kKeys; }
///
/// The declaration is what `sbs` trusts: at run time (`set`, Subsystem::set)
///   - a key the module does not declare is refused ("no LOCAL key NOKEY; it takes KP KI ...");
///   - a value of the wrong type or outside [min, max] is refused, naming the key;
///   - a key declared with live == false is refused as "only at spawn": the
///     module reads it in init() only, so accepting it would change LOCAL and
///     not what the module runs with;
///   - a module that declares nothing accepts no `set` at all.
/// Only after these checks is the LOCAL entry replaced and Module::set() called,
/// which may still refuse (then LOCAL keeps its old value). `get` and `module
/// NAME` list the declarations; `get KEY` of a declared key absent from LOCAL
/// answers the declared `fallback` (the default the module runs with).
/// A name ending in `*` declares a family of keys by prefix (POINT* for POINT1,
/// POINT2, ...); "*" alone accepts any key (test modules). The .rmod's LOCAL
/// lines keep their form; spawn (and chimcfg check) hold them to the same
/// declarations before init() (check_local_section).
enum class LocalType : std::uint8_t {
    number,   ///< exactly one number
    numbers,  ///< one or more numbers (a vector, e.g. one per joint)
    integer,  ///< exactly one integral number
    word,     ///< exactly one word (a file name, a mode)
    text,     ///< any words
    /// One word, the name of a file the module writes (created or truncated).
    /// `sbs` neither spawns nor turns on such a module for a network or web
    /// peer: no command from the network makes a file be written (issue #29.4).
    output_file,
};
CHIMERA_API std::string_view to_string(LocalType t) noexcept;  ///< "number", "numbers", ...

/// An open end of a LocalKey range: {"Q0", LocalType::numbers, -unbounded, unbounded, ...}.
inline constexpr double unbounded = std::numeric_limits<double>::infinity();

struct LocalKey {
    const char* name;  ///< the key, or a prefix ending in '*'
    LocalType type;
    double min = -unbounded;  ///< numeric types: every value >= min
    double max = unbounded;   ///< ... and <= max
    bool live = false;        ///< true: takes effect without a respawn (at once, or at the next
                              ///< on()); false: read at spawn only, so `set` refuses it
    const char* help = "";    ///< one line for `module NAME` and `help`
    const char* fallback = "";  ///< the value used when LOCAL lacks the key ("" : required or none)
};

/// The declaration in `keys` matching `key` (exact, else the longest `*` prefix); nullptr when none.
CHIMERA_API const LocalKey* find_local_key(std::span<const LocalKey> keys, std::string_view key) noexcept;
/// Why `values` cannot be given to `key` at run time ("" when it can): unknown
/// key, spawn-only key, wrong type or count, out of range. `module` names the module.
CHIMERA_API std::string check_local_set(std::span<const LocalKey> keys, std::string_view module, std::string_view key,
                                        const std::vector<std::string>& values);
/// The LOCAL section of a .rmod against what its module declares, as spawn
/// runs it before init() and `chimcfg check` with the module found on the
/// module path: a key the module does not declare (a typo would be ignored),
/// a value of the wrong type or count, a number that is not finite (inf, nan,
/// 1e309) or outside [min, max]. Throws cfg::ParseError "FILE:LINE: LOCAL KEY:
/// reason" for the first problem. A module that declares nothing takes any LOCAL.
CHIMERA_API void check_local_section(std::span<const LocalKey> keys, std::string_view module, const LocalConfig& local);
/// One line describing a declaration: "KP numbers [0, 1e+06] live — proportional gain".
CHIMERA_API std::string describe(const LocalKey& k);

/// Base class of every control module. Every method has a default, so a module
/// overrides only what it needs. Defaults: OK for init, reinit, on, cycle, off,
/// kill, set, get, sync; error() returns ERROR (suspend, operator needed);
/// clear() returns OFF (the operator's clear is trusted).
class CHIMERA_API Module {
public:
    virtual ~Module() = default;

    virtual Result init(Task&) { return Result::OK; }
    virtual Result reinit(Task&) { return Result::OK; }
    virtual Result on(Task&) { return Result::OK; }
    virtual Result cycle(Task&) { return Result::OK; }
    virtual Result off(Task&) { return Result::OK; }
    virtual Result kill(Task&) { return Result::OK; }
    /// Called for an error in on/cycle/off/sync/reinit: OFF, CONTINUE or ERROR.
    virtual Result error(Task&, const err::Error&) { return Result::ERROR; }
    /// Called on a clear signal in the ERROR state with the error that caused
    /// it: OFF (cleared) or ERROR (still broken).
    virtual Result clear(Task&, const err::Error&) { return Result::OFF; }
    /// sbsSet: the LOCAL entry is already updated; task.arg() is "KEY value...".
    virtual Result set(Task&) { return Result::OK; }
    /// sbsGet: task.arg() is the key; answer with task.reply().
    virtual Result get(Task&) { return Result::OK; }
    /// Synchronous tasks: block until the external event, then return; the
    /// cycle follows.
    virtual Result sync(Task&) { return Result::OK; }
    /// A timing failure of this task's cycle (see the header comment): runs in
    /// the task's thread from a signal handler; async-signal-safe code only.
    virtual muf::FailureAction timing_failure(Task&, muf::Failure) noexcept { return muf::FailureAction::resume; }
    /// False when cycle() must never be abandoned half-way (it owns resources
    /// whose destructors must run).
    virtual bool abortable() const noexcept { return true; }
    /// The LOCAL keys this module accepts (see LocalKey); default: none, so
    /// `set` is refused. The span must stay valid for the module's life.
    virtual std::span<const LocalKey> local_keys() const noexcept { return {}; }
};

/// The C-ABI table exported by CHIMERA_MODULE (the thesis's _sbsFunc_t).
struct ChimeraModuleAbi {
    std::uint32_t magic;    ///< CHIMERA_MODULE_MAGIC
    std::uint32_t version;  ///< CHIMERA_MODULE_ABI_VERSION
    const char* name;       ///< MODULE name
    std::size_t size;       ///< sizeof the class (informative)
    Module* (*create)();
    void (*destroy)(Module*);
};
inline constexpr std::uint32_t CHIMERA_MODULE_MAGIC = 0x43484d4dU;  // "CHMM"
// 2: timing_failure, abortable; 3: local_keys; 4: Task::error() returns (Result::ERROR) on an
// abort instead of throwing err::Aborted, so a module built for 3 would run on after it.
inline constexpr std::uint32_t CHIMERA_MODULE_ABI_VERSION = 4;

/// Symbol name looked up for MODULE `name`: "chimera_module_<name>".
CHIMERA_API std::string module_symbol(std::string_view name);

}  // namespace chimera

/// Exports `Class` as the module `name` (an identifier; must equal the .rmod's
/// MODULE). Use once per module, at global scope, in the module's shared object
/// (or in the program itself: modules linked into the executable are found too).
#define CHIMERA_MODULE(name, Class)                                                             \
    extern "C" __attribute__((visibility("default"), used))                                     \
    const ::chimera::ChimeraModuleAbi chimera_module_##name = {                                 \
        ::chimera::CHIMERA_MODULE_MAGIC, ::chimera::CHIMERA_MODULE_ABI_VERSION, #name,          \
        sizeof(Class), []() -> ::chimera::Module* { return new Class(); },                      \
        [](::chimera::Module* m) { delete m; }};
