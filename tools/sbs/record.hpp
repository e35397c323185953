// tools/sbs/record.hpp — `record VAR... DURATION FILE.csv`: the samples of a
// `sample` task written to a CSV file by the sbs program that asked (the
// master's own prompt or -c script, or an sbs attached to it as a peer), so
// the file lands where the user is, and the master never writes a file for a
// network peer.
#pragma once

#include "reply.hpp"

#include <atomic>
#include <functional>
#include <string_view>

namespace chimera::cli {

/// Runs one command where the master is (in process, or over the socket).
using Executor = std::function<Reply(std::string_view)>;

/// True when `command` is a `record` command (for record(), not the master).
bool is_record(std::string_view command);

/// "5s", "500ms", "2min", "1.5" (seconds) → seconds; throws std::invalid_argument.
double parse_duration(std::string_view text);

/// record VAR[IDX]... DURATION FILE.csv [--rate HZ] [--rtpu RTPU]: asks the
/// master for a `sample` task, follows its ring for round(DURATION x rate)
/// samples, writes FILE.csv (replaced atomically: header `t,COLUMN...`, t in
/// seconds from the first sample, then one row per sample), and kills the
/// task. A lost sample (this reader fell behind the ring) fails the command,
/// naming how many, with the file written. `interrupted` (Ctrl-C) stops it
/// early: the rows taken are kept in the file and the command fails saying so.
Reply record(const Executor& exec, std::string_view command, const std::atomic<bool>* interrupted = nullptr);

}  // namespace chimera::cli
