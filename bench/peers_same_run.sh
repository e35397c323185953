#!/usr/bin/env bash
# Issue #15.8's rows beside their peers, interleaved in one sitting (results:
# bench/results/svar.md and xmail.md): TBUF write+read against the Rust
# `triple_buffer` crate, MSG round trips against POSIX mqueue (the peers' C
# harness and the same binary's) and the busy-polled MSG against iceoryx2.
#   bench/peers_same_run.sh BUILD_DIR PEERS_DIR [ROUNDS]
# PEERS_DIR is a copy of ../shared/peers/ipc-baselines, built by its run.sh
# (target/release/ipc_baselines, build/ipc_bench). Prints raw lines; no ratio
# is computed here: read them round by round.
# IDLE=held holds /dev/cpu_dma_latency at 0 for the whole sitting (every row,
# the peers' too), as the runtime does for a real-time subsystem: the CPUs
# then poll when idle instead of halting, and a cross-CPU wake-up costs a few
# microseconds instead of the ~25 µs of waking a halted vCPU. Default: free.
set -euo pipefail
IDLE=${IDLE:-free}
if [ "$IDLE" = held ]; then
  exec 9> /dev/cpu_dma_latency && printf '0x00000000' >&9 || { echo "cannot hold /dev/cpu_dma_latency" >&2; exit 1; }
fi
build=${1:?build dir}
peers=${2:?peers dir (a built copy of shared/peers/ipc-baselines)}
rounds=${3:-3}
rb=$peers/target/release/ipc_baselines
cb=$peers/build/ipc_bench
[[ -x $rb && -x $cb ]] || { echo "build the peers first: (cd $peers && ./run.sh)" >&2; exit 2; }

echo "host: $(uname -r), $(nproc) cpus, load $(cut -d' ' -f1-3 /proc/loadavg), $(date -u +%FT%TZ), IDLE=$IDLE"
for ((r = 1; r <= rounds; r++)); do
  echo "== round $r (load $(cut -d' ' -f1-3 /proc/loadavg))"
  for s in 24 144; do taskset -c 1 "$rb" triple-buffer "$s" 2000000 7; done
  taskset -c 1 "$build/bench/svar/bench_svar" --benchmark_filter='TbufWriteRead|MonotonicClock' \
    --benchmark_repetitions=5 --benchmark_report_aggregates_only=true --benchmark_min_time=0.2 2>/dev/null |
    grep -E '_median'
  "$cb" pingpong mq 64 0 1 100000 0.4
  "$cb" pingpong mq 64 1 1 100000 0.4
  "$build/bench/xmail/bench_xmail" --benchmark_min_time=0.3 \
    --benchmark_filter='MsgBusyPingPong/bytes:24|MsgPingPong/bytes:24/place:[01]|MqPingPong/bytes:24/place:[01]' 2>/dev/null |
    grep -E 'PingPong'
  id="peers$$-$r"
  taskset -c 1 "$rb" iox-pong "$id" 64 zc &
  pong=$!
  taskset -c 0 "$rb" iox-ping "$id" 64 zc 100000 0.4 "iceoryx2 busy zero-copy 64 B" || kill "$pong" 2>/dev/null || true
  wait "$pong" 2>/dev/null || true
done
