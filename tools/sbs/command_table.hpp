// tools/sbs/command_table.hpp — every command a client of a master can send,
// and what each does to the subsystem (issue #29.1). The prompt's help and
// completion come from the table; the web console, the watcher sbs and the
// tests decide from it who may run what, before anything is dispatched.
#pragma once

#include <string>
#include <vector>

namespace chimera::cli {

/// What a command does, for who may send it. `unclassified` is 0, so an entry
/// written without an access stands out (the table test refuses it).
enum class Access {
    unclassified,
    reads,    ///< a bounded view of the subsystem; creates and changes nothing
    session,  ///< changes only this connection (control, release, quit, its own scope)
    acts,     ///< creates a task, allocates, writes a file or changes state
    depends,  ///< reads in some forms, acts in others: command_access() looks at the words
};

/// One command of a table (help text and completion come from it).
struct CommandInfo {
    const char* name;
    const char* usage;
    const char* help;
    Access access;
    /// For `acts`: what it does that a watcher may not (the refusal's reason).
    const char* acts_by;
};

/// The interpreter's commands, in alphabetical order (as §4.4.1 lists them).
const std::vector<CommandInfo>& command_table();

/// The web console's own commands (control, release, scope): answered by the
/// console, never by the interpreter, so they are not in `help`.
const std::vector<CommandInfo>& console_command_table();

/// What the command `words` does: `reads`, `session` or `acts` (never
/// `depends`); `why` gets what it does when it acts, e.g. "creates a task
/// (a sampler)". An unknown command acts (nothing unknown reaches a watcher).
Access command_access(const std::vector<std::string>& words, std::string* why = nullptr);

/// The one decision for a watcher (a web page without control, a watcher
/// sbs): "" when it may run `words`, else the reason, e.g.
/// "scope start creates a task (a sampler) and its ring".
std::string watcher_refusal(const std::vector<std::string>& words);

}  // namespace chimera::cli
