// Internal structures of the sbs service: the task runtime (TaskCore) and the
// subsystem master (SubsystemCore). Not installed.
#pragma once

#include "chimera/ipc/pi_mutex.hpp"
#include "chimera/ipc/ring.hpp"
#include "chimera/module.hpp"
#include "chimera/muf/rt.hpp"
#include "chimera/prof.hpp"
#include "chimera/sbs.hpp"
#include "chimera/svar.hpp"

#include <atomic>
#include <csetjmp>
#include <cstdint>
#include <memory>
#include <mutex>
#include <pthread.h>
#include <string>
#include <thread>
#include <vector>

namespace chimera::sbs::detail {

class SubsystemCore;
class TaskCore;

/// Finds the C-ABI table of MODULE `name` (in the program, then as
/// <name>.so / lib<name>.so in `dirs`); throws sbs::Error listing what was tried.
const ChimeraModuleAbi& load_module(const std::string& name, const std::vector<std::string>& dirs);
/// Loads the module shared object at `path` (NAME.so or libNAME.so) itself,
/// whatever the module path says; returns NAME. Throws sbs::Error.
std::string load_module_file(const std::string& path);
/// Where spawn looks for the module of `rmod`: `dirs` (add_module_path), the
/// .rmod's folder, the install folder (CHIMERA_MODULE_PATH comes first, in load_module).
std::vector<std::string> module_search_dirs(const RmodFile& rmod, std::vector<std::string> dirs);

/// Criticality from frequency, scaled logarithmically between the RTPU's
/// MINFREQ and MAXFREQ onto 1..62 (0 and 63 reserved, §4.5.1).
int crit_for(const RtpuSpec& r, TaskType type, double freq);

/// Timing-failure counters of a task (thesis §6.3), from its RTPU's scheduler.
struct TimingCounts {
    std::uint64_t deadline = 0, maxexec = 0, minexec = 0, aborted = 0;
};

/// How a task thread is scheduled and paced: its membership in the RTPU's
/// muf::RtpuScheduler (src/muf). One per task, used only by the task thread
/// (counts() and policy() may be read by anyone).
///
/// While the task is not running (spawning, OFF, ERROR, synchronous tasks) its
/// thread is outside the scheduler, at the RTPU's idle level (idle()). start()
/// joins the scheduler (add_task + attach_current_thread, the failure handler
/// installed), stop() leaves it (remove_task + detach), so a task turned off is
/// never released and the RTPU's analysis counts only the tasks that run.
class Pacer {
public:
    virtual ~Pacer() = default;
    /// Pinned to the RTPU's CPU, SCHED_FIFO just below the scheduler's band
    /// (SCHED_OTHER for BACKEND other or without privilege). Returns the policy text.
    /// The text says the idle policy; valid until the next idle(). No allocation:
    /// a task thread calls it when it stops (off, error).
    virtual std::string_view idle() = 0;
    /// The text of the last idle(), without changing anything.
    virtual std::string_view idle_policy() const noexcept = 0;
    /// The task turns on. Throws sbs::Error (e.g. SCHED_DEADLINE admission refused).
    virtual void start() = 0;
    /// The task stops running (off, error, kill); back to idle(). Idempotent.
    virtual void stop() noexcept = 0;
    virtual bool running() const noexcept = 0;
    /// Throws sbs::Error when the scheduler refuses it.
    virtual void set_period(std::int64_t period_ns) = 0;
    /// Periodic: blocks until the next release or until `word` no longer holds
    /// `seen` (a command arrived). Returns true at a release; `missed` is set to
    /// the releases missed since start().
    virtual bool wait(std::atomic<std::uint32_t>& word, std::uint32_t seen, std::uint64_t& missed) noexcept = 0;
    /// The mark an aborted cycle jumps to (nullptr: cycles are not abortable),
    /// armed just before cycle() and disarmed as soon as it returns.
    virtual sigjmp_buf* cycle_mark() noexcept = 0;
    virtual void arm_abort() noexcept = 0;
    virtual void disarm_abort() noexcept = 0;
    /// The release instant of the job wait() just released (CLOCK_MONOTONIC
    /// ns); 0 for aperiodic and synchronous tasks (no release instant).
    virtual std::int64_t release_ns() const noexcept = 0;
    /// After the cycle's out-vars: the job is complete (deadline disarmed).
    virtual void cycle_done() noexcept = 0;
    /// Aperiodic servers: around the service of one event.
    virtual void event_begin() noexcept = 0;
    virtual void event_end() noexcept = 0;
    /// The task's criticality now (0 when not running).
    virtual int crit() const noexcept = 0;
    virtual TimingCounts counts() const noexcept = 0;
    /// What the thread really runs under (policy_of()).
    virtual std::string policy() const = 0;
};
/// The pacer of `task` on its RTPU's scheduler.
std::unique_ptr<Pacer> make_rtpu_pacer(TaskCore& task, muf::RtpuScheduler& scheduler);

/// Master -> task requests, applied by the task thread between method calls.
enum class CmdKind : std::uint8_t { none, on, off, kill, clear, reinit, set, get, freq };

struct Object {
    RmodFile rmod;
    const ChimeraModuleAbi* abi = nullptr;
    Module* module = nullptr;
    std::unique_ptr<Task> view;
};

/// Text of at most N - 1 bytes in place (longer is cut, and then ends with
/// err::kCutMark): an error's module and message are kept so on the task
/// thread, which must not allocate.
template <std::size_t N>
struct FixedText {
    static_assert(N > err::kCutMark.size() + 1);
    char text[N] = {};
    std::size_t size = 0;
    void assign(std::string_view v) noexcept { assign({v}); }
    /// Appends the parts in order (cut at N - 1 bytes).
    void assign(std::initializer_list<std::string_view> parts) noexcept {
        size = 0;
        std::size_t whole = 0;
        for (std::string_view part : parts) {
            size += part.copy(text + size, N - 1 - size);
            whole += part.size();
        }
        if (whole > size) {  // cut: the text says so at its end
            const std::size_t keep = N - 1 - err::kCutMark.size();
            size = keep + err::kCutMark.copy(text + keep, err::kCutMark.size());
        }
        text[size] = '\0';
    }
    void clear() noexcept { assign(std::string_view{}); }
    std::string_view view() const noexcept { return {text, size}; }
};

/// One task: its thread, its objects (one, or several when combined), its
/// local table and the state machine of Figure 3.10.
class TaskCore {
public:
    TaskCore(SubsystemCore& sbs, int id, const RtpuSpec& rtpu, std::vector<RmodFile> rmods);
    ~TaskCore();

