#!/usr/bin/env bash
# chimtop against the REAL Figure 3.7 subsystem (build/examples/demo, subsystem
# fig3_7, run under a name of its own), whose task runtime publishes every task's status: --once and --json
# show puma_torque, jtraj and jpid ON and cycling with the §4.4.1 fields
# consistent with each other; --svar shows the variables each task reads and
# writes; the live view (tmux) waits while the subsystem is gone and
# re-attaches when it is started again; a member of the group chimera watches
# it read-only without keeping its segments alive (issue 16.7).
# Usage: test_chimtop_demo.sh CHIMTOP DEMO SBS FIG3_7.SBS
set -u
CHIMTOP=$1
DEMO=$2
SBS=$3
# Names are machine-wide: this run's subsystem is its own, and the member's
# sbs reads a copy of the example's .sbs that names it.
SUB=chimtop_demo_$$
SEG=/dev/shm/chimera.$SUB.status
SOCK=chimtopdemo_$$
LOG=/tmp/chimtop_demo_$$
mkdir -p "$LOG.sbs"
sed "s/^SUBSYSTEM .*/SUBSYSTEM $SUB/" "$4" > "$LOG.sbs/fig3_7.sbs"
cp "$(dirname "$4")/fig3_7.svar" "$LOG.sbs/"
chmod -R go+rX "$LOG.sbs"
SBS_FILE=$LOG.sbs/fig3_7.sbs
fail=0
check() {  # check "description" command...
    local what=$1; shift
    if "$@"; then echo "ok   - $what"; else echo "FAIL - $what"; fail=1; fi
}
has() { grep -q -- "$2" <<<"$1"; }
header_of() { grep -m1 -vE '^(subsystem|RTPU) ' <<<"$1"; }  # --once: the column header
demo_pid=
cleanup() {
    tmux -L "$SOCK" kill-server 2>/dev/null
    tmux -L "$SOCK.member" kill-server 2>/dev/null
    [ -n "$demo_pid" ] && kill "$demo_pid" 2>/dev/null && wait "$demo_pid" 2>/dev/null
    rm -rf "$LOG".*
}
trap cleanup EXIT

# True when a --json snapshot has the three tasks ON with cycle > 0.
ready_py='
import json, sys
t = {x["rmod"]: x for x in json.load(sys.stdin)["tasks"]}
sys.exit(0 if all(n in t and t[n]["state"] == "ON" and t[n]["cycle"] > 0
                  for n in ("puma_torque", "jtraj", "jpid")) else 1)'
wait_ready() {
    for _ in $(seq 150); do
        "$CHIMTOP" "$SUB" --json 2>/dev/null | python3 -c "$ready_py" 2>/dev/null && return 0
        sleep 0.1
    done
    return 1
}

# ---- the live view is up before the subsystem
tmux -L "$SOCK" new-session -d -x 200 -y 45 \
    "$CHIMTOP $SUB --rate 10 --fields rmod,rtpu,state,cycle,miss,mezF,avgC,policy --sort rmod"
sleep 0.8
check "tui: waits for the subsystem" has "$(tmux -L "$SOCK" capture-pane -p)" "waiting for subsystem '$SUB'"

# ---- run 1: PID control for 4 s, then the swap to jpidg for 4 s
"$DEMO" --seconds 8 --quiet --name "$SUB" > "$LOG.run1" 2>&1 &
demo_pid=$!
if ! wait_ready; then
    echo "FAIL - the demo's tasks never showed ON with cycles"; cat "$LOG.run1"
    "$CHIMTOP" "$SUB" --once 2>&1
    exit 1
fi
sleep 0.3  # a few hundred cycles into the profile

out=$("$CHIMTOP" "$SUB" --once --fields rmod,state,cycle --sort rmod)
echo "$out"
for t in puma_torque jtraj jpid; do
    check "--once: $t ON with cycle > 0" \
        awk -v t="$t" '$1 == t && $2 == "ON" && $3 > 0 { found = 1 } END { exit !found }' <<<"$out"
