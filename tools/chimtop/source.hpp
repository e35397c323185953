// What chimtop reads: one subsystem's status segment, seen through this
// chimtop's own profiling window (issue 16.4: its `z` restarts that window
// and nobody else's), kept across the subsystem stopping and starting again;
// and the list of the subsystems running on this machine.
#pragma once

#include <sys/types.h>

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "chimera/prof.hpp"

namespace chimtop {

/// A status segment found in /dev/shm.
struct SubsystemEntry {
    std::string name;
    bool readable = false;  ///< this user may open it
    bool alive = false;     ///< its creator process runs
    int creator_pid = 0;
    std::size_t tasks = 0;
    uid_t owner = 0;
    mode_t mode = 0;
    std::string problem;    ///< why it cannot be read ("" when it can)
};
/// Every /dev/shm/chimera.NAME.status, sorted by name.
std::vector<SubsystemEntry> running_subsystems();
/// "NAME  running (pid 123)  3 tasks" or "NAME  permission denied ..." lines.
std::string entry_line(const SubsystemEntry& e);

/// "permission denied: /dev/shm/chimera.X.status is root's (group chimera,
/// mode 0640): add yourself to group chimera (usermod -aG chimera USER), then
/// log in again" (ipc::permission_advice); `write`: for --half-tick, which
/// only the owner may.
std::string permission_advice(const std::string& subsystem, bool write);

/// One subsystem, re-attached when it restarts (a reader is dropped when its
/// creator is gone or the name now names a new segment). chimtop watches:
/// read-only, no lock a task waits on, not a user of the segment
/// (docs/permissions.md); only --half-tick attaches to write, as the owner.
class Attachment {
public:
    /// `half_tick_ns` >= 0: on every (re-)attachment, switch each RTPU to
    /// half-tick accounting with that tick (0: back to nanoseconds).
    Attachment(std::string subsystem, std::int64_t half_tick_ns);

    /// Attaches if needed; false when the subsystem cannot be read (problem()).
    bool refresh();
    /// Why the last refresh() could not attach ("" after one that did):
    /// "not found ..." or permission_advice() or the attach error.
    const std::string& problem() const { return problem_; }
    bool denied() const { return denied_; }
    /// Why the last accounting change failed ("" if it did not).
    const std::string& error() const { return error_; }

    /// The tasks over this chimtop's window, and the RTPUs (attached only).
    std::vector<chimera::prof::TaskStatus> snapshot() const;
    std::vector<chimera::prof::RtpuEpoch> rtpus() const;
    /// `z`: this window starts again now; no other reader sees a change.
    void restart_window();
    /// Seconds since the window (re)started; nullopt when never restarted
    /// (the counts run since each RTPU's last reset).
    std::optional<double> window_seconds() const;

    const std::string& subsystem() const { return subsystem_; }
    int restarts() const { return restarts_; }

private:
    void apply_accounting();
    ino_t inode() const;

    std::string subsystem_;
    std::string path_;
    std::optional<chimera::prof::StatusReader> reader_;
    chimera::prof::StatusWindow window_;
    ino_t inode_ = 0;
    int restarts_ = 0;
    std::int64_t half_tick_ns_ = -1;
    bool denied_ = false;
    std::string problem_, error_;
};

}  // namespace chimtop