    /// Starts the thread and waits for spawn to finish (in-consts, init,
    /// out-consts). Throws sbs::Error when init failed (the task is then
    /// NOT-CREATED and its thread gone).
    void start();
    /// Sends one request and waits for the task to apply it. Returns "" on
    /// success or the failure message. The caller validated the state.
    std::string request(CmdKind kind, std::string arg = {}, std::string key = {}, double hz = 0,
                        std::string* reply = nullptr);
    void join() noexcept;

    // --- identity (immutable after construction) ---
    SubsystemCore& sbs;
    const int id;
    const RtpuSpec rtpu;
    std::string name;  // rmod name, "a+b" for a combined task
    TaskType type = TaskType::periodic;
    std::vector<Object> objects;
    std::vector<std::string> in_consts, out_consts, in_vars, out_vars;  // global names, transferred
    std::vector<std::string> internal;  // combined: produced and consumed inside the task
    // Stands for a process outside the master (module `peer`, sbs.hpp
    // kPeerModule): the runtime copies none of its ports, and its ERROR makes
    // the configuration illegal only while an ON task reads its outputs.
    bool peer = false;

    // --- local table and its transfer sets ---
    std::unique_ptr<svar::LocalTable> local;
    svar::VarSet set_in_consts, set_out_consts, set_in_vars, set_out_vars, set_on;

    // --- state, read by anyone, written by the task thread ---
    // Changed only through set_state(), which mirrors it into the status slot.
    std::atomic<State> state{State::NOT_CREATED};
    std::atomic<State> next_state{State::NOT_CREATED};
    std::atomic<std::int64_t> period_ns{0};
    std::atomic<int> crit{0};
    std::atomic<std::uint64_t> cycles{0}, misses{0};
    std::atomic<std::uint32_t> warnings{0};
    std::atomic<std::uint32_t> signals_sent{0};
    std::atomic<std::uint32_t> sigmask{sig::ALL};
    std::atomic<bool> own_sigmask{false};
    std::atomic<long> tid{0};
    std::atomic<std::int64_t> on_since_ns{0};
    std::atomic<std::int64_t> last_release_ns{0};
    std::atomic<std::int64_t> max_cycle_ns{0};
    std::atomic<std::uint32_t> events{0};  // aperiodic: pending wake-ups
    std::atomic<bool> stopping{false};     // finish/kill in progress for a blocking sync()

    // --- messages: guarded by msg_mu (never held across a method call; the
    // task thread takes it, so it inherits priority: docs/muf.md, Locks) ---
    mutable ipc::PiMutex msg_mu;
    FixedText<160> policy;
    int error_code = 0;
    FixedText<1024> error_text;  // error that put the task in ERROR (or last error)
    FixedText<64> error_module;
    char first_warning[160] = {};  // "" when none; fixed, so a warning never allocates
    // Fixed buffer read by Task::error_message() in the task itself.
    char last_msg[160] = {};
    std::atomic<int> last_num{0};

