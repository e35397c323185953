#!/usr/bin/env bash
# Runs svar_hot_path_check under strace and shows the system calls made
# between its "hot path begin" and "hot path end" markers (there must be none),
# and its own count of allocations in the same loop (there must be none).
#   bench/svar/check_hot_path.sh BUILD_DIR [ITERATIONS]
set -euo pipefail
build=${1:?usage: check_hot_path.sh BUILD_DIR [ITERATIONS]}
iterations=${2:-100000}
exe="$build/bench/svar/svar_hot_path_check"
command -v strace >/dev/null || { echo "check_hot_path: strace is not installed (apt-get install strace)" >&2; exit 2; }
log=$(mktemp /tmp/svar_hot_path.strace.XXXXXX)
trap 'rm -f "$log"' EXIT
strace -f -qq -o "$log" "$exe" "$iterations"
grep -q 'write(2, "hot path end' "$log" || { echo "check_hot_path: markers not found in the strace log" >&2; exit 2; }
# Lines strictly between the two marker writes.
inside=$(awk '/write\(2, "hot path begin/ {on=1; next} /write\(2, "hot path end/ {on=0} on' "$log")
echo "system calls in the whole run: $(wc -l < "$log")"
if [ -n "$inside" ]; then
    echo "system calls between the markers ($(printf '%s\n' "$inside" | wc -l)):"
    printf '%s\n' "$inside" | head -20
    exit 1
fi
echo "system calls between the markers: 0"