done
all=rmod,rtpu,tid,S,crit,state,cycle,miss,refF,refT,mezF,mezT,ptime,totC,tick,minU,maxU,avgU,minC,maxC,avgC,warn
out=$("$CHIMTOP" "$SUB" --once --fields "$all")
echo "$out"
check "--once: header lists every §4.4.1 field in order" \
    test "$(header_of "$out" | sed 's/\[us\]//g' | xargs | tr ' ' ,)" = "$all"
check "--once: times in us, said in the header" grep -qE 'refT\[us\] .*maxC\[us\]' <<<"$(header_of "$out")"
check "--once: five task rows" test "$(grep -cE '^(puma_torque|jtraj|jpid|grav_comp|jpidg) ' <<<"$out")" -eq 5
check "--once: the RTPUs' summary lines, named as in fig3_7.sbs" \
    test "$(grep -E '^RTPU ' <<<"$out" | awk '{print $2 "@" $4}' | xargs)" = "ctrl@0 robot@1"

json=$("$CHIMTOP" "$SUB" --json --svar)
check "--json: §4.4.1 fields of the real tasks agree with each other" python3 -c '
import json, sys
j = json.loads(sys.argv[1])
assert j["subsystem"] == sys.argv[2], (j["subsystem"], sys.argv[2])
t = {x["rmod"]: x for x in j["tasks"]}
assert set(t) == {"puma_torque", "jtraj", "jpid", "grav_comp", "jpidg"}, t.keys()
ref = {"puma_torque": 500.0, "jtraj": 100.0, "jpid": 500.0, "grav_comp": 100.0, "jpidg": 500.0}
rtpu = {"puma_torque": 1, "jtraj": 0, "jpid": 0, "grav_comp": 0, "jpidg": 0}
assert j["time_unit"] == "us"
for n, x in t.items():
    assert x["refF"] == ref[n] and abs(x["refT"] - 1e6 / ref[n]) < 1e-6, (n, x["refF"], x["refT"])
    assert x["rtpu"] == rtpu[n] and x["S"] == "P" and x["tid"] > 0, (n, x)
    assert x["rtpu_name"] == ("ctrl", "robot")[rtpu[n]], (n, x)
    assert x["policy"] != "" and x["clock"] in ("perf-page", "thread-cputime"), (n, x)
    assert x["consistent"] and x["error"] == "", (n, x)
    assert x["tick"] == 0.001 and x["accounting"] == "ns"
assert t["jpidg"]["state"] == "OFF" and t["jpidg"]["cycle"] == 0
for n in ("puma_torque", "jtraj", "jpid"):
    x = t[n]
    assert x["state"] == "ON" and x["cycle"] > 0 and x["ptime"] > 0, (n, x)
    # mezF = n_c / ptime (ptime in us); avgC = q_t / accounted (the first cycle dropped)
    assert abs(x["mezF"] * x["ptime"] * 1e-6 - x["cycle"]) < 1e-6 * x["cycle"] + 1e-9, (n, x)
    if x["accounted"] > 0:
        assert x["accounted"] == x["cycle"] - 1, (n, x)
        assert 0 < x["minC"] <= x["avgC"] <= x["maxC"], (n, x)
        assert abs(x["avgC"] * x["accounted"] - x["totC"]) < 1e-3 + 1e-9 * x["totC"], (n, x)
        for u, c in (("minU", "minC"), ("maxU", "maxC"), ("avgU", "avgC")):
            assert abs(x[u] - x[c] / x["refT"] * 100) < 1e-6, (n, u, x)
    # mezT: ptime / (cycle + miss) rounded to the 1 ns tick (0.001 us)
    assert abs(x["mezT"] - x["ptime"] / (x["cycle"] + x["miss"])) < 2e-3, (n, x)
    # 14.11: every cycle in the cycle-time histogram, every release in the lateness one
    assert 0 < x["cycP50"] <= x["cycP99"] <= x["cycMax"], (n, x)
    assert 0 <= x["latP50"] <= x["latP99"] <= x["latMax"], (n, x)
    assert x["cycP50"] >= x["minC"] * 0.999, (n, x)  # wall time >= CPU time (bucket edges are >= the value)
