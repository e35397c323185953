#!/usr/bin/env bash
# Every program's command line (issue #16): --version prints "NAME (Chimera)
# VERSION" and exits 0, --help exits 0, an unknown option or a missing
# argument is a usage error with exit status 2 (not CLI11's 105..109), and
# the man page help2man made from --help names the program.
#   test_tool_cli.sh VERSION MANDIR PROGRAM...
set -uo pipefail
version=$1 mandir=$2
shift 2
fail=0
check() {  # what expected_status actual_status
    if [ "$2" != "$3" ]; then echo "FAIL: $1: exit status $3, expected $2"; fail=1; else echo "ok: $1"; fi
}
for prog in "$@"; do
    name=$(basename "$prog")
    out=$("$prog" --version 2>&1); st=$?
    check "$name --version" 0 $st
    [ "$out" = "$name (Chimera) $version" ] || { echo "FAIL: $name --version printed '$out'"; fail=1; }
    "$prog" --help >/dev/null 2>&1; check "$name --help" 0 $?
    err=$("$prog" --no-such-option 2>&1 >/dev/null); st=$?
    check "$name --no-such-option" 2 $st
    [ -n "$err" ] || { echo "FAIL: $name: a usage error with nothing said on stderr"; fail=1; }
    if [ -d "$mandir" ] && command -v help2man >/dev/null; then
        page="$mandir/$name.1"
        if [ -f "$page" ] && grep -q "$name" "$page"; then echo "ok: $name.1"; else echo "FAIL: no man page $page"; fail=1; fi
    fi
done
# A missing required argument is a usage error too.
"$1" >/dev/null 2>&1; st=$?
check "$(basename "$1") without its argument" 2 $st
exit $fail
