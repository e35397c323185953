// chimera/muf.hpp — real-time scheduling (thesis chapter 6): the whole public face.
//
//   muf/rt.hpp         Linux backends (RtpuScheduler: fifo, deadline), timing failures,
//                      the thesis task API (pause, set_deadline, set_dfhandler, ...)
//   muf/taskset.hpp    task-set files (TASK ... PERIOD ... WCET ..., FLOW, EOF)
//   muf/sim.hpp        the discrete-event simulator (RM, EDF, MUF; Gantt charts)
//   muf/analysis.hpp   utilisation, bounds, critical sets, MUF assignment, urgency,
//                      aperiodic servers, soft-task effective execution time
#pragma once

#include "chimera/muf/analysis.hpp"
#include "chimera/muf/sim.hpp"
#include "chimera/muf/taskset.hpp"
#include "chimera/muf/rt.hpp"
