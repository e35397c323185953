// chimera/muf/taskset.hpp — task-set files for chimsched and the tests.
//
// One line per task, in the project's configuration style (chimera::cfg::Reader:
// DEFINE, `#` comments, a final EOF line):
//
//   TASK <name> PERIOD <p> WCET <c> [CRIT <n>] [UPRIO <n>] [DEADLINE <d>] [EFFECTIVE <e>]
//   FLOW <producer> <consumer>      # optional data flow between two tasks (§6.2.4)
//   EOF
//
// Times are in any consistent unit. CRIT is 1..62, UPRIO 0..63. EFFECTIVE is
// the E of a soft task (§6.4). Errors are cfg::ParseError, "FILE:LINE: message".
#pragma once

#include "chimera/export.hpp"

#include <string>
#include <string_view>
#include <vector>

#include "chimera/muf/analysis.hpp"

namespace chimera::muf {

struct TaskSet {
    std::string file;
    std::vector<TaskSpec> tasks;
    std::vector<Flow> flows;
};

/// Reads a task-set file; throws cfg::ParseError naming the file and line.
CHIMERA_API TaskSet read_task_set(const std::string& path);
/// The same from text; `name` is used as FILE in errors.
CHIMERA_API TaskSet parse_task_set(std::string_view text, const std::string& name);

}  // namespace chimera::muf
