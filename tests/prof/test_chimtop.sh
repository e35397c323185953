#!/usr/bin/env bash
# chimtop against a live status segment published by fake_writer (the real
# writer API): --once, --json, field choice and sorting, then the ncurses view
# driven in tmux (send-keys / capture-pane): columns, rows, WARNING>/ERROR>
# lines, the SVAR pane, sorting, the help screen, the field picker, search and
# filter, the RTPU summary lines, `z` restarting only this chimtop's window,
# the list of running subsystems, who may watch (a member of the group chimera
# reads, a non-member gets "permission denied" and what to do), and surviving
# the subsystem's restart.
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
header_of() { grep -m1 -vE '^(subsystem|RTPU) ' <<<"$1"; }      # --once: the column header
rows_of() { awk 'h { print } !h && !/^(subsystem|RTPU) / { h = 1 }' <<<"$1"; }  # --once: the lines after it
screen() { tmux -L "$SOCK" capture-pane -p; }
keys() { tmux -L "$SOCK" send-keys "$@"; sleep 0.4; }
writer_pid=
start_writer() {
    "$WRITER" "$SUB" 60 > /tmp/$SUB.writer.log 2>&1 &
    writer_pid=$!
    for _ in $(seq 100); do grep -q ready /tmp/$SUB.writer.log 2>/dev/null && return 0; sleep 0.05; done
    echo "writer did not start"; cat /tmp/$SUB.writer.log; return 1
}
cleanup() {
    tmux -L "$SOCK" kill-server 2>/dev/null
    tmux -L "$SOCK.member" kill-server 2>/dev/null
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
for f in rmod rtpu tid S crit state cycle miss mezF 'avgC\[us\]' 'maxC\[us\]' 'cycP99\[us\]' 'latP99\[us\]' avgU warn policy; do
    check "--once header has $f" has "$(header_of "$out")" " *$f"
done
check "--once says the unit" has "$(head -1 <<<"$out")" "(times in us)"
check "--once: a summary line per RTPU, named as in the .sbs" \
    grep -qE "^RTPU ctrl +cpu 0 +2 tasks +1 ON .*1 in ERROR" <<<"$out"
check "--once: ...the second RTPU" grep -qE "^RTPU plan +cpu 1 +1 task +1 ON +CPU +[0-9.]+% +miss [1-9]" <<<"$out"
check "--once: the rtpu column names the RTPU" grep -qE "^servo +ctrl " <<<"$out"

check "--once has servo row" has "$out" "^servo "
check "--once has planner row" has "$out" "^planner "
check "--once has logger row in ERROR" grep -qE "^logger .* ERROR" <<<"$out"
check "ERROR> line" has "$out" "^ERROR> logger: disk full"
check "WARNING> line, first warning kept" has "$out" "^WARNING> planner: trajectory clipped$"

out=$("$CHIMTOP" "$SUB" --once --fields rmod,miss,cycle --sort miss --reverse)
first=$(rows_of "$out" | head -1 | awk '{print $1}')
check "sort by miss, descending: planner first" test "$first" = planner
check "chosen fields only" test "$(header_of "$out" | xargs)" = "rmod miss cycle"
out=$("$CHIMTOP" "$SUB" --once --fields cycle,rmod --sort rmod)
check "sort by rmod ascending: logger, planner, servo" \
    test "$(rows_of "$out" | grep -vE '^(WARNING|ERROR)>' | awk '{print $2}' | xargs)" = "logger planner servo"

json=$("$CHIMTOP" "$SUB" --json --svar)
check "--json parses, 3 tasks, servo cycling at ~100 Hz, logger error" python3 -c '
import json, sys
j = json.loads(sys.argv[1])
t = {x["rmod"]: x for x in j["tasks"]}
assert j["subsystem"] == sys.argv[2] and len(t) == 3, t.keys()
s = t["servo"]
assert j["time_unit"] == "us"
assert s["cycle"] > 10 and 60 < s["mezF"] < 140, s
assert s["refF"] == 100 and abs(s["refT"] - 10000) < 1e-6      # us
assert 400 < s["avgC"] < 4000, s["avgC"]                        # 0.5 ms of work, in us
assert s["clock"] in ("perf-page", "thread-cputime")
assert s["rtpu"] == 0 and s["rtpu_name"] == "ctrl" and t["planner"]["rtpu_name"] == "plan"
# 14.11: the percentiles of the real histograms; cycle time >= the work done
assert 400 <= s["cycP50"] <= s["cycP99"] <= s["cycMax"], s
assert 0 <= s["latP50"] <= s["latP99"] <= s["latMax"], s
assert t["logger"]["cycP50"] is None and t["logger"]["latP99"] is None   # no cycle yet
r = {x["name"]: x for x in j["rtpus"]}
assert r["ctrl"]["tasks"] == 2 and r["ctrl"]["on"] == 1 and r["ctrl"]["errors"] == 1, r
assert r["plan"]["cpu"] == 1 and r["plan"]["latP99"] == t["planner"]["latP99"], r
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

keys v  # the pane off again

# ---- 16.6: the help screen, from h, ? and F1; any key goes back
for k in h '?' F1; do
    keys "$k"
    s=$(screen)
    check "tui: '$k' shows the help screen" has "$s" "this help (any key: back)"
    check "tui: ...which explains the window and the unit" has "$s" "Every time is in microseconds (us)"
    keys x
    check "tui: ...and any key goes back to the table" has "$(screen)" "chimtop  subsystem $SUB"
done

# ---- the field picker lists every field; space shows/hides, [ ] move, Enter closes
keys f
s=$(screen)
echo "$s"
nfields=$("$CHIMTOP" --list-fields | wc -l)
check "tui: 'f' lists every field ($nfields)" test "$(grep -cE '^\[[x ]\] ' <<<"$s")" -eq "$nfields"
check "tui: ...shown ones first, marked" test "$(grep -E '^\[x\] ' <<<"$s" | awk '{print $2}' | xargs)" = "rmod state cycle miss warn"
check "tui: ...with a unit for times" grep -qE '^\[ \] latP99\[us\] +release lateness' <<<"$s"
# order: rmod state cycle miss warn | rtpu tid S crit ...: crit is the 9th line
keys j j j j j j j j Space '['   # show crit, then one earlier: before warn
keys Up Up Up Space             # hide state (the cursor is on it)
keys Enter
s=$(screen)
check "tui: fields chosen in the picker, in its order" grep -qE "rmod +cycle +miss +crit +warn" <<<"$s"
check "tui: ...state hidden" bash -c '! grep -qE "rmod +state" <<<"$1"' _ "$s"

# ---- RTPU summary lines and names; the unit in the header
check "tui: summary line of RTPU ctrl" grep -qE "^RTPU ctrl +cpu 0 +2 tasks +1 ON" <<<"$s"
check "tui: summary line of RTPU plan" grep -qE "^RTPU plan +cpu 1 +1 task " <<<"$s"
check "tui: title says the unit" has "$s" "times in us"

# ---- filter (\ or F4) hides; Esc shows all again
keys -l '\'; keys p l a n Enter
s=$(screen)
check "tui: filter 'plan' leaves the planner only" test "$(grep -cE '^(servo|planner|logger) ' <<<"$s")" -eq 1
check "tui: ...planner" grep -qE '^planner ' <<<"$s"
check "tui: ...and the title says so" has "$s" "filter 'plan'"
keys Escape
check "tui: Esc clears the filter" test "$(grep -cE '^(servo|planner|logger) ' <<<"$(screen)")" -eq 3
keys F4 e r r Enter
check "tui: F4 filters too (by state: ERROR)" test "$(grep -cE '^(servo|planner|logger) ' <<<"$(screen)" | xargs)" -eq 1
keys Escape

# ---- search (/ or F3) selects the next match: the SVAR pane follows the selection
keys / p l a n Enter v
check "tui: search 'plan' selects the planner" has "$(screen)" "SVAR of planner"
keys v F3 l o g Enter v
check "tui: F3 searches too (logger selected)" has "$(screen)" "SVAR of logger"
keys v

# ---- z restarts THIS chimtop's window only: another reader's counts do not fall
cyc() { "$CHIMTOP" "$SUB" --json | python3 -c 'import json,sys; print({t["rmod"]: t["cycle"] for t in json.load(sys.stdin)["tasks"]}["servo"])'; }
before=$(cyc)
keys z
sleep 0.3
after=$(cyc)
check "tui: z leaves another reader's counts alone ($before -> $after)" test "$after" -ge "$before"
s=$(screen)
check "tui: z says what it did" has "$s" "window restarted"
check "tui: ...the title shows the window's length" grep -qE "window [0-9]+\.[0-9] s" <<<"$s"
servo_cycles=$(grep -E '^servo ' <<<"$s" | awk '{print $2}')  # rmod cycle miss crit warn
check "tui: ...and its own counts restart ($servo_cycles < $after)" test "$servo_cycles" -lt "$after"

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

# ---- started without a subsystem: the running ones, to choose from
out=$("$CHIMTOP" --once)
check "--once without a name lists the running subsystems" grep -qE "^$SUB +running \(pid $writer_pid\) +3 tasks" <<<"$out"
tmux -L "$SOCK" new-session -d -x 160 -y 40 "$CHIMTOP --rate 10"
sleep 0.8
s=$(screen)
echo "$s"
check "tui: no name -> the list of subsystems" has "$s" "Chimera subsystems on this machine"
line=$(grep -nE "^$SUB " <<<"$s" | cut -d: -f1)
check "tui: ...ours is listed" test -n "$line"
for _ in $(seq $((line - 3))); do tmux -L "$SOCK" send-keys Down; done
keys Enter
sleep 0.5
check "tui: Enter watches the chosen one" has "$(screen)" "chimtop  subsystem $SUB "
tmux -L "$SOCK" kill-server 2>/dev/null

# ---- 16.7 who may watch: a member of the watch group reads, read-only; a
# non-member is told "permission denied" and what to do (as nobody, via setpriv)
if command -v setpriv >/dev/null && [ "$(id -u)" = 0 ] && getent group chimera >/dev/null; then
    as_member() { setpriv --reuid=nobody --regid=nogroup --groups=chimera "$@"; }
    as_stranger() { setpriv --reuid=nobody --regid=nogroup --clear-groups "$@"; }
    check "the status segment is root's, group chimera, mode 0640" \
        test "$(stat -c '%U %G %a' /dev/shm/chimera.$SUB.status)" = "root chimera 640"
    json=$(as_member "$CHIMTOP" "$SUB" --json --svar 2>&1); rc=$?
    check "a member of chimera watches: exit 0" test $rc -eq 0
    check "...the tasks and the SVAR values, as root sees them" python3 -c '
import json, sys
t = {x["rmod"]: x for x in json.loads(sys.argv[1])["tasks"]}
assert set(t) == {"servo", "planner", "logger"} and t["servo"]["cycle"] > 0, t
sv = t["servo"]["svar"]
if "error" not in sv or "built without" not in sv["error"]:
    assert sv["in"]["Q_REF"] == [0.5, 1.5, 2.5] and sv["out"]["TAU"] == [7, 8], sv
' "$json" || echo "$json"
    out=$(as_member "$CHIMTOP" "$SUB" --once --half-tick 1 2>&1); rc=$?
    check "a member cannot change the accounting (--half-tick): exit 1" test $rc -eq 1
    check "...'permission denied', only root may" has "$out" \
        "permission denied: /dev/shm/chimera.$SUB.status is root's (group chimera, mode 0640): only root may change it: run as root (sudo); members of group chimera may only watch it"
    out=$(as_stranger "$CHIMTOP" "$SUB" --once 2>&1); rc=$?
    check "a non-member: exit 1" test $rc -eq 1
    check "...'permission denied' and what to do, not 'not found'" has "$out" \
        "permission denied: /dev/shm/chimera.$SUB.status is root's (group chimera, mode 0640): add yourself to group chimera (usermod -aG chimera nobody), then log in again"
    out=$(as_stranger "$CHIMTOP" --once 2>&1)
    check "a non-member's list says so too" grep -qE "^$SUB +permission denied" <<<"$out"
    tmux -L "$SOCK" new-session -d -x 220 -y 20 "setpriv --reuid=nobody --regid=nogroup --clear-groups $CHIMTOP $SUB"
    sleep 0.8
    check "tui: a non-member sees 'permission denied'" has "$(screen)" "permission denied: /dev/shm/chimera.$SUB.status"
    tmux -L "$SOCK" kill-server 2>/dev/null
    # A server of its own: a new one on the socket just killed may find it still going away.
    tmux -L "$SOCK.member" new-session -d -x 160 -y 40 "setpriv --reuid=nobody --regid=nogroup --groups=chimera $CHIMTOP $SUB --rate 10"
    rows() { test "$(grep -cE '^(servo|planner|logger) ' <<<"$(tmux -L "$SOCK.member" capture-pane -p)")" -eq 3; }
    for _ in $(seq 50); do rows && break; sleep 0.1; done
    check "tui: a member sees the three tasks" rows || tmux -L "$SOCK.member" capture-pane -p
    tmux -L "$SOCK.member" kill-server 2>/dev/null
else
    echo "skip - permission tests: need root, setpriv (util-linux) and the group chimera (scripts/setup-debian.sh)"
fi
exit $fail
