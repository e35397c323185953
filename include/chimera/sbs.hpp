// chimera/sbs.hpp — the subsystem (SBS) master API, thesis §4.2–4.5.
//
// The autonomous-program interface of §4.4.4, one call per thesis routine:
//
//   sbsInit      Subsystem::init(".sbs")     reads the .sbs, creates the SVAR table
//   sbsSpawn     spawn(rmod, rtpu)            NOT-CREATED -> (in-consts, init, out-consts) -> OFF
//   sbsControl   control(task, Control::on)   on / off / kill / clear, synchronous
//   sbsReconfig  reconfig({...})              ordered list; stops at the first failure
//   sbsFreqGet/Set, sbsGet/Set, sbsStatus/StatusAll, sbsSigWait, sbsFinish
//
//     // From the top of the tree; the modules' .so are found through
//     // CHIMERA_MODULE_PATH or add_module_path() (build/modules/...) or installed.
//     auto sbs = chimera::sbs::Subsystem::init("examples/fig3_7_pid/fig3_7.sbs");
//     auto robot = sbs->spawn("modules/robotsim/puma_torque.rmod", "robot");  // first: NDOF, DH
//     auto traj = sbs->spawn("modules/trajgen/jtraj.rmod", "ctrl");           // configure from them
//     auto pid = sbs->spawn("modules/pid/jpid.rmod", "ctrl");
//     auto r = sbs->reconfig({{robot, Control::on}, {traj, Control::on}, {pid, Control::on}});
//     if (!r) throw chimera::sbs::Error(r.message);  // which item failed, and why
//     std::this_thread::sleep_for(2s);
//     for (auto& s : sbs->status_all()) std::cout << format_status(s) << '\n';
//     sbs->finish();
//
// Each task is one pthread pinned to its RTPU's CPU. A control signal is
// checked against the task's state machine (Figure 3.10) by the master; an
// invalid one (on to an ON task, clear to a task not in ERROR, ...) is refused
// with sbs::Refused and the task is untouched. A valid one is applied by the
// task between method calls, and control() returns when it has been.
//
// Module path: a MODULE name is first looked up in the running program (modules
// linked in), then as `<name>.so` / `lib<name>.so` in: the folders of the
// CHIMERA_MODULE_PATH environment variable (colon-separated), folders added
// with add_module_path(), the .rmod's own folder, and the installed module
// folder.
//
// Scheduling (thesis ch. 6, docs/architecture.md §9): each RTPU of the .sbs
// gets one muf::RtpuScheduler, made when its first task is spawned, with the
// policy of its SCHEDULER line (RM, EDF or MUF) and the backend of its BACKEND
// key (fifo: a dispatcher gives the task threads SCHED_FIFO priorities 10..79
// in urgency order; deadline: SCHED_DEADLINE reservations for the critical set;
// other: SCHED_OTHER, best effort).
//  - A periodic task joins the scheduler when it is turned on and leaves it
//    when it stops running (off, error, kill): a task that is not ON is never
//    released and does not count in the RTPU's analysis. Its period is the
//    .rmod's FREQ/PERIOD (freq_set: from the next release), its C the .rmod's
//    WCET, its E the EFFECTIVE of a soft task, its criticality the CRIT line or
//    the MUF assignment. Without WCET, C is taken as 0: every task is then in
//    the critical set (crit 5 under MUF) and no MAXEXEC budget is armed; give
//    WCET to let the analysis choose the critical set and to have cycles that
//    overrun their budget reported. The first release comes one period after on.
//  - Missed releases (late, skipped, or aborted by a handler) are the task's
//    misses; DEADLINE/MAXEXEC/MINEXEC failures go to the modules'
//    timing_failure() (module.hpp) and are counted in the status.
//  - Aperiodic tasks serve their events under a server (§6.5, servers of the
//    runtime built on the public muf API only): TASKTYPE deferrable or sporadic
//    with PERIOD (or FREQ) and WCET is the MUF deferrable / sporadic server of
//    capacity WCET per period (criticality 6 while it has capacity, 4 when it is
//    used up); background, or a sporadic/deferrable task without them, runs at
//    criticality 2, below every periodic task.
//  - Synchronous tasks, and every task thread while not running (spawning, OFF,
//    ERROR), stay pinned at SCHED_FIFO 9, just below the scheduler's band.
// Without real-time privilege the subsystem says so once on stderr and runs
// best effort; status shows the policy each task really got.
#pragma once

#include "chimera/export.hpp"

#include <chimera/module.hpp>
#include <chimera/prof.hpp>
#include <chimera/sbs_files.hpp>

