// Helpers of the `sbs` program tests: a private workspace per test (its own
// .sbs with a unique subsystem name, its own socket folder and HOME), and
// running the program with a time limit.
#pragma once

#include <nlohmann/json.hpp>

#include <sys/types.h>

#include <string>
#include <vector>

namespace sbs_test {

/// $NAME or a test failure naming the missing variable.
std::string env(const char* name);

struct Outcome {
    int status = -1;  ///< exit status; 128+N when killed by signal N
    std::string out, err;
};

/// Runs `program args...`, feeding `input` on stdin; kills it after
/// `timeout_s` (the Outcome then has status -1).
Outcome run(const std::string& program, const std::vector<std::string>& args, const std::string& input = {},
        int timeout_s = 60);

/// Every line of `text` parsed as JSON (a line that is not JSON fails the test).
std::vector<nlohmann::json> json_lines(const std::string& text);

/// A temporary folder holding `<name>.sbs` (SUBSYSTEM unique to this process
/// and test) for the tools.svar of tests/tools/data; XDG_RUNTIME_DIR and HOME
/// point into it while it lives. Removed with everything in it.
class Workspace {
public:
    Workspace();
    ~Workspace();
    Workspace(const Workspace&) = delete;
    Workspace& operator=(const Workspace&) = delete;

    const std::string& dir() const { return dir_; }
    const std::string& sbs() const { return sbs_; }
    const std::string& subsystem() const { return subsystem_; }
    /// Where `sbs --listen` puts its socket for this subsystem.
    std::string socket_path() const;
    /// Writes `text` to dir/name and returns the path.
    std::string write(const std::string& name, const std::string& text) const;
    /// `sbs <this .sbs> --module-path <data> args...`
    Outcome sbs_run(const std::vector<std::string>& args, const std::string& input = {}, int timeout_s = 60) const;
    std::vector<std::string> sbs_args(const std::vector<std::string>& args) const;

private:
    std::string dir_, sbs_, subsystem_;
};

/// Reads from `fd` until `pattern` has appeared in what was read (kept in
/// `seen`) or `timeout_ms` passed; false on timeout or end of file.
bool read_until(int fd, std::string& seen, const std::string& pattern, int timeout_ms = 10000);

/// Writes `keys` to a pseudo-terminal master once the program on it reads
/// in raw mode (libedit at its prompt; at most 2 s): keys typed in the
/// instant between the prompt text and the mode switch would go through the
/// cooked line discipline instead.
void type_at_prompt(int fd, const std::string& keys);

/// Waits until `path` exists (or timeout); true when it does.
bool wait_for_file(const std::string& path, int timeout_ms = 10000);

/// Waits for a child with a time limit; returns its exit status (or -1 after killing it).
int wait_child(pid_t pid, int timeout_ms = 20000);

}  // namespace sbs_test
