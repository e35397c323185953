// The LTTng-ust provider `chimera`: probes and tracepoint definitions, built
// only when the `lttng` feature found liblttng-ust (see chimera/trace.hpp).
#define LTTNG_UST_TRACEPOINT_CREATE_PROBES
#define LTTNG_UST_TRACEPOINT_DEFINE
#include "chimera/trace.hpp"
