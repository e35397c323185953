#!/usr/bin/env bash
# Runs a command where the raw_syscalls:sys_enter tracepoint can be opened
# (the system-call counter of test_prof and bench_prof). If tracefs is not
# mounted, it is mounted in a private mount namespace of this command only,
# so the machine's mounts are not touched. Exit 77 (skipped) when neither is
# possible (not root, no unshare).
# Usage: in_tracefs_namespace.sh COMMAND [ARGS...]
set -u
if [ -r /sys/kernel/tracing/events/raw_syscalls/sys_enter/id ] ||
   [ -r /sys/kernel/debug/tracing/events/raw_syscalls/sys_enter/id ]; then
    exec "$@"
fi
if ! command -v unshare >/dev/null || [ "$(id -u)" -ne 0 ]; then
    echo "tracefs not mounted and no way to mount it privately (needs root and unshare)"
    exit 77
fi
if ! reason=$(unshare -m true 2>&1); then
    echo "tracefs not mounted, and this container forbids a private mount namespace (unshare -m: ${reason:-refused}): skipped"
    exit 77
fi
exec unshare -m -- sh -c 'mount -t tracefs nodev /sys/kernel/tracing || { echo "cannot mount tracefs in a private namespace: skipped"; exit 77; }; exec "$@"' sh "$@"