#include <chrono>
#include <cstdint>
#include <initializer_list>
#include <memory>
#include <optional>
#include <span>
#include <stdexcept>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

namespace chimera::sbs {

/// The MODULE of a peer task: a stand-in for a process outside the master (a
/// Python program, like a LinuxCNC HAL user-space component) that reads and
/// writes the table itself in its own non-real-time loop. Its .rmod declares
/// what the process consumes (INVAR) and produces (OUTVAR), so §3.3.1
/// verification and status see it like any task, but the runtime copies none
/// of its ports: the process's own writes are never overwritten by the task.
inline constexpr std::string_view kPeerModule = "peer";

/// A task of the subsystem; ids are never reused within a subsystem.
struct TaskId {
    int value = -1;
    explicit operator bool() const noexcept { return value >= 0; }
    friend bool operator==(TaskId, TaskId) = default;
};

/// Control signals master -> task (sbsControl).
enum class Control : std::uint8_t { on, off, kill, clear };
CHIMERA_API std::string_view to_string(Control c) noexcept;

/// Any failure of a master call; what() names the task/file and the reason.
class CHIMERA_API Error : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};
/// A signal invalid for the task's current state (nothing happened).
class CHIMERA_API Refused : public Error {
public:
    using Error::Error;
};
/// §3.3.1 verification failed: the variable and the modules are named.
class CHIMERA_API VerifyError : public Error {
public:
    using Error::Error;
};

/// The last folders of the module path: the installed module folder or,
/// while the running program lives in the build tree it was built in, that
/// tree's module folders instead (build/modules/* and the source's modules/*),
/// so `build/tools/sbs/sbs FILE.sbs` finds the modules built with it, never an
/// earlier install's. CHIMERA_MODULE_PATH and --module-path /
/// add_module_path() come before them.
CHIMERA_API std::vector<std::string> default_module_dirs();

/// No module of that name on the module path (it may be elsewhere: see module_local_keys).
class CHIMERA_API ModuleNotFound : public Error {
public:
    using Error::Error;
};

/// The LOCAL keys that MODULE `rmod.module` declares, the module loaded as
/// spawn loads it (CHIMERA_MODULE_PATH, `module_dirs`, the .rmod's folder, the
/// install folder) — so its constructors run. For `chimcfg check`, which then
/// runs check_local_section() as spawn does. Throws ModuleNotFound, or Error
/// for a module found but not loadable.
CHIMERA_API std::vector<LocalKey> module_local_keys(const RmodFile& rmod, const std::vector<std::string>& module_dirs);

/// One item of sbsReconfig.
struct ReconfigItem {
    ReconfigItem() = default;
    ReconfigItem(TaskId t, Control s, std::string a = {}) : task(t), signal(s), arg(std::move(a)) {}
    TaskId task;
    Control signal = Control::on;
    std::string arg;  ///< passed to the method as task.arg()
};

/// One violation of §3.3.1 in a configuration (Subsystem::verification_problems).
struct VerifyProblem {
    enum class Kind { two_producers, no_producer };
    Kind kind = Kind::no_producer;
    std::string variable;
    std::vector<std::string> tasks;  ///< the two producers, or the reader with no producer
    std::string message;             ///< as verify() / VerifyError says it
};

/// Result of reconfig(): ok, or the index of the item that failed and why.
/// Items before `failed` were applied; it and those after it were not sent.
struct [[nodiscard]] ReconfigResult {
    bool ok = true;
    std::size_t processed = 0;  ///< items applied
    std::size_t failed = 0;     ///< index of the failing item (when !ok)
    std::string message;        ///< "item 2 (on pid): ..." when !ok
    explicit operator bool() const noexcept { return ok; }
};

/// sbsStatus: the fields of §4.4.1 the runtime knows.
struct TaskStatus {
    TaskId id;
    std::string rmod;     ///< rmod name ("a+b" for a combined task)
    std::string module;
    std::string rtpu;
    int cpu = -1;
    long tid = 0;         ///< Linux thread id
    char type = 'P';      ///< P periodic, Y synchronous, S sporadic, D deferrable, B background
    int crit = 0;
    State state = State::NOT_CREATED;
    std::uint64_t cycles = 0;   ///< since turned on
    std::uint64_t misses = 0;   ///< deadlines missed: jobs late or aborted, releases skipped
    /// Timing failures seen by the RTPU's scheduler (§6.3) since the task was
    /// spawned; for a server, DEADLINE is its replenishment time and MAXEXEC its
    /// capacity used up.
    std::uint64_t deadline_failures = 0, maxexec_failures = 0, minexec_failures = 0;
    std::uint64_t aborted = 0;  ///< cycles abandoned by a timing_failure() answer
    double ref_freq = 0, ref_period = 0;
    double mez_freq = 0;        ///< measured cycles per second since turned on
    double mez_period = 0;      ///< mean measured period between releases
    double max_cycle_time = 0;  ///< seconds, wall time of the longest cycle (in-vars..out-vars)
    std::uint32_t warnings = 0;
    std::string warning;        ///< first warning since the last status() call
    int error_code = 0;
    std::string error;          ///< message of the error that put the task in ERROR
    std::string policy;         ///< scheduling the thread really got, e.g. "SCHED_FIFO 42"
    /// The profile the task publishes in the status segment (§4.4.1, §6.7):
    /// ptime, totC, minC/maxC/avgC, minU/maxU/avgU, mezT, the CPU-time source...
    /// Its counters run "since the last reset" of the task's RTPU.
    prof::TaskStatus profile;
};

