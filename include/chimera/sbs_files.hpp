// chimera/sbs_files.hpp — the .rmod (thesis §3.8) and .sbs (§4.5.1) files.
//
// Both are read with chimera::cfg::Reader (DEFINE, `#` comments, final EOF);
// every error is a cfg::ParseError whose what() reads `FILE:LINE: message`, and
// nothing is returned from a bad file.
//
// .rmod — one reconfigurable module (keywords in this order; [] = optional):
//
//   MODULE    name                 C++ module (its CHIMERA_MODULE name)
//   DESC      one line of text
//   [SVARALIAS internal=GLOBAL]    any number; renames a port (Z=Q_MEZ)
//   [INCONST  name... | none]      absent is the same as `none`
//   [OUTCONST name... | none]
//   [INVAR    name... | none]
//   [OUTVAR   name... | none]
//   TASKTYPE  periodic | synchronous | sporadic | deferrable | background
//   FREQ hz  |  PERIOD seconds     exactly one of them; required for periodic and
//                                  synchronous tasks, optional for aperiodic ones
//                                  (their server period)
//   [WCET seconds]                 C, the worst-case execution time: the MAXEXEC
//                                  budget of each cycle and the analysis's C; for a
//                                  sporadic or deferrable server, its capacity.
//                                  Absent: 0, which puts the task in the critical
//                                  set and arms no budget (see sbs.hpp).
//   [EFFECTIVE seconds]            E of a guaranteed soft real-time task (§6.4,
//                                  periodic only): the analysis reserves E, not C;
//                                  past E the task drops to criticality 3 until its
//                                  deadline (Listing 2).
//   [CRIT n]                       explicit MUF criticality 1..62 (§6.2.3); else
//                                  the analysis assigns it
//   [LOCAL]                        free `KEY value...` lines up to EOF, read by the
//                                  module (module-dependent configuration)
//   EOF
//
// Port names in INCONST..OUTVAR are the module's internal names; SVARALIAS maps
// them onto the global table's names (an unaliased name is used as is).
//
// .sbs — one subsystem:
//
//   SUBSYSTEM name
//   SVARFILE  file.svar            relative paths are taken from the .sbs's folder
//   [MASTER   rtpu]                the RTPU hosting the SBS interface (default:
//                                  the first RTPU)
//   then one block per RTPU, each starting with
//   RTPU      name [cpu]           cpu: the Linux CPU number the RTPU stands for.
//                                  When omitted the name must be `cpuN` (CPU N).
//   followed, in any order, each at most once, by
//   [SCHEDULER RM | EDF | MUF]           default MUF
//   [USAGE     exclusive | shared]       default exclusive
//   [ERRPRINT  errors | warnings | none] default warnings
//   [MINFREQ   hz]                       default 1.0
//   [MAXFREQ   hz]                       default 1000.0 (must exceed MINFREQ)
//   [BACKEND   fifo | deadline | other]  Linux scheduling backend
//                                        (docs/architecture.md §9);
//                                        `other` runs best-effort (SCHED_OTHER);
//                                        default fifo
//   [ACCOUNTING nanoseconds | halftick TICK]  how the RTPU's tasks' CPU time is
//                                        profiled (§6.7): to the nanosecond (default),
//                                        or quantised in half-ticks of a TICK-second
//                                        clock, as the thesis measured (prof.hpp)
//   EOF
#pragma once

#include "chimera/export.hpp"

#include <chimera/cfg.hpp>

#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

namespace chimera {

/// TASKTYPE of a .rmod file.
enum class TaskType : std::uint8_t { periodic, synchronous, sporadic, deferrable, background };

/// "periodic", ...; and the one-letter status code of §4.4.1 (P, Y, S, D, B).
CHIMERA_API std::string_view to_string(TaskType t) noexcept;
CHIMERA_API char status_letter(TaskType t) noexcept;
/// True for sporadic, deferrable and background: woken by an event, not a clock.
inline bool is_aperiodic(TaskType t) noexcept {
    return t == TaskType::sporadic || t == TaskType::deferrable || t == TaskType::background;
}

/// The LOCAL section of a .rmod: free `KEY value...` lines, in file order.
/// Keys are unique. Values are kept as text (DEFINEs substituted).
class CHIMERA_API LocalConfig {
public:
    struct Entry {
        std::string key;
        std::vector<std::string> values;  ///< whitespace-separated tokens
        int line = 0;                     ///< line in the .rmod (0 when set at run time)
    };

    bool has(std::string_view key) const noexcept { return find(key) != nullptr; }
    const Entry* find(std::string_view key) const noexcept;
    /// All values of `key`, joined by one space; nullopt when absent.
    [[nodiscard]] std::optional<std::string> text(std::string_view key) const;
    /// The values of `key` as numbers. Throws std::invalid_argument naming the
    /// file, line and key when absent or not numeric.
    std::vector<double> numbers(std::string_view key) const;
    /// The single numeric value of `key`, or `fallback` when the key is absent;
    /// throws std::invalid_argument when present but not one number.
    double number(std::string_view key, double fallback) const;
    /// Replaces (or adds) `key` (used by sbsSet; `line` 0 for run-time values).
    void set(std::string_view key, std::vector<std::string> values, int line = 0);
    /// Removes `key` (nothing when absent).
    void erase(std::string_view key);
    const std::vector<Entry>& entries() const noexcept { return entries_; }

