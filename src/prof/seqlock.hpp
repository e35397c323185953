// src/prof/seqlock.hpp — the status segment's sequence counters use the
// protocol of chimera/ipc/seqlock.hpp (shared with the SVAR table's watchers).
#pragma once

#include "chimera/ipc/seqlock.hpp"

namespace chimera::prof::detail {
using ipc::seqlock::cpu_relax;
using ipc::seqlock::read_consistent;
using ipc::seqlock::write_begin;
using ipc::seqlock::write_end;
}  // namespace chimera::prof::detail
