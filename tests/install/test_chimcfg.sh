#!/usr/bin/env bash
# Runs the chimcfg binary as a user does (issue 2, "A tool for users"): check
# prints one summary line per good file and exits 0, or prints the FILE:LINE:
# errors of the bad ones on stderr and exits 1; dump prints every variable of a
# .svar (name, type, nelem, units, desc, init, min, max). One validator (issue
# #15.4): check refuses, with FILE:LINE, what spawn and sbs refuse.
#   test_chimcfg.sh CHIMCFG SOURCE_ROOT PID_MODULE_DIR
# (PID_MODULE_DIR empty: the robotics modules are not built, and the LOCAL
# checks against a module's declarations are skipped, saying so.)
set -uo pipefail
chimcfg=$(readlink -f "${1:?usage: test_chimcfg.sh CHIMCFG SOURCE_ROOT}")
source=$(cd "${2:?usage: test_chimcfg.sh CHIMCFG SOURCE_ROOT PID_MODULE_DIR}" && pwd)
pid_dir=${3:+$(readlink -f "$3")}
unset CHIMERA_MODULE_PATH
cd "$source/tests/install/data"
thesis=../../svar/data
out=$(mktemp) err=$(mktemp) tmp=$(mktemp -d)
trap 'rm -rf "$out" "$err" "$tmp"' EXIT
failures=0

# run EXPECTED_STATUS ARGS...: runs chimcfg, keeps stdout/stderr in $out/$err.
run() {
    local want=$1; shift
    "$chimcfg" "$@" > "$out" 2> "$err"
    local got=$?
    if [ "$got" != "$want" ]; then
        echo "FAIL: chimcfg $* exited $got, expected $want; stderr:" >&2
        cat "$err" >&2
        failures=$((failures + 1))
        return 1
    fi
}
# same NAME FILE TEXT: the file holds exactly TEXT.
same() {
    if [ "$(cat "$2")" != "$3" ]; then
        echo "FAIL: $1" >&2
        diff -u <(printf '%s\n' "$3") "$2" >&2
        failures=$((failures + 1))
    fi
}

# Good files of the three kinds: one line each, exit 0, nothing on stderr.
run 0 check controller.svar ctl.rmod ctl.sbs &&
same "check of good files (stdout)" "$out" "controller.svar: ok, svar, 3 variables, 76 bytes of data
ctl.rmod: ok, rmod ctl, module pid, periodic at 100 Hz; in-consts GAIN; out-consts none; in-vars Q_REF; out-vars TAU; ports checked against controller.svar; LOCAL checked against module pid
ctl.sbs: ok, subsystem ctl, 1 RTPU, master main, svar controller.svar (3 variables)" &&
same "check of good files (stderr)" "$err" ""

# The module checked is loaded into chimcfg's own copy of the runtime
# (libchimera.so, as sbs has it), not into a second copy it brings in itself:
# two copies in one process (two sets of globals, LTTng-UST loaded late with
# dynamic TLS) made the ASan build's leak check crash at exit in a fresh
# Debian 12 root. The dynamic linker names who first needs the library.
loads=$(LD_DEBUG=files "$chimcfg" check ctl.rmod 2>&1 > /dev/null | grep -E "file=libchimera\.so\.[0-9]+ .*needed by")
if [ "$(printf '%s\n' "$loads" | grep -c .)" != 1 ] || ! grep -q "needed by $chimcfg " <<< "$loads"; then
    echo "FAIL: chimcfg should load libchimera.so once, itself; the dynamic linker says:" >&2
    printf '%s\n' "${loads:-(no libchimera.so loaded)}" >&2
    failures=$((failures + 1))
fi

# The thesis's own sample .svar (§5.5.2) is rejected at the line saying AME...
run 1 check $thesis/thesis_sample.svar &&
same "thesis sample (stderr)" "$err" "$thesis/thesis_sample.svar:23: expected NAME, found AME" &&
same "thesis sample (stdout)" "$out" ""
# ...and accepted once that line is fixed.
run 0 check $thesis/thesis_sample_fixed.svar &&
same "fixed thesis sample" "$out" "$thesis/thesis_sample_fixed.svar: ok, svar, 4 variables, 272 bytes of data"