sv = t["jpid"]["svar"]
assert "error" not in sv, sv
assert set(sv["in"]) == {"Q_REF", "Q^_REF", "Q_MEZ", "Q^_MEZ"}, sv["in"].keys()
assert list(sv["out"]) == ["T_REF"] and len(sv["out"]["T_REF"]) == 6, sv
assert list(t["puma_torque"]["svar"]["in"]) == ["T_REF"], t["puma_torque"]["svar"]
assert len(t["puma_torque"]["svar"]["out"]["Q_MEZ"]) == 6
assert set(t["jtraj"]["svar"]["out"]) == {"Q_REF", "Q^_REF", "Q^^_REF"}
' "$json" "$SUB" || echo "$json"

out=$("$CHIMTOP" "$SUB" --once --svar --fields rmod,state)
check "--once --svar: jpid's pane lists T_REF with 6 values" \
    grep -qE "^  out T_REF  double\[6\] ( [-0-9.e+]+){6} Nm" <<<"$out"

# Half-tick accounting (§6.7), switched from chimtop, over a 0.5 s window:
# every CPU time is a whole number of half-ticks, mezT a whole number of ticks.
json=$("$CHIMTOP" "$SUB" --json --half-tick 1 --sample 0.5)
check "--half-tick 1: the thesis's quantisation on the real tasks" python3 -c '
import json, sys
t = {x["rmod"]: x for x in json.loads(sys.argv[1])["tasks"]}
whole = lambda v, q: abs(v / q - round(v / q)) < 1e-6
for n in ("puma_torque", "jtraj"):
    x = t[n]
    assert x["accounting"] == "half-tick" and x["tick"] == 1000, (n, x)   # 1 ms, in us
    assert x["cycle"] > 0 and x["accounted"] > 0, (n, x)
    for f in ("minC", "maxC", "totC"):
        assert x[f] >= 500 and whole(x[f], 500), (n, f, x[f])
    assert whole(x["mezT"], 1000) and whole(x["ptime"], 1000), (n, x)
' "$json" || echo "$json"
json=$("$CHIMTOP" "$SUB" --json --half-tick 0 --sample 0.2)
check "--half-tick 0: back to nanoseconds" python3 -c '
import json, sys
t = {x["rmod"]: x for x in json.loads(sys.argv[1])["tasks"]}
assert t["puma_torque"]["accounting"] == "ns" and t["puma_torque"]["tick"] == 0.001
' "$json"

screen=$(tmux -L "$SOCK" capture-pane -p)
echo "$screen"
check "tui: rows of the real tasks" test "$(grep -cE '^(puma_torque|jtraj|jpid|grav_comp|jpidg) ' <<<"$screen")" -eq 5
check "tui: puma_torque ON on RTPU robot (named as in the .sbs)" grep -qE '^puma_torque +robot +ON ' <<<"$screen"

wait "$demo_pid"; rc=$?; demo_pid=
check "demo run 1 exits 0" test $rc -eq 0
check "demo removed its status segment" test ! -e "$SEG"
sleep 0.5
check "tui: subsystem stopped -> waiting" has "$(tmux -L "$SOCK" capture-pane -p)" "waiting for subsystem '$SUB'"

# ---- run 2: the same subsystem started again (jpid hands over to jpidg
# half-way, so only the tasks that stay ON are looked at); long enough for
# the member's checks on a loaded machine
"$DEMO" --seconds 8 --quiet --name "$SUB" > "$LOG.run2" 2>&1 &
demo_pid=$!
for _ in $(seq 150); do
    "$CHIMTOP" "$SUB" --once --fields rmod,state,cycle 2>/dev/null |
        awk '$1 == "jtraj" && $2 == "ON" && $3 > 0 { f = 1 } END { exit !f }' && break
    sleep 0.1
done
sleep 0.3
screen=$(tmux -L "$SOCK" capture-pane -p)
echo "$screen"
check "tui: re-attached to the restarted subsystem" has "$screen" "(re-attached)"
check "tui: its tasks shown again" grep -qE '^jtraj +ctrl +ON +[1-9]' <<<"$screen"