/// "rmod rtpu tid S crit state cycle miss refF mezF ..." in one line, plus
/// WARNING> / ERROR> lines as §4.4.1 prints them. Times in µs (the header
/// says "[us]"), with the release lateness's 99th percentile (latP99).
CHIMERA_API std::string format_status(const TaskStatus& s);
/// The column header matching format_status().
CHIMERA_API std::string format_status_header();

/// How an RTPU's scheduler ranks its tasks, and the work that costs (docs/muf.md,
/// "Static ranking" / "Dynamic ranking"): under dynamic ranking (non-harmonic
/// periods, deadlines shorter than periods) the dispatcher re-ranks at each
/// release and changes the priorities that move — counted here, apart from the
/// tasks' own system calls.
struct RtpuRanking {
    std::string rtpu;
    /// "none" (no task spawned there yet), "static" (one SCHED_FIFO priority per
    /// task for good), "dynamic" (re-ranked at each release) or "best-effort"
    /// (backend other, or no real-time privilege: no priorities at all).
    std::string mode = "none";
    std::uint64_t reschedules = 0;       ///< urgency recomputations by the dispatcher
    std::uint64_t priority_changes = 0;  ///< priorities it changed
};

/// A signal received by sig_wait().
struct SignalEvent {
    int signal = -1;
    TaskId task;
    std::string rmod;
};

namespace detail {
class SubsystemCore;
}

class CHIMERA_API Subsystem {
public:
    /// sbsInit: reads the .sbs, creates the subsystem's SVAR table from its
    /// SVARFILE. Throws cfg::ParseError (FILE:LINE:) or sbs::Error.
    static std::unique_ptr<Subsystem> init(const std::string& sbs_path);
    /// Same from a parsed file.
    static std::unique_ptr<Subsystem> init(SbsFile file);
    /// sbsFinish if not done.
    ~Subsystem();
    Subsystem(const Subsystem&) = delete;
    Subsystem& operator=(const Subsystem&) = delete;

    const SbsFile& file() const noexcept;
    const std::string& name() const noexcept;

    /// Adds a folder to search for module shared objects.
    void add_module_path(std::string dir);
    /// Loads the module shared object at `path` (NAME.so or libNAME.so: its
    /// constructors run) and adds its folder to the module path, so a .rmod
    /// naming MODULE NAME spawns from it. Returns NAME. Throws sbs::Error (not a
    /// module, another module NAME already loaded from elsewhere).
    std::string load_module(const std::string& path);

    /// sbsSpawn: creates a task from a .rmod on an RTPU (empty: the MASTER
    /// RTPU), runs in-consts, init, out-consts and returns once the task is
    /// OFF. Throws sbs::Error (bad file, module not found, init failed — the
    /// task is then NOT-CREATED) or VerifyError (an in-const nobody produces).
    TaskId spawn(const std::string& rmod_path, std::string_view rtpu = {});
    /// A combined task (§3.8.1): several objects, one thread, one local table;
    /// their methods run in the order given. Ports one object produces and
    /// another consumes stay in the local table (never copied to the global
    /// one). All must have the same TASKTYPE and frequency.
    TaskId spawn_combined(const std::vector<std::string>& rmod_paths, std::string_view rtpu = {});
    /// spawn / spawn_combined from .rmod contents already parsed, or made in
    /// memory by a program (the `sample` command's sampler task): the same
    /// checks, the same life. The task's name is the (joined) RmodFile names.
    TaskId spawn_parsed(std::vector<RmodFile> rmods, std::string_view rtpu = {});

    /// Looks a task up by rmod name (the latest one created with that name).
    [[nodiscard]] std::optional<TaskId> find(std::string_view rmod) const;

