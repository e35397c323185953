// chimera/spp.hpp — special purpose processors (thesis §7.4).
//
// An SPP is a computing device that tasks hand work to: "download library X",
// "call routine Y", move data in and out, wait for the result. Here the SPP is
// an executive thread (chimexec, §7.4.2) with its own memory, optionally pinned
// to a CPU and run SCHED_FIFO: a worker today, the same interface for an
// accelerator later (docs/architecture.md §13).
//
//   spp::Library lib;                       // the "compiled math library"
//   lib.add_variable("x", 8 * sizeof(double));
//   lib.add_routine("scale", [](spp::Memory& m, const spp::Args& a) { ... });
//   auto proc = spp::Processor::init(spp::find_config(spp::load_config("lab.spp"), "fpa0"), lib);
//   auto s = spp::Spp::init(*proc, 10);     // one per task, with its priority
//   auto x = s->translate("x"), scale = s->translate("scale");
//   s->write(x, input, sizeof input);       // buffered XFER
//   s->call(scale, spp::Args{}.add(x).add(2.0));  // buffered CALL
//   s->read(x, output, sizeof output);      // buffered XFER
//   s->wait();                              // WAKEUP: blocks until all done
//
// The executive takes commands (CALL, WAKEUP, XFER) from the command buffers
// and runs each to completion, never preempting one (§7.4.2). Each task's
// commands run in the order it issued them. Between tasks the executive is not
// first-come-first-served, which the thesis leaves open: the next command
// comes from the highest-priority task that has one pending (ties: the
// earliest issued). lock() gives one task exclusive use of the SPP for a job;
// tasks waiting for the lock get it in priority order, and release() is itself
// buffered, so the job's commands all run before the next holder's.
//
// Real-time paths: call/write/read/wait/release are noexcept, allocate
// nothing, and make a system call only to wake a sleeping executive or to
// sleep in wait(). A task's Spp object is used by that task's thread only.
//
// Configuration file (the thesis's hardware configuration entry, cfg.hpp style):
//   SPP <name>
//     DRIVER thread          # the only driver on Linux today
//     MEMSIZE <bytes>        # the SPP's memory (library variables live here)
//     [QUEUE <commands>]     # command buffer entries per task, default 64
//     [TASKS <n>]            # tasks that may use it at once, default 8
//     [CPU <n>]              # pin the executive to this CPU
//     [PRIORITY <1-99>]      # run it SCHED_FIFO (without privilege: SCHED_OTHER, said once per process)
//   END
//   EOF
#pragma once

#include "chimera/export.hpp"
#include "chimera/ipc/pi_mutex.hpp"

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <mutex>
#include <new>
#include <stdexcept>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

namespace chimera::spp {

/// Set-up error (configuration, library, translate); what() names the SPP or FILE:LINE.
class CHIMERA_API Error : public std::runtime_error {
public:
    explicit Error(const std::string& m) : std::runtime_error(m) {}
};

/// A translated symbol: a routine or a variable of the SPP's library.
struct Handle {
    enum class Kind : std::uint8_t { none, routine, variable };
    Kind kind = Kind::none;
    std::uint32_t index = 0;
    explicit operator bool() const noexcept { return kind != Kind::none; }
};

/// Arguments of a remote call (no return values: results go to SPP memory,
/// §7.4.2). Up to kMaxArgs integers, doubles or handles.
class Args {
public:
    static constexpr int kMaxArgs = 6;
    Args& add(std::int64_t v) noexcept { return put(Value{.i = v}); }
    Args& add(int v) noexcept { return add(static_cast<std::int64_t>(v)); }
    Args& add(double v) noexcept { return put(Value{.d = v}); }
    Args& add(Handle h) noexcept { return put(Value{.h = h}); }
    std::int64_t i(int k) const noexcept { return v_[k].i; }
    double d(int k) const noexcept { return v_[k].d; }
    Handle h(int k) const noexcept { return v_[k].h; }
    int size() const noexcept { return n_; }
    /// False when more than kMaxArgs were added (call() then refuses it).
    bool valid() const noexcept { return n_ <= kMaxArgs; }

private:
    union Value {
        std::int64_t i;
        double d;
        Handle h;
    };
    Args& put(Value v) noexcept {
        if (n_ < kMaxArgs) v_[n_] = v;
        ++n_;
        return *this;
    }
    Value v_[kMaxArgs]{};
    int n_ = 0;
};

class Processor;

/// The SPP's memory as a routine sees it.
class CHIMERA_API Memory {
public:
    /// The variable's storage, or nullptr for a handle that is not a variable.
    template <typename T = std::byte>
    T* at(Handle h) const noexcept {
        return reinterpret_cast<T*>(address(h));
    }
    /// Its size in bytes (0 when not a variable).
    std::size_t size_of(Handle h) const noexcept;

private:
    friend class Processor;
    std::byte* address(Handle h) const noexcept;
    const Processor* proc_ = nullptr;
};

using Routine = void (*)(Memory& memory, const Args& args);

/// The library "downloaded" to an SPP at init: routines and variables by name.
class CHIMERA_API Library {
public:
    /// Throws Error when the name is already used.
    void add_routine(std::string name, Routine fn);
    /// `align`: any power of two; the variable's address has it.
    void add_variable(std::string name, std::size_t bytes, std::size_t align = 16);