# ---- 16.7 who may watch: a member of the group chimera (nobody, via setpriv)
# reads the status and the SVAR table of the running subsystem, read-only,
# while its tasks run; its chimtop is no user of the segments (run 2's end
# removes them under it).
member=0
if command -v setpriv >/dev/null && [ "$(id -u)" = 0 ] && getent group chimera >/dev/null; then
    member=1
    as_member() { setpriv --reuid=nobody --regid=nogroup --groups=chimera "$@"; }
    check "the SVAR table is root's, group chimera, mode 0640" \
        test "$(stat -c '%U %G %a' /dev/shm/chimera.$SUB.svar)" = "root chimera 640"
    json=$(as_member "$CHIMTOP" "$SUB" --json --svar 2>&1)
    check "a member reads the running tasks and their SVAR values" python3 -c '
import json, sys
t = {x["rmod"]: x for x in json.loads(sys.argv[1])["tasks"]}
for n in ("puma_torque", "jtraj"):
    assert t[n]["state"] == "ON" and t[n]["cycle"] > 0, (n, t[n])
sv = t["puma_torque"]["svar"]
assert "error" not in sv and len(sv["in"]["T_REF"]) == 6, sv
' "$json" || echo "$json"
    tmux -L "$SOCK.member" new-session -d -x 200 -y 45 \
        "setpriv --reuid=nobody --regid=nogroup --groups=chimera $CHIMTOP $SUB --svar --rate 10 --sort rmod"
    for _ in $(seq 50); do has "$(tmux -L "$SOCK.member" capture-pane -p)" "SVAR of" && break; sleep 0.1; done
    check "tui: a member's chimtop shows the SVAR pane" grep -qE "^(in|out) +[A-Z_^]+ +double" \
        <<<"$(tmux -L "$SOCK.member" capture-pane -p | sed 's/^ *//')"
    # sbs as a member: read-only queries answer; commanding it stays with root.
    # The member runs the build tree's sbs and reads the example's .sbs: where
    # nobody cannot read them (a clone under a home directory of mode 0700,
    # as /root is), these checks cannot run.
    if ! as_member test -r "$SBS_FILE" || ! as_member "$SBS" --version >/dev/null 2>&1; then
        echo "skip - a member's sbs: nobody cannot read $SBS_FILE or run $SBS with its library (a clone under a directory of mode 0700, as /root is?); clone where others may read, e.g. /srv, for these checks"
    else
    out=$(as_member "$SBS" "$SBS_FILE" -c 'status; display T_REF' 2>&1); rc=$?
    echo "$out"
    check "a member's sbs queries it read-only: exit 0" test $rc -eq 0
    check "...status: the tasks ON and cycling" test "$(grep -cE '^(puma_torque|jtraj) +[a-z]+ +[0-9]+ P +[0-9]+ ON +[1-9]' <<<"$out")" -eq 2
    check "...display: T_REF's six values" grep -qE "^  T_REF +double\[6\]( +[-0-9.e+]+){6} +Nm" <<<"$out"
    out=$(as_member "$SBS" "$SBS_FILE" -c 'setvar Q_REF 0 --force' 2>&1); rc=$?
    check "a member's sbs may not write: exit 1" test $rc -eq 1
    check "...'permission denied', only root may" has "$out" \
        "error: permission denied: setvar writes a state variable, and subsystem $SUB runs as root: only root may command it (sudo sbs $SBS_FILE); this sbs only watches it: status, display, help, quit"
    out=$(setpriv --reuid=nobody --regid=nogroup --clear-groups "$SBS" "$SBS_FILE" -c status 2>&1); rc=$?
    check "a non-member's sbs: exit 1" test $rc -eq 1
    check "...told to join the group" has "$out" \
        "may not watch it either: segment /chimera.$SUB.status: permission denied: /dev/shm/chimera.$SUB.status is root's (group chimera, mode 0640): add yourself to group chimera (usermod -aG chimera nobody), then log in again"
    fi
else
    echo "skip - the member's view: needs root, setpriv (util-linux) and the group chimera (scripts/setup-debian.sh)"
fi

wait "$demo_pid"; rc=$?; demo_pid=
check "demo run 2 exits 0" test $rc -eq 0
if [ $member = 1 ]; then
    check "demo run 2 removed its SVAR table, though a member's chimtop still watches it (a watcher is no user)" \
        test ! -e /dev/shm/chimera.$SUB.svar
    check "...the member's chimtop still runs" tmux -L "$SOCK.member" has-session
    tmux -L "$SOCK.member" kill-server 2>/dev/null
fi
exit $fail
