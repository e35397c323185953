// chimera/trace.hpp — LTTng-ust tracepoints of the runtime
// (docs/architecture.md §11, "context-switch profiling": a full per-cycle trace
// when one is wanted).
//
// Built when the meson feature `lttng` finds liblttng-ust: libraries that
// depend on chimera_prof_dep are compiled with CHIMERA_HAVE_LTTNG=1 and the
// provider `chimera` is linked into libchimera (src/prof/tracepoints.cpp).
// Otherwise every macro below expands to nothing (its arguments are not
// evaluated). With the provider built but no session listening, each
// tracepoint costs one load and a predictable, not-taken branch.
//
// Events (provider `chimera`):
//   cycle_begin      (rmod, slot, cycle)                     TaskProfiler::cycle_begin
//   cycle_end        (rmod, slot, cycle, cpu_ns, switched)   TaskProfiler::cycle_end
//   deadline_miss    (rmod, slot, cycle, missed)             TaskProfiler::missed
//   failure_handler  (rmod, kind)  kind: 1 DEADLINE, 2 MAXEXEC, 3 MINEXEC   (sbs/muf)
//   svar_copy        (rmod, direction, nvars, bytes)  direction 0 in, 1 out  (sbs)
//   state_transition (rmod, from, to)  TaskState numbers             (sbs)
// The sbs runtime emits failure_handler, svar_copy (around its SVAR copies)
// and state_transition; svar itself sits beside prof and does not include this.
//
// Recording and reading: see docs/prof.md.
//
// This file is also the LTTng tracepoint-provider header: lttng-ust re-reads
// it with LTTNG_UST_TRACEPOINT_HEADER_MULTI_READ, so the provider part below
// is deliberately not under #pragma once.

#if defined(CHIMERA_HAVE_LTTNG) && CHIMERA_HAVE_LTTNG

#undef LTTNG_UST_TRACEPOINT_PROVIDER
#define LTTNG_UST_TRACEPOINT_PROVIDER chimera

#undef LTTNG_UST_TRACEPOINT_INCLUDE
#define LTTNG_UST_TRACEPOINT_INCLUDE "chimera/trace.hpp"

#if !defined(CHIMERA_TRACE_PROVIDER_H) || defined(LTTNG_UST_TRACEPOINT_HEADER_MULTI_READ)
#define CHIMERA_TRACE_PROVIDER_H

#include <lttng/tracepoint.h>

LTTNG_UST_TRACEPOINT_EVENT(chimera, cycle_begin,
    LTTNG_UST_TP_ARGS(const char*, rmod, unsigned int, slot, unsigned long, cycle),
    LTTNG_UST_TP_FIELDS(
        lttng_ust_field_string(rmod, rmod)
        lttng_ust_field_integer(unsigned int, slot, slot)
        lttng_ust_field_integer(unsigned long, cycle, cycle)))

LTTNG_UST_TRACEPOINT_EVENT(chimera, cycle_end,
    LTTNG_UST_TP_ARGS(const char*, rmod, unsigned int, slot, unsigned long, cycle,
                      unsigned long, cpu_ns, int, switched),
    LTTNG_UST_TP_FIELDS(
        lttng_ust_field_string(rmod, rmod)
        lttng_ust_field_integer(unsigned int, slot, slot)
        lttng_ust_field_integer(unsigned long, cycle, cycle)
        lttng_ust_field_integer(unsigned long, cpu_ns, cpu_ns)
        lttng_ust_field_integer(int, switched, switched)))

LTTNG_UST_TRACEPOINT_EVENT(chimera, deadline_miss,
    LTTNG_UST_TP_ARGS(const char*, rmod, unsigned int, slot, unsigned long, cycle,
                      unsigned int, missed),
    LTTNG_UST_TP_FIELDS(
        lttng_ust_field_string(rmod, rmod)
        lttng_ust_field_integer(unsigned int, slot, slot)
        lttng_ust_field_integer(unsigned long, cycle, cycle)
        lttng_ust_field_integer(unsigned int, missed, missed)))

