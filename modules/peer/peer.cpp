// peer — the stand-in task of a process outside the master (sbs.hpp,
// kPeerModule): a Python program that declares the variables it produces
// (OUTVAR) and consumes (INVAR) and runs its own non-real-time loop against
// the table, like a LinuxCNC HAL user-space component. The `peer` command
// spawns it (TASKTYPE background), so the master's §3.3.1 verification counts
// the process as a producer and status lists it; the runtime copies none of
// its ports (the process reads and writes the table itself).
//
//   LOCAL  PID n          the process it stands for
//          [PROGRAM text] what that process is (for status and `set`)
//
// The master wakes the task (an event) when it finds the process gone; the
// cycle then checks and raises an error, so the task goes to ERROR — no
// longer a producer — with the reason in status. That check is one kill(pid,
// 0) in a background task's cycle, which runs only when the master asks.
#include <chimera/module.hpp>

#include <signal.h>

#include <cerrno>
#include <stdexcept>
#include <string>

namespace {

constexpr chimera::LocalKey kPeerLocalKeys[] = {
    {"PID", chimera::LocalType::integer, 1.0, 4194304.0, false, "the process this task stands for", ""},
    {"PROGRAM", chimera::LocalType::text, -chimera::unbounded, chimera::unbounded, false,
     "what that process is", ""},
};

bool alive(long pid) { return ::kill(static_cast<pid_t>(pid), 0) == 0 || errno == EPERM; }

class Peer : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kPeerLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        pid_ = static_cast<long>(t.local().number("PID", 0));
        if (pid_ <= 0) throw std::invalid_argument(std::string(t.rmod()) + ": LOCAL PID (the peer's process) is required");
        return check(t);
    }
    chimera::Result on(chimera::Task& t) override { return check(t); }
    chimera::Result cycle(chimera::Task& t) override { return check(t); }

private:
    chimera::Result check(chimera::Task& t) {
        if (alive(pid_)) return chimera::Result::OK;
        return t.error(chimera::err::code::user + 1, "peer process " + std::to_string(pid_) + " is gone");
    }
    long pid_ = 0;
};

}  // namespace

CHIMERA_MODULE(peer, Peer)
