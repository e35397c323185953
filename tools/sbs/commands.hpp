// tools/sbs/commands.hpp — the commands of the `sbs` command line (thesis
// §4.4.1), run against a subsystem this process is the master of. The prompt,
// `-c` scripts and the network server all call Interpreter::execute(), so a
// command means the same thing wherever it is typed.
#pragma once

#include "command_table.hpp"
#include "reply.hpp"

#include <chimera/muf/analysis.hpp>
#include <chimera/prof.hpp>
#include <chimera/sbs.hpp>
#include <chimera/svar.hpp>

#include <map>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <string_view>
#include <vector>

namespace chimera::cli {

/// The status fields of §4.4.1 (plus the Linux additions) that `status set`
/// may choose from, in display order.
const std::vector<std::string>& status_field_names();

/// The fields `status` shows until `status set` picks others.
const std::vector<std::string>& default_status_fields();

/// The reply of `status`: a line per task with `fields` (times in µs), its
/// WARNING>/ERROR> lines, and the JSON of every field. `reset`: say that
/// profiling restarted for every reader.
Reply status_reply(const std::string& subsystem, const std::vector<sbs::TaskStatus>& rows,
                   const std::vector<std::string>& fields, bool reset);

/// A variable `display` shows: `dir` ("in", "out-const"...; "" for the whole table).
struct VarItem {
    std::string dir;
    std::string name;
};
/// The reply of `display`: each variable's type, values and units, read from
/// `t` (a watcher's table reads without the lock); `who`: the task whose
/// ports they are ("" for the table).
Reply values_reply(svar::Table& t, const std::vector<VarItem>& items, const std::string& who);

/// Who sent a command. A network peer may name only .rmod files on the
/// module path the master was started with (never a path, never the working
/// folder), so it cannot get a library of its own choosing loaded.
/// The web console (--http) is a network origin with its own status window
/// that leaves the prompt's default RMOD alone. Neither makes a file be
/// written: save and record are refused, and so are spawn, on and reconfig on
/// of a task whose module declares an output file (docs/permissions.md).
enum class Origin { local, network, web };

/// What clients (Origin network and web) may have the master allocate in
/// sampler rings (docs/permissions.md): one ring, all their rings, and how
/// many samplers they run at once (each is a task thread).
inline constexpr std::size_t kMaxClientRingBytes = std::size_t{32} << 20;
inline constexpr std::size_t kMaxClientRingsBytes = std::size_t{128} << 20;
inline constexpr std::size_t kMaxClientSamplers = 8;

class Interpreter {
public:
    /// `module_dirs`: folders added with --module-path (already given to the
    /// subsystem with add_module_path()).
    Interpreter(sbs::Subsystem& subsystem, std::vector<std::string> module_dirs);

    /// Runs ONE command (no `;`). Never throws: failures are replies.
    Reply execute(std::string_view command, Origin origin = Origin::local);

    /// The default RMOD: the one the last command was directed to (§4.4.1).
    const std::string& default_rmod() const noexcept { return default_rmod_; }
    /// "SBS <subsystem><<rmod>> ".
    std::string prompt() const;

    /// Completion candidates for the last (partial) word of `line`, already
    /// filtered by that word as a prefix and sorted.
    std::vector<std::string> complete(std::string_view line);
    /// The same, with mutex_ held.
    std::vector<std::string> complete_locked(std::string_view line);

    /// Every folder searched for modules and .rmod files, in search order:
    /// CHIMERA_MODULE_PATH, --module-path, the .sbs's folder, the installed folder.
    std::vector<std::string> module_path() const;

    /// Spawns the .sbs's TASK lines in file order (each one's SET lines
    /// applied after its spawn), then turns on those marked ON in one
    /// reconfig. On a failure it kills what it spawned and the reply's error
    /// starts with FILE:LINE of the TASK or SET line.
    Reply start_tasks();