LTTNG_UST_TRACEPOINT_EVENT(chimera, failure_handler,
    LTTNG_UST_TP_ARGS(const char*, rmod, int, kind),
    LTTNG_UST_TP_FIELDS(
        lttng_ust_field_string(rmod, rmod)
        lttng_ust_field_integer(int, kind, kind)))

LTTNG_UST_TRACEPOINT_EVENT(chimera, svar_copy,
    LTTNG_UST_TP_ARGS(const char*, rmod, int, direction, unsigned int, nvars, unsigned int, bytes),
    LTTNG_UST_TP_FIELDS(
        lttng_ust_field_string(rmod, rmod)
        lttng_ust_field_integer(int, direction, direction)
        lttng_ust_field_integer(unsigned int, nvars, nvars)
        lttng_ust_field_integer(unsigned int, bytes, bytes)))

LTTNG_UST_TRACEPOINT_EVENT(chimera, state_transition,
    LTTNG_UST_TP_ARGS(const char*, rmod, int, from, int, to),
    LTTNG_UST_TP_FIELDS(
        lttng_ust_field_string(rmod, rmod)
        lttng_ust_field_integer(int, from, from)
        lttng_ust_field_integer(int, to, to)))

#endif  // CHIMERA_TRACE_PROVIDER_H

#include <lttng/tracepoint-event.h>

#endif  // CHIMERA_HAVE_LTTNG

#ifndef CHIMERA_TRACE_HPP_API
#define CHIMERA_TRACE_HPP_API

namespace chimera::trace {
/// True when this build emits LTTng tracepoints.
inline constexpr bool enabled =
#if defined(CHIMERA_HAVE_LTTNG) && CHIMERA_HAVE_LTTNG
    true;
#else
    false;
#endif
}  // namespace chimera::trace

#if defined(CHIMERA_HAVE_LTTNG) && CHIMERA_HAVE_LTTNG
#define CHIMERA_TRACE_CYCLE_BEGIN(rmod, slot, cycle) \
    lttng_ust_tracepoint(chimera, cycle_begin, (rmod), (slot), (cycle))
#define CHIMERA_TRACE_CYCLE_END(rmod, slot, cycle, cpu_ns, switched) \
    lttng_ust_tracepoint(chimera, cycle_end, (rmod), (slot), (cycle), (cpu_ns), (switched))
#define CHIMERA_TRACE_DEADLINE_MISS(rmod, slot, cycle, missed) \
    lttng_ust_tracepoint(chimera, deadline_miss, (rmod), (slot), (cycle), (missed))
#define CHIMERA_TRACE_FAILURE_HANDLER(rmod, kind) \
    lttng_ust_tracepoint(chimera, failure_handler, (rmod), (kind))
#define CHIMERA_TRACE_SVAR_COPY(rmod, direction, nvars, bytes) \
    lttng_ust_tracepoint(chimera, svar_copy, (rmod), (direction), (nvars), (bytes))
#define CHIMERA_TRACE_STATE_TRANSITION(rmod, from, to) \
    lttng_ust_tracepoint(chimera, state_transition, (rmod), (from), (to))
#else
#define CHIMERA_TRACE_CYCLE_BEGIN(rmod, slot, cycle) ((void)0)
#define CHIMERA_TRACE_CYCLE_END(rmod, slot, cycle, cpu_ns, switched) ((void)0)
#define CHIMERA_TRACE_DEADLINE_MISS(rmod, slot, cycle, missed) ((void)0)
#define CHIMERA_TRACE_FAILURE_HANDLER(rmod, kind) ((void)0)
#define CHIMERA_TRACE_SVAR_COPY(rmod, direction, nvars, bytes) ((void)0)
#define CHIMERA_TRACE_STATE_TRANSITION(rmod, from, to) ((void)0)
#endif

#endif  // CHIMERA_TRACE_HPP_API