    struct RoutineEntry {
        std::string name;
        Routine fn;
    };
    struct VariableEntry {
        std::string name;
        std::size_t bytes;
        std::size_t align;
    };
    const std::vector<RoutineEntry>& routines() const noexcept { return routines_; }
    const std::vector<VariableEntry>& variables() const noexcept { return variables_; }

private:
    bool used(std::string_view name) const noexcept;
    std::vector<RoutineEntry> routines_;
    std::vector<VariableEntry> variables_;
};

struct Config {
    std::string name;
    std::string driver = "thread";
    std::size_t memsize = 0;
    int queue = 64;
    int tasks = 8;
    int cpu = -1;
    int priority = 0;
    std::string file;
    int line = 0;
};

CHIMERA_API std::vector<Config> load_config(const std::string& path);
CHIMERA_API std::vector<Config> parse_config(std::string_view text, std::string name);
/// The entry of that name; throws Error naming the SPP when absent.
CHIMERA_API const Config& find_config(const std::vector<Config>& configs, std::string_view name);

/// Command types of the executive (§7.4.2). RELEASE is the buffered end of a
/// locked job.
enum class CommandType : std::uint8_t { CALL, WAKEUP, XFER_IN, XFER_OUT, RELEASE };

/// One configured SPP and its executive thread.
class CHIMERA_API Processor {
public:
    /// Lays out the library's variables in MEMSIZE bytes and starts the
    /// executive, pinned and raised as configured before this returns.
    /// Throws Error: unknown driver, a value out of the file format's range
    /// (for a Config made in code), library does not fit, CPU not usable.
    static std::unique_ptr<Processor> init(const Config& config, const Library& library);
    /// Every Spp attached must have finished (been destroyed) first, so all
    /// their commands have run; one still attached aborts the program, naming
    /// the SPP, rather than leave it pointing into freed memory.
    ~Processor();
    Processor(const Processor&) = delete;
    Processor& operator=(const Processor&) = delete;

    const Config& config() const noexcept { return config_; }
    /// Handle of a routine or variable; Kind::none when unknown.
    Handle lookup(std::string_view name) const noexcept;
    /// Commands the executive has run, and routines that threw.
    std::uint64_t executed() const noexcept { return executed_.load(std::memory_order_relaxed); }
    std::uint64_t faults() const noexcept { return faults_.load(std::memory_order_relaxed); }
    /// True when the executive got the SCHED_FIFO priority it was configured
    /// with (settled when init returns).
    bool realtime() const noexcept { return realtime_.load(); }
    /// Commands issued by the attached tasks and not yet completed (the one
    /// running included): the SPP's backlog, for a status display.
    std::size_t queued() const noexcept;
    /// Tasks blocked in lock() right now, waiting to be granted the SPP.
    int lock_waiters() const noexcept { return lock_waiters_.load(); }

private:
    friend class Spp;
    friend class Memory;
    struct Command {
        CommandType type;
        Handle target;
        std::uint64_t seq;      // issue order, across tasks (ties in priority)
        Args args;
        void* user;             // task-side buffer of an XFER
        std::size_t bytes;
        std::size_t offset;     // into the variable
    };
    struct Slot;

