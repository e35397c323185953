#include "command_table.hpp"

#include <cstdlib>
#include <string_view>

namespace chimera::cli {

const std::vector<CommandInfo>& command_table() {
    static const std::vector<CommandInfo> table = {
        {"clear", "clear [RMOD]", "send the clear-error signal to a task in ERROR",
         Access::acts, "changes a task's state"},
        {"complete", "complete LINE", "the TAB completions of LINE (what an attached prompt asks the master)",
         Access::reads, nullptr},
        {"display", "display [RMOD|all] [VAR...]", "show SVAR values (what the task reads and writes; VAR may use * ?)",
         Access::reads, nullptr},
        {"event", "event [RMOD] [COUNT]", "wake an aperiodic task (sporadic, deferrable or background server) that is ON: one cycle per event (default 1, at most 1000)",
         Access::acts, "runs cycles of a task"},
        {"finish", "finish", "turn every task off, kill them and end the subsystem",
         Access::acts, "ends the subsystem"},
        {"freq", "freq [RMOD] [HZ]", "show or change the frequency of a task",
         Access::depends, nullptr},
        {"help", "help [COMMAND]", "list the commands, or explain one",
         Access::reads, nullptr},
        {"kill", "kill [RMOD]", "destroy a task (off first if it is ON)",
         Access::acts, "destroys a task"},
        {"module", "module [NAME] | module load PATH", "list the modules and .rmod files on the module path, or show one's ports and LOCAL keys; `module load` loads a module shared object (NAME.so, libNAME.so) from PATH and adds its folder to the module path (not over the network)",
         Access::depends, nullptr},
        {"network", "network", "pass control to a network peer until it quits or is lost",
         Access::acts, "passes control to the network"},
        {"off", "off [RMOD]", "send the off signal",
         Access::acts, "changes a task's state"},
        {"on", "on [RMOD]", "send the on signal",
         Access::acts, "changes a task's state"},
        {"peer", "peer NAME --pid PID [--out VAR...] [--in VAR...] [--program TEXT...]", "declare a process outside the master (a Python program) that produces the --out and consumes the --in variables in its own loop: a background task NAME (module peer) that verification counts as their producer and status lists; it goes to ERROR when the process is gone; `kill NAME` removes it",
         Access::acts, "creates a task"},
        {"quit", "quit", "leave this interface (at the prompt: finish the subsystem and exit)",
         Access::session, nullptr},
        {"reconfig", "reconfig SIG RMOD [, SIG RMOD ...] | reconfig --check SIG RMOD [, ...]", "apply an ordered list of signals (on off kill clear); stops at the first failure; --check: verify the configuration it would leave (§3.3.1) and send nothing",
         Access::depends, nullptr},
        {"record", "record VAR[IDX]... DURATION FILE.csv [--rate HZ] [--rtpu RTPU]", "record state variables (VAR, VAR[i], VAR[i:j]) at a task's rate for DURATION (5s, 500ms, 2min) into a CSV file: a `sample` task, read by this sbs program, killed at the end; the reply counts lost samples (not over the network: a peer runs `sample` and reads the ring itself)",
         Access::acts, "creates a task (a sampler) and writes a file"},
        {"sample", "sample VAR[IDX]... [--rate HZ] [--rtpu RTPU] [--capacity N]", "start a sampler task: chosen elements of state variables read at HZ (default: the fastest producer's rate) into a shared-memory ring for any number of readers (scope, record, Python's chimera.record); `kill` the task to stop it",
         Access::acts, "creates a task (a sampler) and its ring"},
        {"save", "save FILE.sbs", "write the running configuration as a .sbs that starts the same subsystem: the RTPUs, a TASK line per task (its RTPU, ON when on) and a SET line per LOCAL value changed at run time (not over the network)",
         Access::acts, "writes a file"},
        {"set", "set [RMOD] [KEY [VALUE...]]", "show the LOCAL configuration of a task, one key, or change a key",
         Access::depends, nullptr},
        {"setvar", "setvar VAR[IDX] VALUE... [--force]", "write a state variable of the running table (halcmd setp): range-checked against the .svar MIN/MAX; refused while a task produces it unless --force",
         Access::acts, "writes a state variable"},
        {"show", "show [rtpu|svar [NAME...] | graph]", "alone: list what it shows; show the RTPUs (CPU, policy, scheduler, tasks, planned utilisation) or the variables with producers and consumers (halcmd show thread / show sig); graph: the port graph (tasks, their ports, states, RTPUs) and the §3.3.1 problems of the tasks ON",
         Access::reads, nullptr},
        {"sleep", "sleep SECONDS", "pause (lets the tasks run between the commands of a script; at most 60 s)",
         Access::acts, "holds the master's one command thread for up to 60 s"},
        {"spawn", "spawn RMOD[+RMOD...] [RTPU]", "create a task from RMOD.rmod on an RTPU (default: the MASTER RTPU); a+b+c: one combined task (§3.8.1), methods in that order",
         Access::acts, "creates a task"},
        {"status", "status [RMOD|all] | status reset | status set [FIELD...|default|all]", "show the status of the tasks, counted since this interface's last `status` (the prompt and a network peer each have their own; chimtop never changes it); times in us; `status reset` shows it and restarts profiling on every RTPU for every reader (the thesis's reset); `status set` picks the fields",
         Access::depends, nullptr},
    };
    return table;
}
const std::vector<CommandInfo>& console_command_table() {
    static const std::vector<CommandInfo> table = {
        {"control", "control", "take control of the subsystem (one page or peer at a time)", Access::session, nullptr},
        {"release", "release", "give control back and watch", Access::session, nullptr},
        {"scope", "scope start VAR[IDX]... [--rate HZ] [--rtpu RTPU] [--capacity N] | scope stop | scope ack BATCH",
         "this page's scope: start spawns its sampler task (needs control), stop kills it, ack paces its stream",
         Access::depends, nullptr},
    };
    return table;
}

namespace {

const CommandInfo* find_command(std::string_view name) {
    for (const auto* table : {&command_table(), &console_command_table()})
        for (const auto& c : *table)
            if (name == c.name) return &c;
    return nullptr;
}

bool is_number(const std::string& text) {
    char* end = nullptr;
    std::strtod(text.c_str(), &end);
    return end != text.c_str() && *end == '\0';
}

// The forms of the `depends` commands, one rule each: nullptr when the form
// only reads (or only touches the caller's session), else what it does.
const char* acting_form(const std::vector<std::string>& w) {
    const std::string& c = w[0];
    const std::string second = w.size() > 1 ? w[1] : "";
    if (c == "freq")  // freq [RMOD] shows; a number, or RMOD HZ, changes it
        return w.size() > 2 || (w.size() == 2 && is_number(second)) ? "changes a task's frequency" : nullptr;
    if (c == "module") return second == "load" ? "loads a shared object into the master" : nullptr;
    if (c == "reconfig") return second == "--check" ? nullptr : "sends signals to tasks";
    if (c == "set") return w.size() > 2 ? "changes a task's LOCAL configuration" : nullptr;
    if (c == "status") {
        if (second == "reset") return "restarts every reader's profile";
        return second == "set" && w.size() > 2 ? "changes the fields every interface's status shows" : nullptr;
    }
    if (c == "scope") return second == "start" ? "creates a task (a sampler) and its ring" : nullptr;
    return "is not classified";  // a `depends` entry without a rule here: acts, to be safe
}

}  // namespace

Access command_access(const std::vector<std::string>& words, std::string* why) {
    if (words.empty()) return Access::reads;
    const CommandInfo* info = find_command(words[0]);
    const char* acts_by = info == nullptr ? "is not a command" : "is not classified";
    Access access = Access::acts;  // unknown or unclassified: never run by a watcher
    if (info != nullptr && info->access == Access::depends) {
        acts_by = acting_form(words);
        access = acts_by == nullptr ? (words[0] == "scope" ? Access::session : Access::reads) : Access::acts;
    } else if (info != nullptr && info->access != Access::unclassified) {
        access = info->access;
        acts_by = info->acts_by;
    }
    if (access == Access::acts && why != nullptr) *why = acts_by != nullptr ? acts_by : "changes the subsystem";
    return access;
}

std::string watcher_refusal(const std::vector<std::string>& words) {
    std::string why;
    if (command_access(words, &why) != Access::acts) return {};
    std::string form = words[0];
    if (words[0] == "scope" || words[0] == "module" || words[0] == "status")  // their acting sub-command
        if (words.size() > 1) form += " " + words[1];
    return form + " " + why;
}

}  // namespace chimera::cli
