#!/usr/bin/env bash
# chain_vs_hal.sh -- issue 14 item 2: the whole subsystem's CPU time per 1 kHz
# cycle for a 6-joint chain, beside LinuxCNC HAL running its own chain
# (chain6.hal: 6 x integ, ddt, siggen, limit3, pid + timedelta = 31 functions),
# alternated in one sitting: HAL, Chimera combined task, Chimera separate tasks,
# ROUNDS times.
#
#   bench/chain/chain_vs_hal.sh BUILD_DIR [PEER_DIR]      (as root)
#
# PEER_DIR: the LinuxCNC HAL peer harness (default ../shared/peers/linuxcnc-hal
# beside the checkout). knobs (env): DUR=10 (s per window) WARM=2 ROUNDS=3
# CPU=<last CPU> (both pinned there: HAL pins its thread to the last CPU).
#
# The measure is the same for both: the on-CPU time of every thread of the
# process (rtapi_app for HAL, bench_chain for Chimera), from the kernel's
# /proc/PID/task/*/schedstat, over the window, divided by the cycles run.
# HAL runs as its peer harness runs it in mode "rt" (SCHED_FIFO 98, mlockall,
# LINUXCNC_FORCE_REALTIME=1, rtprio_shim.so); it is installed (linuxcnc-uspace,
# Debian) when missing — a bench-only dependency, never the project's.
set -u
BUILD=${1:?usage: chain_vs_hal.sh BUILD_DIR [PEER_DIR]}
BUILD=$(cd "$BUILD" && pwd)
HERE=$(cd "$(dirname "$0")" && pwd)
PEER=${2:-$HERE/../../../shared/peers/linuxcnc-hal}
DUR=${DUR:-10}
WARM=${WARM:-2}
ROUNDS=${ROUNDS:-3}
CPU=${CPU:-$(( $(nproc) - 1 ))}
CHAIN=$BUILD/bench/chain/bench_chain
REALTIME=/usr/lib/linuxcnc/realtime
WORK=$(mktemp -d /tmp/chain-vs-hal.XXXXXX)
chmod 755 "$WORK"  # rtapi_app runs as nobody and binds its socket below

die() { echo "chain_vs_hal: $*" >&2; exit 1; }
[ "$(id -u)" = 0 ] || die "run as root (HAL's realtime mode and SCHED_FIFO)"
[ -x "$CHAIN" ] || die "$CHAIN not built (ninja -C $BUILD bench/chain/bench_chain)"
[ -f "$PEER/chain6.hal" ] || die "no LinuxCNC HAL peer harness at $PEER (give PEER_DIR)"
if ! command -v halcmd >/dev/null; then
    echo "chain_vs_hal: installing linuxcnc-uspace (the peer; log $WORK/apt.log)"
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends \
        linuxcnc-uspace kmod; } >"$WORK/apt.log" 2>&1 || die "apt-get failed, see $WORK/apt.log"
fi
gcc -O2 -shared -fPIC -o "$WORK/rtprio_shim.so" "$PEER/rtprio_shim.c" -ldl || die "shim build failed"
mkdir -p "$WORK/rtapi" && chmod 1777 "$WORK/rtapi"
export RTAPI_FIFO_PATH="$WORK/rtapi/.rtapi_fifo" RTAPI_UID="$(id -u nobody)"

# Sum of the first schedstat field (ns on CPU) over every thread of PID.
cpu_ns() { cat /proc/"$1"/task/*/schedstat 2>/dev/null | awk '{s += $1} END {printf "%d", s}'; }
# "tid comm ns" per thread of PID, for the per-thread breakdown.
thread_ns() { for t in /proc/"$1"/task/*; do echo "${t##*/} $(cat "$t/comm") $(cut -d' ' -f1 "$t/schedstat")"; done 2>/dev/null; }

hal_pid() { ps -C rtapi_app -o pid=,stat= --sort=start_time | awk '$2 !~ /^Z/ {print $1; exit}'; }

