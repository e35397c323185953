#!/usr/bin/env bash
# The bridge's latency across two network namespaces joined by a veth pair,
# beside Cyclone DDS's own ddsperf for the same payload, alternated in the same
# run (issue #19.6; method in bench/results/dds.md). Needs root (namespaces).
#   bench/dds/bench_dds.sh BUILD_DIR        (DUR=10 WARM=2 ROUNDS=3 to change)
# Each round runs ddsperf, then the bridge with each NOTIFY of $NOTIFY (poll
# wake spin). BEFORE=DIR adds, in the same rounds, the ddsbridge.so of DIR
# (another build of the module: "before" a change) with NOTIFY poll and wake.
# A variant NOTIFY:StateVar sends the bridge's chimera_msgs/StateVar (no
# strings) instead of the JointState. The variant "plain" (PLAIN=1 puts it
# first) is a second peer: bench_dds_writer, Cyclone's own writer sending the
# bridge's exact sample from a 1 kHz loop, read by the same consumer: DDS's
# one-way time on one clock, where ddsperf gives half a round trip.
# The CPUs' idle states are the same for every measurement: IDLE=held (the
# default) holds /dev/cpu_dma_latency at 0 for the whole run, as the runtime
# does for a real-time subsystem (so ddsperf gets the same shallow idle as the
# bridge); IDLE=free holds nothing and tells the runtime not to either.
# BESIDE=1 adds ddsperf run again beside the producer's 1 kHz task (stamp and
# a bridge publishing to no reader, so nothing is sent): the peer under the
# same CPU load as the bridge's own runs.
set -u
build=$(cd "${1:?usage: bench_dds.sh BUILD_DIR}" && pwd)
here=$(cd "$(dirname "$0")" && pwd)
config=$(cd "$here/../../examples/two_machines" && pwd)/cyclone.xml
DUR=${DUR:-10} WARM=${WARM:-2} ROUNDS=${ROUNDS:-3} NOTIFY=${NOTIFY:-poll wake spin} BEFORE=${BEFORE:-}
IDLE=${IDLE:-held} BESIDE=${BESIDE:-0} PLAIN=${PLAIN:-0}
variants=$NOTIFY
[ "$PLAIN" = 1 ] && variants="plain $variants"
[ -n "$BEFORE" ] && variants="$variants poll@before wake@before"
SIZE=152  # the CDR size of the bridge's JointState sample (6 names "jointN", 6 positions; README of bench/results/dds.md)
tag=$$
. "$here/../../scripts/netns_pair.sh"
work=$(mktemp -d /tmp/bench_dds.XXXXXX)
cleanup() { netns_pair_down; rm -rf "$work"; }
trap cleanup EXIT
netns_pair_up bd 10.219.2 || exit 1
ns_pub=$NETNS_A ns_sub=$NETNS_B veth_pub=$VETH_A veth_sub=$VETH_B
domain=$((1 + tag % 230))
sed -e "s/^DOMAIN .*/DOMAIN    $domain/" -e "s|^CONFIG .*|CONFIG    $config|" "$here/bench_bridge.rmod" > "$work/bench_bridge.rmod"
in_pub() { CHIMERA_DDS_INTERFACE=$veth_pub CYCLONEDDS_URI=file://$config ip netns exec "$ns_pub" "$@"; }
in_sub() { CHIMERA_DDS_INTERFACE=$veth_sub CYCLONEDDS_URI=file://$config ip netns exec "$ns_sub" "$@"; }
if [ "$IDLE" = held ]; then
    exec 9> /dev/cpu_dma_latency && printf '0x00000000' >&9 || { echo "cannot hold /dev/cpu_dma_latency"; exit 1; }
else
    export CHIMERA_NO_CPU_LATENCY=1
fi
median() { sort -g | awk '{ v[NR] = $1 } END { print (NR % 2) ? v[(NR + 1) / 2] : (v[NR / 2] + v[NR / 2 + 1]) / 2 }'; }

echo "# $(date -u '+%Y-%m-%d %H:%M') UTC, load $(cut -d' ' -f1-3 /proc/loadavg), DUR=$DUR WARM=$WARM ROUNDS=$ROUNDS IDLE=$IDLE, payload $SIZE bytes, 1 kHz, cpuidle $(cat /sys/devices/system/cpu/cpuidle/current_driver 2>/dev/null)"
# The bridge: stamp + ddsbridge in one 1 kHz task, the bridge's receiving code read at 1 kHz.
# Appends its line to the legs table; prints "TRANSFER_P50 TRANSFER_P99".
bridge_run() {  # bridge_run NOTIFY[:StateVar][@before]
    local notify=${1%@*} modules=$build/modules/ddsbridge message=JointState
    [ "$1" != "$notify" ] && modules=$BEFORE
    [ "${notify#*:}" != "$notify" ] && message=${notify#*:}
    notify=${notify%:*}
    sed -e "s/^NOTIFY .*/NOTIFY    $notify/" "$work/bench_bridge.rmod" > "$work/bench_bridge_$notify.rmod"
    [ "$message" = StateVar ] && sed -i -e "s/JointState.position/StateVar/" "$work/bench_bridge_$notify.rmod"
    if [ "$1" = plain ]; then
        in_pub "$build/bench/dds/bench_dds_writer" "$domain" bench/joint_states $((DUR + WARM + 3)) > "$work/producer.log" 2>&1 &
    else
        in_pub "$build/bench/dds/bench_dds_producer" "$here/bench.sbs" "bdds$tag" "$here/stamp.rmod" \
            "$work/bench_bridge_$notify.rmod" "$build/bench/dds" "$modules" $((DUR + WARM + 3)) > "$work/producer.log" 2>&1 &
    fi
    local producer=$!
    in_sub "$build/bench/dds/bench_dds_consumer" "$domain" "$config" bench/joint_states "$WARM" "$DUR" "$message" > "$work/consumer.log" 2>&1
    wait $producer
    echo "  round $round $1: $(tr '\n' ' ' < "$work/producer.log") $(grep '^received' "$work/consumer.log")" >&2
    awk -v round="$round" -v variant="$1" '/^(transfer|wait|leg_)/ { v[$1] = $5 " | " $7 }
        END { print "| " round " | " variant " | " v["leg_write"] " | " v["leg_handoff"] " | " v["leg_dds"] " | " v["leg_store"] " | " v["transfer"] " | " v["wait"] " |" }' \
        "$work/consumer.log" >> "$work/legs.md"
    awk '/^transfer/ { print $5, $7 }' "$work/consumer.log"
}
header="| round | ddsperf one-way p50 | p99 |" rule="|---|---|---|"
for v in $variants; do header="$header bridge $v: transfer p50 | p99 |" rule="$rule---|---|"; done
# ddsperf: ping at 1 kHz, best effort, one-way = round trip / 2 (as ddsperf prints it);
# the median over its one-second windows after the warm-up. Prints "P50 P99".
ddsperf_run() {
    in_pub ddsperf -D $((DUR + WARM + 3)) -u pong > "$work/pong.log" 2>&1 &
    local pong=$!
    in_sub ddsperf -D $((DUR + WARM)) -u ping 1kHz size $SIZE > "$work/ping.log" 2>&1
    wait $pong
    local windows
    windows=$(grep " size $SIZE mean " "$work/ping.log" | awk -v w="$WARM" '$2 + 0 > w')
    echo "$(sed -n 's/.* 50% \([0-9.]*\)us.*/\1/p' <<< "$windows" | median)" \
         "$(sed -n 's/.* 99% \([0-9.]*\)us.*/\1/p' <<< "$windows" | median)"
}
# ddsperf beside the producer's task: its bridge publishes on a domain no one reads.
ddsperf_beside_task() {
    sed -e "s/^DOMAIN .*/DOMAIN    $(( (domain + 1) % 230 + 1 ))/" "$work/bench_bridge.rmod" > "$work/bench_alone.rmod"
    in_pub "$build/bench/dds/bench_dds_producer" "$here/bench.sbs" "bdda$tag" "$here/stamp.rmod" \
        "$work/bench_alone.rmod" "$build/bench/dds" "$build/modules/ddsbridge" $((DUR + WARM + 6)) > "$work/alone.log" 2>&1 &
    local producer=$!
    sleep 2
    ddsperf_run
    wait $producer
}
[ "$BESIDE" = 1 ] && { header="$header ddsperf beside the task p50 | p99 |"; rule="$rule---|---|"; }
echo "$header"
echo "$rule"
for round in $(seq "$ROUNDS"); do
    read -r p50 p99 <<< "$(ddsperf_run)"
    [ -n "$p50" ] || { echo "round $round: ddsperf failed:"; cat "$work/ping.log" "$work/pong.log"; exit 1; }
    row="| $round | $p50 | $p99 |"
    for v in $variants; do
        read -r t50 t99 <<< "$(bridge_run "$v")"
        [ -n "$t50" ] || { echo "round $round: the bridge ($v) failed:"; cat "$work/producer.log" "$work/consumer.log"; exit 1; }
        row="$row $t50 | $t99 |"
    done
    if [ "$BESIDE" = 1 ]; then
        read -r b50 b99 <<< "$(ddsperf_beside_task)"
        row="$row $b50 | $b99 |"
    fi
    echo "$row"
done
echo
echo "The bridge's transfer by legs (p50 | p99, µs): write = table write -> the bridge's TBUF write;"
echo "hand-off = -> the bridge thread's dds_write; dds = -> the listener's entry; store = -> the consumer's"
echo "TBUF write; transfer = their sum; consumer's wait = -> the consumer loop's read (apart)."
echo
echo "| round | bridge | write p50 | p99 | hand-off p50 | p99 | dds p50 | p99 | store p50 | p99 | transfer p50 | p99 | consumer's wait p50 | p99 |"
echo "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
cat "$work/legs.md"
echo "# load at the end: $(cut -d' ' -f1-3 /proc/loadavg)"