# Good and bad together: the good ones still get their line, exit 1.
run 1 check ctl.rmod truncated.svar bad_keyword.rmod nothere.svar notes.txt &&
same "mixed check (stdout)" "$out" "ctl.rmod: ok, rmod ctl, module pid, periodic at 100 Hz; in-consts GAIN; out-consts none; in-vars Q_REF; out-vars TAU; ports not checked (give the .sbs or .svar too); LOCAL checked against module pid" &&
same "mixed check (stderr)" "$err" "truncated.svar:6: truncated file: expected EOF as the last line, found end of file
bad_keyword.rmod:9: a periodic task needs FREQ or PERIOD, found FRQ
nothere.svar: cannot open file: No such file or directory
notes.txt: unknown kind of file '.txt' (expected .svar, .rmod or .sbs)"

# One validator: what spawn refuses, check refuses, at the line.
# LOCAL values against the keys the module declares (the module loaded as spawn
# loads it): not finite, out of range, a misspelt key.
rmod_with() {  # rmod_with NAME LOCAL-LINE: ctl.rmod with a LOCAL section
    sed '/^EOF/d' ctl.rmod > "$tmp/$1.rmod"
    printf 'LOCAL\nKP 1\n%s\nEOF\n' "$2" >> "$tmp/$1.rmod"
}
rmod_with inf 'KI inf'
rmod_with nan 'KD nan'
rmod_with huge 'ILIMIT 1e309'
rmod_with negative 'ILIMIT -5'
rmod_with typo 'ILIMT 0.5'
rmod_with good 'ILIMIT 0.5'
if [ -z "$pid_dir" ]; then
    echo "chimcfg: the pid module is not built (robotics off): LOCAL against its declarations not checked"
else
run 1 check --module-path "$pid_dir" "$tmp/inf.rmod" "$tmp/nan.rmod" "$tmp/huge.rmod" "$tmp/negative.rmod" \
    "$tmp/typo.rmod" &&
same "LOCAL against the declarations" "$err" "$tmp/inf.rmod:12: LOCAL KI: 'inf' is not a number
$tmp/nan.rmod:12: LOCAL KD: 'nan' is not a number
$tmp/huge.rmod:12: LOCAL ILIMIT: '1e309' is not a number
$tmp/negative.rmod:12: LOCAL ILIMIT: -5 is out of range [0, inf]
$tmp/typo.rmod:12: LOCAL ILIMT: not a key of pid (KP, KI, KD, ILIMIT, ULIMIT, STALE, SLEW)"
CHIMERA_MODULE_PATH=$pid_dir run 0 check "$tmp/good.rmod" &&
same "LOCAL checked" "$out" "$tmp/good.rmod: ok, rmod good, module pid, periodic at 100 Hz; in-consts GAIN; out-consts none; in-vars Q_REF; out-vars TAU; ports not checked (give the .sbs or .svar too); LOCAL checked against module pid"
fi
run 0 check --no-modules "$tmp/inf.rmod" &&
same "--no-modules" "$out" "$tmp/inf.rmod: ok, rmod inf, module pid, periodic at 100 Hz; in-consts GAIN; out-consts none; in-vars Q_REF; out-vars TAU; ports not checked (give the .sbs or .svar too); LOCAL not checked (--no-modules)"

# Ranges: a task frequency above 1 MHz (FREQ 1e23 was '1e+23 Hz').
sed 's/^FREQ .*/FREQ      99999999999999999999999/' ctl.rmod > "$tmp/fast.rmod"
run 1 check "$tmp/fast.rmod" &&
same "FREQ 1e23" "$err" "$tmp/fast.rmod:9: FREQ 99999999999999999999999: 1e+23 Hz is above the highest task frequency, 1e+06 Hz (a period of 1 us)"

# From the build tree the shipped modules are on the default path (above);
# a module nowhere leaves LOCAL unchecked and says how to name its folder.
sed 's/^MODULE .*/MODULE    ghostmod/' ctl.rmod > "$tmp/ghost.rmod"
run 0 check "$tmp/ghost.rmod" &&
grep -q "LOCAL not checked (module ghostmod not on the module path: --module-path DIR or CHIMERA_MODULE_PATH)" "$out" ||
    { echo "FAIL: a module nowhere:" >&2; cat "$out" "$err" >&2; failures=$((failures + 1)); }

# A .rmod's ports against the table of the .sbs (or .svar) checked with it, as
# spawn holds them.
sed 's/^INVAR .*/INVAR     NOSUCH/' ctl.rmod > "$tmp/port.rmod"
run 1 check ctl.sbs "$tmp/port.rmod" &&
same "ports" "$err" "$tmp/port.rmod: INVAR NOSUCH is not a variable of the state variable table controller.svar"