    /// sbsControl: applies one signal and waits until the task has done it.
    /// Throws Refused when invalid for the state, VerifyError when turning the
    /// task on would give one variable two producers, Error when the method
    /// failed (the task's new state is then in status()).
    void control(TaskId task, Control signal, std::string_view arg = {});

    /// sbsReconfig: verifies the configuration that would result (§3.3.1,
    /// both equations, over the tasks ON afterwards), applies the items in
    /// order and stops at the first failure. One that takes longer than a
    /// cycle (the period of the fastest periodic task ON before or after it)
    /// raises the illegal-configuration flag when that cycle has passed and
    /// lowers it at its end (§3.10); one done within the cycle raises nothing;
    /// with no periodic task, the flag is up for the whole reconfiguration.
    ReconfigResult reconfig(std::span<const ReconfigItem> items);
    ReconfigResult reconfig(std::initializer_list<ReconfigItem> items) {
        return reconfig(std::span<const ReconfigItem>(items.begin(), items.size()));
    }

    /// §3.3.1 over a set of tasks: throws VerifyError naming the variable and
    /// the modules when two produce one variable or an input has no producer.
    void verify(std::span<const TaskId> tasks) const;
    /// The same check, every violation (verify() throws the first), for a
    /// view that marks them all; empty when the set verifies.
    std::vector<VerifyProblem> verification_problems(std::span<const TaskId> tasks) const;
    /// The violations of the configuration reconfig(items) would leave (the
    /// check reconfig() runs before sending anything); nothing is sent.
    /// Throws Error for an item naming no task.
    std::vector<VerifyProblem> reconfig_problems(std::span<const ReconfigItem> items) const;
    std::vector<VerifyProblem> reconfig_problems(std::initializer_list<ReconfigItem> items) const {
        return reconfig_problems(std::span<const ReconfigItem>(items.begin(), items.size()));
    }

    /// sbsFreqGet / sbsFreqSet (Hz; takes effect at the next release).
    double freq_get(TaskId task) const;
    void freq_set(TaskId task, double hz);

    /// sbsGet / sbsSet: the LOCAL configuration of the task, through the
    /// module's get()/set() (applied between method calls).
    /// set() first checks the modules' declared LOCAL keys (module.hpp,
    /// LocalKey) and throws Refused naming the key and the reason: unknown,
    /// read only at spawn, wrong type or count, out of range. get() of a
    /// declared key absent from LOCAL answers its declared default.
    std::string get(TaskId task, std::string_view key);
    void set(TaskId task, std::string_view key, std::string_view value);
    /// The LOCAL keys the task's modules declare (all objects of a combined task, in order).
    std::vector<LocalKey> local_keys(TaskId task) const;

    /// Wakes an aperiodic (sporadic, deferrable, background) task: one cycle
    /// per event. Callable from any thread, real-time safe.
    void event(TaskId task) noexcept;

    /// sbsStatus / sbsStatusAll (live tasks, creation order).
    TaskStatus status(TaskId task) const;
    /// The task's state alone (status() also hands over its first warning).
    State state(TaskId task) const;
    std::vector<TaskStatus> status_all() const;
    /// Each RTPU of the .sbs in file order: its ranking mode and dispatcher counts.
    std::vector<RtpuRanking> rtpu_ranking() const;

    /// Signal masks: bits set are the signals the master catches. A task whose
    /// own mask was never set uses the subsystem-wide mask (initially ALL).
    void set_sigmask(std::uint32_t mask);
    void set_sigmask(TaskId task, std::uint32_t mask);
    void clear_task_sigmask(TaskId task);

    /// sbsSigWait: the oldest caught signal whose bit is in `wanted` (from
    /// `from` only, if given); caught signals that do not match are discarded.
    /// nullopt on timeout (a negative timeout waits forever).
    [[nodiscard]] std::optional<SignalEvent> sig_wait(std::uint32_t wanted = sig::ALL, std::optional<TaskId> from = {},
                                        std::chrono::nanoseconds timeout = std::chrono::nanoseconds(-1));
    /// sbsSigSend from the master side (for drivers and tests).
    void sig_send(TaskId from, int signal);

    /// The illegal-configuration flag (§3.10).
    bool illegal_configuration() const noexcept;
    /// Reconfigurations that outlasted their cycle (and so raised the flag).
    std::uint64_t late_reconfigs() const noexcept;

    /// sbsFinish: turns every ON task off, kills every task, joins the threads,
    /// removes the shared segments. Idempotent.
    void finish();

    /// For the runtime.
    explicit Subsystem(std::unique_ptr<detail::SubsystemCore> core);

private:
    TaskStatus status_without_profile(TaskId task) const;
    std::unique_ptr<detail::SubsystemCore> core_;
};

}  // namespace chimera::sbs