    Processor(const Config& config, const Library& library);
    int place() noexcept;
    void run() noexcept;
    Slot* pick() noexcept;
    void execute(const Command& c) noexcept;
    void grant_next_locked();
    void kick() noexcept;

    Config config_;
    std::vector<Library::RoutineEntry> routines_;
    std::vector<Library::VariableEntry> variables_;
    std::vector<std::size_t> offsets_;
    struct AlignedDelete {  // memory_ comes from an over-aligned operator new[]
        std::size_t align;
        void operator()(std::byte* p) const noexcept { ::operator delete[](p, std::align_val_t{align}); }
    };
    std::unique_ptr<std::byte[], AlignedDelete> memory_;
    std::vector<std::unique_ptr<Slot>> slots_;
    Memory view_;

    // The executive's wake-up word: bit 0 says it is (about to be) asleep on
    // this word; the rest counts kicks (new commands, grants, stop) by 2. One
    // word, so that a kick's count and its clearing of the idle bit are one
    // change: a separate flag could be cleared by a kick the executive had
    // already counted, leaving it asleep with every later kick skipping the wake.
    std::atomic<std::uint32_t> work_{0};
    std::atomic<std::uint64_t> next_seq_{1};
    std::atomic<int> owner_{-1};           // slot holding the lock, or -1
    std::atomic<bool> stop_{false};
    std::atomic<std::uint64_t> executed_{0};
    std::atomic<std::uint64_t> faults_{0};
    std::atomic<bool> realtime_{false};
    std::atomic<int> lock_waiters_{0};

    // lock()/release() hand-over and slot allocation. Tasks take it, so it
    // inherits priority; a task waiting for the grant sleeps on its slot's
    // `granted` word (no condition variable: they inherit nothing).
    ipc::PiMutex lock_mutex_;
    std::uint64_t lock_ticket_ = 0;
    std::thread thread_;
};

/// One task's SPP object (§7.4.1): init is the constructor, finish the destructor.
class CHIMERA_API Spp {
public:
    /// Attaches a task of this priority (higher runs first). Throws Error when
    /// TASKS objects are already in use.
    static std::unique_ptr<Spp> init(Processor& processor, int priority);
    ~Spp();  // finish()
    Spp(const Spp&) = delete;
    Spp& operator=(const Spp&) = delete;

    /// Symbolic name → handle; throws Error naming the SPP and the symbol.
    Handle translate(std::string_view name) const;

    // Buffered commands: 0, or -EINVAL (bad handle, range, args), -ENOSPC
    // (command buffer full: wait() and issue again), -EPIPE (after finish).
    [[nodiscard]] int call(Handle routine, const Args& args = {}) noexcept;
    /// XFER task → SPP: `bytes` from `src` into the variable at `offset`.
    /// `src` must stay valid until the command has run (wait()).
    [[nodiscard]] int write(Handle variable, const void* src, std::size_t bytes, std::size_t offset = 0) noexcept;
    /// XFER SPP → task.
    [[nodiscard]] int read(Handle variable, void* dst, std::size_t bytes, std::size_t offset = 0) noexcept;
    /// Issues WAKEUP and blocks until the executive reaches it: every command
    /// issued before has run. 0, or -EPIPE after finish. The buffer keeps an
    /// entry for the WAKEUP beyond its QUEUE commands, so a full buffer is no
    /// obstacle and wait() sleeps at once.
    [[nodiscard]] int wait() noexcept;
    /// Exclusive access for a job; blocks until granted (priority order). A
    /// task locking again after release() waits for that release to run, and
    /// for any higher-priority locker it hands the SPP to.
    void lock();
    /// Buffered end of the job: the lock passes on when the executive reaches it.
    [[nodiscard]] int release() noexcept;
    /// Waits for the commands issued, releases a held lock, detaches.
    void finish() noexcept;

    int priority() const noexcept;

private:
    Spp(Processor& p, int slot) : proc_(&p), slot_(slot) {}
    int push(Processor::Command c) noexcept;
    Processor* proc_;
    int slot_;
    bool locked_ = false;
    bool finished_ = false;
};

}  // namespace chimera::spp