    // --- request mailbox ---
    // Bumped for every request and event; a process-private futex (the
    // task's one wake-up word, also given to the MUF scheduler's wait).
    std::atomic<std::uint32_t> word{0};
    std::atomic<bool> cmd_pending{false};  // a request waits (read by the loop without a lock)
    // cmd_mu guards the fields below; the task thread answers by bumping
    // `answered` and waking it (a futex: glibc condition variables inherit no
    // priority and the task must never wait on one).
    ipc::PiMutex cmd_mu;
    std::atomic<std::uint32_t> answered{0};
    void wait_answer(const bool& done);
    void tell_master() noexcept;
    CmdKind cmd = CmdKind::none;
    std::string cmd_arg, cmd_key, cmd_reply, cmd_result;
    double cmd_hz = 0;
    bool cmd_done = false;
    bool started = false, start_failed = false;
    std::string start_error;

    // Per-call argument and get() reply, seen by Task::arg()/reply().
    std::string arg;
    std::string reply;
    bool reply_set = false;

    pthread_t thread{};
    bool joinable = false;

    // --- scheduling (set by the master before start(); the pacer lives on the thread) ---
    muf::RtpuScheduler* scheduler = nullptr;
    std::unique_ptr<Pacer> pacer;
    bool abortable = true;  // every object's abortable()

    // --- profiling and the published status (§4.4.1, §6.7) ---
    prof::TaskSlot slot;                  // claimed by the master at spawn, released after the thread ends
    prof::TaskProfiler* profiler = nullptr;  // lives on the task thread's stack while it runs

    void set_state(State s) noexcept;
    /// The policy text of the status (and of the status segment).
    void publish_policy(std::string_view text) noexcept;

private:
    static void* thread_main(void* self) noexcept;
    /// The thread (task_loop.cpp): its set-up, then Figure 3.10 until kill.
    void run();
    /// Leaves the RTPU's scheduler (no more releases) and publishes the idle policy.
    void stop_running() noexcept;
};

/// The subsystem: the .sbs, the global table, the tasks, the signal queue.
class SubsystemCore {
public:
    explicit SubsystemCore(SbsFile f);
    ~SubsystemCore();

    SbsFile file;
    svar::Table table;
    /// One scheduler per RTPU (index as in file.rtpus), created when the first
    /// task is spawned there; declared before `tasks` so it outlives their threads.
    std::mutex schedulers_mu;
    std::vector<std::unique_ptr<muf::RtpuScheduler>> schedulers;
    muf::RtpuScheduler& scheduler(const RtpuSpec& rtpu);  // throws Error
    /// Says once per subsystem that real-time scheduling was refused.
    void warn_no_privilege(const std::string& why) noexcept;
    static constexpr std::uint32_t kMaxTasks = 128;  // status slots; a spawn past them is refused
    prof::StatusSegment status;  // /chimera.<subsystem>.status, read by chimtop and the sbs tool
    int rtpu_index(const RtpuSpec& rtpu) const noexcept;
    std::vector<std::string> module_dirs;

    mutable ipc::PiMutex tasks_mu;  // the error path reads the states under it
    std::vector<std::unique_ptr<TaskCore>> tasks;  // index = TaskId
    TaskCore* task(TaskId id) const;               // throws Error on a bad id

    // Signals task -> master: a lock-free bounded queue; a task never waits
    // for the master. Full, the newest signal is dropped and counted.
    std::atomic<std::uint32_t> wide_mask{sig::ALL};
    void post_signal(TaskCore& from, int signal) noexcept;
    struct Pending {
        int signal;
        int task;
    };
    static constexpr std::size_t kSignalQueue = 256;
    ipc::Ring<Pending, kSignalQueue> signal_queue;
    ipc::Doorbell signal_bell;
    std::atomic<std::uint64_t> signals_dropped{0};

    // The illegal-configuration flag bits in the SVAR table (§3.10).
    static constexpr std::uint32_t kIllegalReconfig = 1u;  // a reconfiguration outlasted a cycle
    static constexpr std::uint32_t kIllegalError = 2u;     // a task is halted in ERROR
    static constexpr std::uint32_t kIllegalTask = 4u;      // set by a task
    ipc::PiMutex flag_mu;
    void set_flag(std::uint32_t bit, bool on) noexcept;
    std::atomic<std::uint64_t> late_reconfigs{0};  // those that raised kIllegalReconfig
    void refresh_error_flag() noexcept;

    // Errors and warnings per the RTPU's ERRPRINT. A task thread only queues
    // its line (no stdio, no allocation, no wait); the reporter thread, not
    // real-time, prints it. A full queue drops the line and counts it; a
    // line longer than a slot is cut and ends with err::kCutMark.
    void print(const RtpuSpec& rtpu, bool is_error, std::initializer_list<std::string_view> parts) noexcept;
    struct Report {
        char text[248];
    };
    ipc::Ring<Report, 64> reports;
    ipc::Doorbell report_bell;
    std::atomic<std::uint64_t> reports_dropped{0};
    std::atomic<bool> reporter_stop{false};
    std::thread reporter;  // last: started after everything it reads
    void report_loop() noexcept;
    void drain_reports() noexcept;

    std::atomic<bool> rt_warned{false};
    bool finished = false;
};

}  // namespace chimera::sbs::detail
