#include "watcher.hpp"

#include "command_line.hpp"
#include "commands.hpp"

#include <chimera/ipc/segment.hpp>
#include <chimera/sbs.hpp>

#include <algorithm>

namespace chimera::cli {

namespace {

// What `status` shows of a task, from its slot of the status segment. A task
// in init or kill shows OFF: it runs no cycle (the prompt's states are §4.4.1's four).
sbs::TaskStatus row_of(const prof::TaskStatus& p) {
    sbs::TaskStatus t;
    t.rmod = p.rmod;
    t.rtpu = p.rtpu_name.empty() ? std::to_string(p.rtpu) : p.rtpu_name;
    t.cpu = p.cpu;
    t.tid = p.tid;
    t.type = p.type;
    t.crit = p.crit;
    switch (p.state) {
        case prof::TaskState::not_created: t.state = State::NOT_CREATED; break;
        case prof::TaskState::on: t.state = State::ON; break;
        case prof::TaskState::error: t.state = State::ERROR; break;
        case prof::TaskState::off:
        case prof::TaskState::spawning:
        case prof::TaskState::killing: t.state = State::OFF; break;
    }
    t.ref_freq = p.ref_f;
    t.ref_period = p.ref_t;
    t.policy = p.policy;
    t.warnings = p.warn;
    t.warning = p.warning;
    t.error = p.error;
    t.profile = p;
    return t;
}

}  // namespace

Watcher::Watcher(std::string subsystem, std::string owner, std::string sbs_path)
    : subsystem_(std::move(subsystem)),
      owner_(std::move(owner)),
      sbs_path_(std::move(sbs_path)),
      reader_(prof::StatusReader::watch(subsystem_)) {}

Reply Watcher::execute(std::string_view command) {
    std::vector<std::string> w;
    try {
        w = split_words(command);
        if (w.empty()) return Reply{};
        if (w[0] == "status") return status(w);
        if (w[0] == "display") return display(w);
    } catch (const std::exception& e) {
        return Reply::failure(w.empty() ? "" : w[0], e.what());
    }
    Reply r;
    r.command = w[0];
    const std::string command_it = "only " + owner_ + " may command it (" + (owner_ == "root" ? "sudo " : "") +
                                   "sbs " + sbs_path_ + ")";
    if (const std::string why = watcher_refusal(w); !why.empty())
        return Reply::failure(w[0], "permission denied: " + why + ", and subsystem " + subsystem_ + " runs as " +
                                        owner_ + ": " + command_it + "; this sbs only watches it: status, display, help, quit");
    if (w[0] == "quit" && w.size() == 1) {
        r.action = Action::quit;
        return r;
    }
    if (w[0] == "help") {
        r.text = "watching subsystem " + subsystem_ + " (run by " + owner_ + "), read-only:\n"
                 "  status [RMOD|all]     the tasks, counted since this sbs's last status (times in us)\n"
                 "  display [VAR...]      the SVAR table's values (glob patterns)\n"
                 "  quit\n"
                 "Commanding it is " + owner_ + "'s: " + (owner_ == "root" ? "sudo " : "") + "sbs " + sbs_path_;
        return r;
    }
    // It only reads, but what it reads is the master's own (its interpreter, its module path).
    return Reply::failure(w[0], w[0] + " is answered by the master, which subsystem " + subsystem_ + "'s owner " +
                                    owner_ + " runs: " + command_it + "; this sbs only watches it: status, display, help, quit");
}

Reply Watcher::status(const std::vector<std::string>& w) {
    if (w.size() > 2 || (w.size() == 2 && (w[1] == "reset" || w[1] == "set")))
        return Reply::failure("status", w.size() == 2 && w[1] == "reset"
                                            ? "permission denied: status reset restarts every reader's profile; only " +
                                                  owner_ + " may (this sbs only watches)"
                                            : "usage while watching: status [RMOD|all]");
    std::vector<sbs::TaskStatus> rows;
    for (const auto& p : window_.take(reader_))
        if (w.size() == 1 || w[1] == "all" || p.rmod == w[1]) rows.push_back(row_of(p));
    if (rows.empty() && w.size() == 2 && w[1] != "all")
        return Reply::failure("status", "no task " + w[1] + " in subsystem " + subsystem_);
    Reply r = status_reply(subsystem_, rows, default_status_fields(), false);
    r.command = "status";
    return r;
}

Reply Watcher::display(const std::vector<std::string>& w) {
    if (!table_) {
        svar::TableOptions o;
        o.attach.prefault = false;
        table_ = svar::Table::watch(ipc::segment_name(subsystem_, "svar"), o);
    }
    std::vector<VarItem> items;
    for (std::size_t i = 0; i < table_->size(); ++i) {
        const std::string name(table_->var(i).name());
        const bool wanted = w.size() == 1 || (w.size() == 2 && w[1] == "all") ||
                            std::any_of(w.begin() + 1, w.end(), [&](const std::string& p) { return glob_match(p, name); });
        if (wanted) items.push_back({"", name});
    }
    if (items.empty()) return Reply::failure("display", "no variable matches in table " + table_->name());
    Reply r = values_reply(*table_, items, "");
    r.command = "display";
    return r;
}

}  // namespace chimera::cli