hal_round() {
    [ -z "$(hal_pid)" ] || die "an rtapi_app is already running (not ours): stop it first (halrun -U)"
    $REALTIME start >>"$WORK/hal.log" 2>&1 || die "realtime start failed, see $WORK/hal.log"
    LINUXCNC_FORCE_REALTIME=1 LD_PRELOAD="$WORK/rtprio_shim.so" halcmd -f "$PEER/chain6.hal" >>"$WORK/hal.log" 2>&1 \
        || die "halcmd -f chain6.hal failed, see $WORK/hal.log"
    local pid; pid=$(hal_pid)
    halcmd start
    sleep "$WARM"
    local policy; policy=$(ps -L -o cls=,rtprio=,psr= -p "$pid" | awk '$1 == "FF" {print "SCHED_FIFO " $2 " CPU " $3; exit}')
    local a b; a=$(cpu_ns "$pid")
    thread_ns "$pid" >"$WORK/hal-threads-0.txt"
    sleep "$DUR"
    b=$(cpu_ns "$pid")
    thread_ns "$pid" >"$WORK/hal-threads-1.txt"
    # Per thread, ns per cycle (to set beside bench_chain's breakdown).
    awk -v c=$((DUR * 1000)) 'NR == FNR {a[$1] = $3; next} {d = $3 - a[$1]; if (d > 0) printf "  hal thread %s %s %.0f ns/cycle\n", $1, $2, d / c}' \
        "$WORK/hal-threads-0.txt" "$WORK/hal-threads-1.txt" >>"$WORK/hal-breakdown.txt"
    halcmd show thread >"$WORK/hal-thread.txt" 2>&1
    { halcmd stop; halcmd unloadrt all; $REALTIME stop; } >>"$WORK/hal.log" 2>&1
    echo "RESULT mode=hal cycles=$((DUR * 1000)) process_cpu_ns_per_cycle=$(( (b - a) / (DUR * 1000) )) policy=\"${policy:-not SCHED_FIFO}\""
}

chimera_round() {
    "$CHAIN" --mode "$1" --seconds "$DUR" --warm "$WARM" --cpu "$CPU" >"$WORK/chimera-$1.txt" 2>&1 \
        || { cat "$WORK/chimera-$1.txt"; die "bench_chain --mode $1 failed"; }
    grep '^RESULT' "$WORK/chimera-$1.txt"
}

echo "chain_vs_hal: $(date -u +%FT%TZ), $(uname -r), $(nproc) CPUs, CPU $CPU, ${DUR} s windows, $ROUNDS rounds, load $(cut -d' ' -f1-3 /proc/loadavg)"
for r in $(seq 1 "$ROUNDS"); do
    echo "round $r"
    for run in hal_round "chimera_round combined" "chimera_round separate"; do
        line=$($run) || exit 1
        echo "$line" | tee -a "$WORK/results.txt"
    done
done
echo "load after: $(cut -d' ' -f1-3 /proc/loadavg); raw output in $WORK"
# Medians per mode, and the ratios to HAL.
awk '
    /^RESULT/ { m = ""; v = ""
        for (i = 2; i <= NF; ++i) { split($i, kv, "="); if (kv[1] == "mode") m = kv[2]; if (kv[1] == "process_cpu_ns_per_cycle") v = kv[2] }
        vals[m] = vals[m] " " v }
    function median(s,   a, n, i, j, t) { n = split(s, a, " ")
        for (i = 1; i <= n; ++i) for (j = i + 1; j <= n; ++j) if (a[j] + 0 < a[i] + 0) { t = a[i]; a[i] = a[j]; a[j] = t }
        return n % 2 ? a[(n + 1) / 2] : (a[n / 2] + a[n / 2 + 1]) / 2 }
    END { h = median(vals["hal"])
        printf "median process CPU per cycle: HAL %d ns", h
        for (m in vals) if (m != "hal") printf ", chimera %s %d ns (%.2fx HAL)", m, median(vals[m]), median(vals[m]) / h
        printf "\n" }' "$WORK/results.txt"
