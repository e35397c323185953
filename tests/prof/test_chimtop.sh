#!/usr/bin/env bash
# chimtop against a live status segment published by fake_writer (the real
# writer API): --once, --json, field choice and sorting, then the ncurses view
# driven in tmux (send-keys / capture-pane): columns, rows, WARNING>/ERROR>
# lines, the SVAR pane, sorting, and surviving the subsystem's restart.
set -u
CHIMTOP=$1
WRITER=$2
SUB=chimtoptest_$$
SOCK=chimtop_$$
fail=0
check() {  # check "description" command...
    local what=$1; shift
    if "$@"; then echo "ok   - $what"; else echo "FAIL - $what"; fail=1; fi
}
has() { grep -q -- "$2" <<<"$1"; }
writer_pid=
start_writer() {
    "$WRITER" "$SUB" 60 > /tmp/$SUB.writer.log 2>&1 &
    writer_pid=$!
    for _ in $(seq 100); do grep -q ready /tmp/$SUB.writer.log 2>/dev/null && return 0; sleep 0.05; done
    echo "writer did not start"; cat /tmp/$SUB.writer.log; return 1
}
cleanup() {
    tmux -L "$SOCK" kill-server 2>/dev/null
    [ -n "$writer_pid" ] && kill "$writer_pid" 2>/dev/null && wait "$writer_pid" 2>/dev/null
    rm -f /tmp/$SUB.writer.log
}
trap cleanup EXIT

# No subsystem yet: a clear error, exit 1.
out=$("$CHIMTOP" "$SUB" --once 2>&1); rc=$?
check "--once without the subsystem fails" test $rc -eq 1
check "...naming the segment" has "$out" "/chimera.$SUB.status not found"
out=$("$CHIMTOP" "$SUB" --once --fields rmod,bogus 2>&1); rc=$?
check "unknown field rejected (exit 2)" test $rc -eq 2
check "...naming it" has "$out" "unknown status field 'bogus'"

out=$("$CHIMTOP" --list-fields 2>&1); rc=$?
check "--list-fields needs no subsystem" test $rc -eq 0
check "...and lists the §4.4.1 fields" test "$(awk '{print $1}' <<<"$out" | head -22 | xargs)" = \
    "rmod rtpu tid S crit state cycle miss refF refT mezF mezT ptime totC tick minU maxU avgU minC maxC avgC warn"

start_writer || exit 1
sleep 0.6

out=$("$CHIMTOP" "$SUB" --once)
echo "$out"
for f in rmod rtpu tid S crit state cycle miss refF mezF mezT ptime minC maxC avgC avgU warn policy; do
    check "--once header has $f" has "$(sed -n 2p <<<"$out")" " *$f"
done
check "--once has servo row" has "$out" "^servo "
check "--once has planner row" has "$out" "^planner "
check "--once has logger row in ERROR" grep -qE "^logger .* ERROR" <<<"$out"
check "ERROR> line" has "$out" "^ERROR> logger: disk full"
check "WARNING> line, first warning kept" has "$out" "^WARNING> planner: trajectory clipped$"

out=$("$CHIMTOP" "$SUB" --once --fields rmod,miss,cycle --sort miss --reverse)
first=$(sed -n 3p <<<"$out" | awk '{print $1}')
check "sort by miss, descending: planner first" test "$first" = planner
check "chosen fields only" test "$(sed -n 2p <<<"$out" | xargs)" = "rmod miss cycle"
out=$("$CHIMTOP" "$SUB" --once --fields cycle,rmod --sort rmod)
check "sort by rmod ascending: logger, planner, servo" \
    test "$(sed -n '3,$p' <<<"$out" | grep -vE '^(WARNING|ERROR)>' | awk '{print $2}' | xargs)" = "logger planner servo"

