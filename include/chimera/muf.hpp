// chimera/muf.hpp — real-time scheduling (thesis chapter 6): the whole public face.
//
//   muf/analysis.hpp   utilisation, bounds, critical sets, MUF assignment, urgency,
//                      aperiodic servers, soft-task effective execution time
#pragma once

#include "chimera/muf/analysis.hpp"