    /// Lets go of the shared segments this interpreter mapped, so the
    /// subsystem's finish() (their last user) removes them.
    void detach();

private:
    using Words = std::vector<std::string>;
    Reply run(const Words& w);
    Reply cmd_spawn(const Words& w);
    Reply cmd_control(const Words& w, sbs::Control signal);
    /// Throws for a network origin when `keys` declare an output file.
    void refuse_file_writer(const std::string& command, const std::string& task,
                            const std::vector<LocalKey>& keys) const;
    Reply cmd_set(const Words& w);
    Reply cmd_status(const Words& w);
    Reply cmd_display(const Words& w);
    Reply cmd_module(const Words& w);
    Reply cmd_reconfig(const Words& w);
    Reply cmd_freq(const Words& w);
    Reply cmd_event(const Words& w);
    Reply cmd_help(const Words& w);
    Reply cmd_sample(const Words& w);
    double producers_rate(const std::vector<std::string>& vars, std::string& why) const;
    const RtpuSpec& sampler_rtpu(const std::string& name) const;
    std::set<std::string> tasks_on() const;
    std::vector<muf::TaskSpec> analysed_tasks(const std::string& rtpu) const;
    std::vector<muf::TaskSpec> analysed_tasks(const std::string& rtpu, const std::set<std::string>& on) const;
    /// Issue #29.2: "" when `task` at `hz` may run on `rtpu` beside `running`
    /// (null: only its rate is checked). A client is refused (CommandError,
    /// "WHAT refused: ..."); the owner gets the warning line it returns.
    std::string admit(const std::string& what, const std::string& rtpu, const muf::TaskSpec& task, double hz,
                      const std::vector<muf::TaskSpec>* running, const std::string& hint = {}) const;
    /// admit() for a task about to be spawned from `f` on `rtpu` ("": the MASTER RTPU).
    std::string admit_spawn(const std::string& name, const RmodFile& f, const std::string& rtpu) const;
    /// admit() for turning on task `name` while the tasks `on` are ON.
    std::string admit_on(const std::string& what, const std::string& name, const std::set<std::string>& on) const;
    /// admit() for `freq NAME HZ`.
    std::string admit_freq(const std::string& name, double hz) const;
    /// admit() for the items of a reconfig, in order (an off or kill frees its share first).
    std::string admit_reconfig(const std::vector<std::vector<std::string>>& groups) const;
    void admit_sampler(const RtpuSpec& spec, const std::string& name, double rate, std::size_t channels) const;
    static std::size_t ring_entries(const std::string& capacity, double rate);
    void bound_client_rings(std::size_t bytes);
    std::string free_sampler_name();
    sbs::TaskId spawn_on(const RmodFile& f, const std::string& rtpu);
    Reply cmd_peer(const Words& w);
    /// Peer tasks whose process is gone are woken to find out (their task
    /// goes to ERROR): run before every command, so verification never counts
    /// a dead process as a producer.
    void check_peers();

    /// The task named `rmod` (or the default one when empty); throws
    /// std::runtime_error naming what is wrong. Makes it the default RMOD.
    sbs::TaskId task_of(const std::string& rmod);
    bool is_task(std::string_view name) const;
    /// Makes `name` the default RMOD, the one before it the previous.
    void make_default(const std::string& name);
    /// Drops a task that is gone; when it was the default, the previous
    /// default (if it still exists) or none becomes the default.
    void forget_task(const std::string& name);
    std::vector<std::string> live_rmods() const;
    /// A .rmod file for `name`: a path, or NAME[.rmod] in the module path.
    std::optional<std::string> find_rmod_file(const std::string& name) const;
    svar::Table* table();
    std::vector<std::string> local_keys(const std::string& rmod) const;
    Reply local_view(sbs::TaskId id);
    Reply cmd_show(const Words& w);
    Reply show_graph();
    Reply reconfig_check(const std::vector<sbs::ReconfigItem>& items, const std::vector<std::string>& names);
    Reply cmd_setvar(const Words& w);
    Reply cmd_save(const Words& w);
    Reply module_load(const Words& w);
    std::string saved_sbs() const;
    std::vector<std::string> saved_tasks() const;
    void check_saved_starts(const SbsFile& saved, const std::vector<std::string>& names);
    struct Users {
        std::vector<std::string> producers, consumers;  // live tasks writing / reading a variable
    };
    Users users_of(const std::string& name) const;

    sbs::Subsystem& sbs_;
    std::vector<std::string> extra_dirs_;
    std::string default_rmod_;
    std::string previous_rmod_;  // the default before it: the default again when it is killed
    std::vector<std::string> fields_;
    std::map<std::string, RmodFile> rmods_;  // rmod name -> the file it was spawned from
    std::map<std::string, std::string> rtpu_of_;  // rmod name -> its RTPU (rmods_ says which are live)
    std::map<std::string, std::vector<std::string>> files_of_;  // rmod name -> the .rmod paths it was spawned from
    std::optional<svar::Table> table_;
    std::optional<prof::StatusReader> prof_;
    /// "Since the last status" per interface (issue 16.4), indexed by Origin:
    /// [0] the prompt and -c scripts, [1] the network peer in control, [2] the web console.
    prof::StatusWindow windows_[3];
    Origin origin_ = Origin::local;  // of the command being executed
    unsigned samplers_made_ = 0;     // `sample` names its tasks sample.1, sample.2, ...
    std::map<std::string, std::size_t> client_rings_;  // sampler made by a client -> its ring's bytes
    std::mutex mutex_;  // one command at a time, whichever interface sent it
};

}  // namespace chimera::cli