json=$("$CHIMTOP" "$SUB" --json --svar)
check "--json parses, 3 tasks, servo cycling at ~100 Hz, logger error" python3 -c '
import json, sys
j = json.loads(sys.argv[1])
t = {x["rmod"]: x for x in j["tasks"]}
assert j["subsystem"] == sys.argv[2] and len(t) == 3, t.keys()
s = t["servo"]
assert s["cycle"] > 10 and 60 < s["mezF"] < 140, s
assert s["refF"] == 100 and abs(s["refT"] - 0.01) < 1e-12
assert 0.0004 < s["avgC"] < 0.004, s["avgC"]
assert s["clock"] in ("perf-page", "thread-cputime")
assert t["planner"]["miss"] >= 1 and t["planner"]["warn"] == 2
assert t["logger"]["state"] == "ERROR" and t["logger"]["error"] == "disk full"
sv = s["svar"]
if "error" not in sv or "built without" not in sv["error"]:
    assert sv["in"]["Q_REF"] == [0.5, 1.5, 2.5], sv
    assert sv["out"]["TAU"] == [7, 8], sv
' "$json" "$SUB"

# ---- the live view in a terminal
tmux -L "$SOCK" new-session -d -x 160 -y 40 "$CHIMTOP $SUB --rate 10 --fields rmod,state,cycle,miss,warn --sort rmod"
sleep 1.2
screen=$(tmux -L "$SOCK" capture-pane -p)
echo "$screen"
check "tui: title names the subsystem" has "$screen" "chimtop  subsystem $SUB"
check "tui: column header" grep -qE "rmod +state +cycle +miss +warn" <<<"$screen"
check "tui: three task rows" test "$(grep -cE '^(servo|planner|logger) ' <<<"$screen")" -eq 3
check "tui: ERROR> line" has "$screen" "ERROR> logger: disk full"
check "tui: WARNING> line" has "$screen" "WARNING> planner: trajectory clipped"
order=$(grep -E '^(servo|planner|logger) ' <<<"$screen" | awk '{print $1}' | xargs)
check "tui: sorted by rmod" test "$order" = "logger planner servo"

tmux -L "$SOCK" send-keys r
sleep 0.5
screen=$(tmux -L "$SOCK" capture-pane -p)
order=$(grep -E '^(servo|planner|logger) ' <<<"$screen" | awk '{print $1}' | xargs)
check "tui: 'r' reverses the sort" test "$order" = "servo planner logger"

tmux -L "$SOCK" send-keys v
sleep 0.5
screen=$(tmux -L "$SOCK" capture-pane -p)
check "tui: 'v' opens the SVAR pane for the selected task (servo)" has "$screen" "SVAR of servo"
if ! has "$screen" "built without the svar service"; then
    check "tui: SVAR pane shows Q_REF values" grep -qE "in  Q_REF .*0.5 1.5 2.5" <<<"$screen"
    check "tui: SVAR pane shows TAU values" grep -qE "out TAU .*7 8" <<<"$screen"
fi

tmux -L "$SOCK" send-keys f
sleep 0.3
tmux -L "$SOCK" send-keys "rmod,crit,policy" Enter
sleep 0.5
screen=$(tmux -L "$SOCK" capture-pane -p)
check "tui: 'f' chooses and orders fields" grep -qE "rmod +crit +policy" <<<"$screen"
check "tui: policy column shown" has "$screen" "SCHED_OTHER (test)"

# The subsystem stops ...
kill "$writer_pid"; wait "$writer_pid" 2>/dev/null; writer_pid=
sleep 0.6
screen=$(tmux -L "$SOCK" capture-pane -p)
check "tui: subsystem stopped -> waiting" has "$screen" "waiting for subsystem '$SUB'"
# ... and comes back.
start_writer || exit 1
sleep 1.0
screen=$(tmux -L "$SOCK" capture-pane -p)
echo "$screen"
check "tui: re-attached after restart" test "$(grep -cE '^(servo|planner|logger) ' <<<"$screen")" -eq 3
check "tui: says it re-attached" has "$screen" "(re-attached)"

tmux -L "$SOCK" send-keys q
sleep 0.4
check "tui: 'q' quits" bash -c "! tmux -L $SOCK has-session 2>/dev/null"
exit $fail