# An RTPU's frequency bounds hold to the task frequency range, and its CPU to
# the CPUs this machine lets the process use, as sbs holds them.
sed 's/^MAXFREQ .*/MAXFREQ 1e30/' ctl.sbs > "$tmp/maxfreq.sbs"
sed 's/^RTPU .*/RTPU main 200/' ctl.sbs > "$tmp/cpu.sbs"
cp controller.svar "$tmp/"
run 1 check "$tmp/maxfreq.sbs" "$tmp/cpu.sbs" &&
same "MAXFREQ, CPU" "$err" "$tmp/maxfreq.sbs:$(grep -n '^MAXFREQ' ctl.sbs | cut -d: -f1): MAXFREQ: 1e+30 Hz is above the highest task frequency, 1e+06 Hz (a period of 1 us)
$tmp/cpu.sbs:$(grep -n '^RTPU' ctl.sbs | cut -d: -f1): RTPU main names CPU 200, which this process may not use (it has $(nproc) CPUs)"

# Sizes without overflow, bounded by the documented maximum: 64 x
# struct[1073741824] wrapped to '0 bytes of data'; one NELEM of 2 GB is refused
# at its line without allocating it.
{
    for i in $(seq 64); do printf 'NAME V%d\nTYPE struct[1073741824]\nDESC x\nUNITS none\nNELEM 1\n\n' "$i"; done
    echo EOF
} > "$tmp/wrap.svar"
printf 'NAME V\nTYPE double\nDESC x\nUNITS none\nNELEM 268435456\n\nEOF\n' > "$tmp/big.svar"
run 1 check "$tmp/wrap.svar" "$tmp/big.svar" &&
same "sizes" "$err" "$tmp/wrap.svar:5: NELEM 1 of V1 (struct[1073741824]) needs more than the 256 MiB a table may hold
$tmp/big.svar:5: NELEM 268435456 of V (double) needs more than the 256 MiB a table may hold"
printf 'NAME V\nTYPE double\nDESC x\nUNITS none\nNELEM 1\nINIT 1e309\n\nEOF\n' > "$tmp/init.svar"
run 1 check "$tmp/init.svar" &&
same "INIT 1e309" "$err" "$tmp/init.svar:6: expected a number for INIT value 1 of V, found '1e309'"

# Regular files only, never blocking or reading without end; an empty file
# has a line.
mkfifo "$tmp/fifo.svar"
ln -s /dev/zero "$tmp/zero.rmod"
: > "$tmp/empty.sbs"
timeout 10 "$chimcfg" check "$tmp/fifo.svar" "$tmp/zero.rmod" "$tmp/empty.sbs" > "$out" 2> "$err"
status=$?
[ "$status" = 1 ] || { echo "FAIL: FIFO, /dev/zero, empty: exit $status (124: it blocked)" >&2; failures=$((failures + 1)); }
same "not regular, empty" "$err" "$tmp/fifo.svar: cannot read file: it is a FIFO, not a regular file
$tmp/zero.rmod: cannot read file: it is a character device, not a regular file
$tmp/empty.sbs:1: empty file: expected the file's content and EOF as the last line"
head -c $((5 * 1024 * 1024)) /dev/zero | tr '\0' '#' > "$tmp/long.svar"
run 1 check "$tmp/long.svar" && grep -q "more than the 4 MiB a configuration file may have" "$err" ||
    { echo "FAIL: a 5 MiB file is refused unread:" >&2; cat "$err" >&2; failures=$((failures + 1)); }

# dump: every variable with its type, nelem, units, desc, init, min and max.
run 0 dump controller.svar && same "dump" "$out" "$(cat controller.dump)"
run 1 dump $thesis/thesis_sample.svar &&
same "dump of a bad file" "$err" "$thesis/thesis_sample.svar:23: expected NAME, found AME"
run 1 dump ctl.rmod && same "dump of a .rmod" "$err" "ctl.rmod: dump reads .svar files"

# No subcommand is a usage error.
"$chimcfg" > /dev/null 2>&1 && { echo "FAIL: chimcfg without a subcommand exited 0" >&2; failures=$((failures + 1)); }

if [ "$failures" != 0 ]; then
    echo "chimcfg: $failures check(s) failed" >&2
    exit 1
fi
echo "chimcfg: all checks passed"
