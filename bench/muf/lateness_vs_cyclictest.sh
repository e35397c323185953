#!/usr/bin/env bash
# Release lateness of a muf task against cyclictest, alternating in time, same
# CPU, same SCHED_FIFO priority, same period, same number of cycles (issue #14
# item 10). Prints one JSON line per run and a summary: the median over the
# rounds of each tool's p50 / p99 / p99.9 / max, and the ratios.
#   bench/muf/lateness_vs_cyclictest.sh BUILD_DIR [ROUNDS=3] [CYCLES=60000] [CPU=1]
set -euo pipefail
build=${1:?usage: $0 BUILD_DIR [ROUNDS] [CYCLES] [CPU]}
rounds=${2:-3}
cycles=${3:-60000}
cpu=${4:-1}
prio=80
command -v cyclictest >/dev/null || { echo "cyclictest missing (apt-get install rt-tests)" >&2; exit 1; }
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT

# cyclictest's histogram (µs buckets) to the same JSON fields.
cyclictest_run() {
    cyclictest -m -p "$prio" -i 1000 -l "$cycles" -q -t1 -a "$cpu" -h 100000 >"$out/ct.txt" 2>/dev/null
    python3 - "$out/ct.txt" <<'PY'
import json, sys
hist, mx, over = [], 0, 0
for line in open(sys.argv[1]):
    if line.startswith('# Max Latencies:'): mx = int(line.split()[-1])
    elif line.startswith('# Histogram Overflows:'): over = int(line.split()[-1])
    elif line[:1].isdigit():
        us, n = line.split()[:2]
        hist.append((int(us), int(n)))
total = sum(n for _, n in hist) + over
def pct(q):
    want, seen = q * (total - 1), 0
    for us, n in hist:
        seen += n
        if seen > want: return us
    return mx
print(json.dumps({"tool": "cyclictest", "samples": total, "p50_us": pct(.5), "p99_us": pct(.99),
                  "p999_us": pct(.999), "max_us": mx}))
PY
}

for r in $(seq 1 "$rounds"); do
    "$build/bench/muf/lateness" --cycles "$cycles" --cpu "$cpu" --priority "$prio" | tee -a "$out/chimera.jsonl"
    cyclictest_run | tee -a "$out/cyclictest.jsonl"
done
python3 - "$out/chimera.jsonl" "$out/cyclictest.jsonl" <<'PY'
import json, statistics, sys
a = [json.loads(l) for l in open(sys.argv[1])]
b = [json.loads(l) for l in open(sys.argv[2])]
print("median of %d rounds (µs)     chimera  cyclictest  ratio" % len(a))
for k in ("p50_us", "p99_us", "p999_us", "max_us"):
    x, y = statistics.median(r[k] for r in a), statistics.median(r[k] for r in b)
    print("%-26s %8.1f %10.1f %6.2f" % (k, x, y, x / y if y else float("nan")))
for k in ("woken_p99_us", "woken_p999_us"):
    x, y = statistics.median(r[k] for r in a), statistics.median(r[k.replace("woken_", "")] for r in b)
    print("%-26s %8.1f %10.1f %6.2f" % (k + " (as cyclictest)", x, y, x / y if y else float("nan")))
print("skipped releases (chimera):", [r["skipped"] for r in a])
print("cyclictest steps over the periods it slept through without a sample; chimera's p*_us")
print("count each of them with its lateness, woken_* count one sample per wake-up as cyclictest does")
PY