    std::string file;  ///< the .rmod, for messages

private:
    std::vector<Entry> entries_;
};

/// The frequencies a task may run at, from a .rmod's FREQ/PERIOD or `freq`:
/// a period of 1 µs (what a timer wake-up can still mean) to 10^6 s.
inline constexpr double kMinFrequencyHz = 1e-6;
inline constexpr double kMaxFrequencyHz = 1e6;
/// Why `hz` is not a task frequency ("" when it is): one check for the
/// .rmod reader (so chimcfg check), spawn and Subsystem::freq_set.
CHIMERA_API std::string frequency_problem(double hz);

/// A parsed .rmod file.
struct CHIMERA_API RmodFile {
    std::string path;    ///< as opened
    std::string name;    ///< the rmod name: the file name without folder and `.rmod`
    std::string module;  ///< MODULE
    std::string desc;    ///< DESC
    std::vector<std::pair<std::string, std::string>> aliases;  ///< internal -> global
    std::vector<std::string> in_consts, out_consts, in_vars, out_vars;  ///< internal names
    TaskType type = TaskType::periodic;
    double freq = 0.0;    ///< Hz (0 for an aperiodic task without FREQ/PERIOD)
    double period = 0.0;  ///< seconds, always 1/freq when freq > 0
    double wcet = 0.0;       ///< WCET, seconds (0: not given)
    double effective = 0.0;  ///< EFFECTIVE, seconds (0: a hard task, E = C)
    std::optional<int> crit; ///< CRIT
    LocalConfig local;

    /// The global SVAR name of an internal port name (SVARALIAS applied).
    std::string global_name(std::string_view internal) const;
    /// The four lists with SVARALIAS applied.
    std::vector<std::string> global_in_consts() const;
    std::vector<std::string> global_out_consts() const;
    std::vector<std::string> global_in_vars() const;
    std::vector<std::string> global_out_vars() const;
};

/// Why the ports of `f` do not fit a table ("" when they do): every
/// INCONST, OUTCONST, INVAR and OUTVAR (SVARALIAS applied) names a variable
/// for which `is_variable` is true; `svarfile` names the table in the
/// message. One check for spawn and chimcfg check.
CHIMERA_API std::string port_problem(const RmodFile& f, const std::function<bool(const std::string&)>& is_variable,
                                     std::string_view svarfile);

/// Why `rmods` cannot be one combined task ("" when they can): its objects
/// run at one rate and task type (§3.8.1). For spawn and chimcfg check.
CHIMERA_API std::string combined_problem(const std::vector<RmodFile>& rmods);

/// Reads a .rmod; throws cfg::ParseError.
CHIMERA_API RmodFile read_rmod(const std::string& path);
/// Parses from a reader (for text held in memory); `path` names the rmod.
CHIMERA_API RmodFile parse_rmod(cfg::Reader& reader, const std::string& path);

enum class Scheduler : std::uint8_t { RM, EDF, MUF };
enum class Usage : std::uint8_t { exclusive, shared };
enum class ErrPrint : std::uint8_t { errors, warnings, none };
enum class Backend : std::uint8_t { fifo, deadline, other };

CHIMERA_API std::string_view to_string(Scheduler s) noexcept;
CHIMERA_API std::string_view to_string(Usage u) noexcept;
CHIMERA_API std::string_view to_string(ErrPrint e) noexcept;
CHIMERA_API std::string_view to_string(Backend b) noexcept;

/// One RTPU block of a .sbs file.
struct RtpuSpec {
    std::string name;
    int cpu = 0;  ///< Linux CPU number
    Scheduler scheduler = Scheduler::MUF;
    Usage usage = Usage::exclusive;
    ErrPrint errprint = ErrPrint::warnings;
    double minfreq = 1.0;
    double maxfreq = 1000.0;
    Backend backend = Backend::fifo;
    bool half_tick = false;  ///< ACCOUNTING halftick
    double tick = 0.001;     ///< its tick, seconds
    int line = 0;  ///< line of the RTPU keyword
};

/// A TASK line of a .sbs, with the SET lines under it: a task the `sbs` tool
/// spawns when it starts the subsystem (an addition to the thesis's .sbs,
/// §4.5.1, so that `save` can write a running configuration back; see
/// docs/cli.md). The library parses it; a program using Subsystem directly
/// spawns what it wants itself.
struct TaskLine {
    struct Set {
        std::string key;
        std::vector<std::string> values;
        int line = 0;
    };
    std::vector<std::string> rmods;  ///< one rmod, or the objects of a combined task (a+b+c, §3.8.1)
    std::string rtpu;                ///< "" : the MASTER RTPU
    bool on = false;                 ///< ON: turned on after every TASK line is spawned
    std::vector<Set> local;          ///< SET KEY VALUE...: LOCAL values given before it is turned on
    int line = 0;
};

/// A parsed .sbs file.
struct CHIMERA_API SbsFile {
    std::string path;
    std::string subsystem;  ///< SUBSYSTEM
    std::string svarfile;   ///< SVARFILE, resolved against the .sbs's folder
    std::string master;     ///< MASTER (the first RTPU when absent)
    std::vector<RtpuSpec> rtpus;
    std::vector<TaskLine> tasks;  ///< TASK lines, in file order

    const RtpuSpec* find_rtpu(std::string_view name) const noexcept;
};

/// Reads a .sbs; throws cfg::ParseError.
CHIMERA_API SbsFile read_sbs(const std::string& path);
/// Parses from a reader; relative SVARFILE paths are resolved against `base_dir`.
CHIMERA_API SbsFile parse_sbs(cfg::Reader& reader, const std::string& base_dir);
/// Throws cfg::ParseError (FILE:LINE of the RTPU) when an RTPU names a CPU
/// this process may not run on: one check for sbs and chimcfg check (which
/// therefore judges a file for the machine it runs on).
CHIMERA_API void check_rtpu_cpus(const SbsFile& f);

}  // namespace chimera
