// tools/sbs/watcher.hpp — `sbs FILE.sbs` run by another user while the
// subsystem runs (issue 16.7, docs/permissions.md). Its master is not this
// user's to command (and its socket is its owner's alone), so this sbs only
// watches: `status` and `display` read the status segment and the SVAR table
// as a watcher (read-only, not a user of them, no lock a task waits on);
// every other command is refused with "permission denied" and what to do.
#pragma once

#include "reply.hpp"

#include <chimera/prof.hpp>
#include <chimera/svar.hpp>

#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace chimera::cli {

class Watcher {
public:
    /// `owner`: the user the subsystem runs as; `sbs_path`: the file given,
    /// for the advice. Throws ipc::SegmentError (EACCES: what to do in
    /// what()) when this user may not read the status segment.
    Watcher(std::string subsystem, std::string owner, std::string sbs_path);

    /// Runs ONE command (no `;`). Never throws: failures are replies.
    Reply execute(std::string_view command);
    /// "SBS <subsystem>(watching) ".
    std::string prompt() const { return "SBS " + subsystem_ + "(watching) "; }
    int master_pid() const { return reader_.creator_pid(); }

private:
    Reply status(const std::vector<std::string>& w);
    Reply display(const std::vector<std::string>& w);

    std::string subsystem_, owner_, sbs_path_;
    prof::StatusReader reader_;
    prof::StatusWindow window_;  // "since the last status" of this sbs alone
    std::optional<svar::Table> table_;
};

}  // namespace chimera::cli
