#!/usr/bin/env bash
# The bridge's latency across two network namespaces joined by a veth pair,
# beside Cyclone DDS's own ddsperf for the same payload, alternated in the same
# run (issue #19.6; method in bench/results/dds.md). Needs root (namespaces).
#   bench/dds/bench_dds.sh BUILD_DIR        (DUR=10 WARM=2 ROUNDS=3 to change)
set -u
build=$(cd "${1:?usage: bench_dds.sh BUILD_DIR}" && pwd)
here=$(cd "$(dirname "$0")" && pwd)
config=$(cd "$here/../../examples/two_machines" && pwd)/cyclone.xml
DUR=${DUR:-10} WARM=${WARM:-2} ROUNDS=${ROUNDS:-3}
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
median() { sort -g | awk '{ v[NR] = $1 } END { print (NR % 2) ? v[(NR + 1) / 2] : (v[NR / 2] + v[NR / 2 + 1]) / 2 }'; }

echo "# $(date -u '+%Y-%m-%d %H:%M') UTC, load $(cut -d' ' -f1-3 /proc/loadavg), DUR=$DUR WARM=$WARM ROUNDS=$ROUNDS, payload $SIZE bytes, 1 kHz"
echo "| round | ddsperf one-way p50 | ddsperf p99 | bridge, NOTIFY poll: transfer p50 | p99 | NOTIFY wake: p50 | p99 | NOTIFY spin: p50 | p99 | consumer's wait p50 | p99 |"
echo "|---|---|---|---|---|---|---|---|---|---|---|"
# The bridge: stamp + ddsbridge in one 1 kHz task, the bridge's receiving code read at 1 kHz.
# Prints "P50 P99 WAIT50 WAIT99" of the transfer.
bridge_run() {  # bridge_run NOTIFY
    sed -e "s/^NOTIFY .*/NOTIFY    $1/" "$work/bench_bridge.rmod" > "$work/bench_bridge_$1.rmod"
    in_pub "$build/bench/dds/bench_dds_producer" "$here/bench.sbs" "bdds$tag" "$here/stamp.rmod" \
        "$work/bench_bridge_$1.rmod" "$build/bench/dds" "$build/modules/ddsbridge" $((DUR + WARM + 3)) > "$work/producer.log" 2>&1 &
    local producer=$!
    in_sub "$build/bench/dds/bench_dds_consumer" "$domain" "$config" bench/joint_states "$WARM" "$DUR" > "$work/consumer.log" 2>&1
    wait $producer
    echo "  NOTIFY $1: $(tr '\n' ' ' < "$work/producer.log") $(grep '^received' "$work/consumer.log")" >&2
    # The transfer's legs (p50 p99 of each), for the second table.
    awk -v round="$round" -v notify="$1" '/^(transfer|leg_)/ { v[$1] = $5 " | " $7 }
        END { print "| " round " | " notify " | " v["leg_write"] " | " v["leg_handoff"] " | " v["leg_dds"] " | " v["leg_store"] " | " v["transfer"] " |" }' \
        "$work/consumer.log" >> "$work/legs.md"
    awk '/^transfer/ { t50 = $5; t99 = $7 } /^wait/ { w50 = $5; w99 = $7 } END { print t50, t99, w50, w99 }' "$work/consumer.log"
}
for round in $(seq "$ROUNDS"); do
    # ddsperf: ping at 1 kHz, best effort, one-way = round trip / 2 (as ddsperf prints it);
    # the median over its one-second windows after the warm-up.
    in_pub ddsperf -D $((DUR + WARM + 3)) -u pong > "$work/pong.log" 2>&1 &
    pong=$!
    in_sub ddsperf -D $((DUR + WARM)) -u ping 1kHz size $SIZE > "$work/ping.log" 2>&1
    wait $pong
    windows=$(grep " size $SIZE mean " "$work/ping.log" | awk -v w="$WARM" '$2 + 0 > w')
    p50=$(sed -n 's/.* 50% \([0-9.]*\)us.*/\1/p' <<< "$windows" | median)
    p99=$(sed -n 's/.* 99% \([0-9.]*\)us.*/\1/p' <<< "$windows" | median)
    read -r poll50 poll99 w50 w99 <<< "$(bridge_run poll)"
    read -r wake50 wake99 _ _ <<< "$(bridge_run wake)"
    read -r spin50 spin99 _ _ <<< "$(bridge_run spin)"
    if [ -z "$poll50" ] || [ -z "$wake50" ] || [ -z "$spin50" ] || [ -z "$p50" ]; then
        echo "round $round failed:"; cat "$work/ping.log" "$work/producer.log" "$work/consumer.log"; exit 1
    fi
    echo "| $round | $p50 | $p99 | $poll50 | $poll99 | $wake50 | $wake99 | $spin50 | $spin99 | $w50 | $w99 |"
done
echo
echo "The bridge's transfer by legs (p50 | p99, µs): write = table write -> the bridge's TBUF write;"
echo "hand-off = -> the bridge thread's dds_write; dds = -> the listener's entry; store = -> the consumer's TBUF write."
echo
echo "| round | NOTIFY | write p50 | p99 | hand-off p50 | p99 | dds p50 | p99 | store p50 | p99 | transfer p50 | p99 |"
echo "|---|---|---|---|---|---|---|---|---|---|---|---|"
cat "$work/legs.md"
echo "# load at the end: $(cut -d' ' -f1-3 /proc/loadavg)"
