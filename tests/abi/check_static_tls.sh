#!/usr/bin/env bash
# libchimera's thread-local storage stays small. The library is marked
# STATIC_TLS (ipc's lock owner id is initial-exec, read on every table lock),
# so a program that dlopens it — Python importing the bindings — takes its
# whole TLS block from glibc's static surplus, about 1.6 KB shared by every
# such library: a big block there makes a later one fail to load (libgomp,
# through matplotlib: "cannot allocate memory in static TLS block"; seen when
# err's 1.4 KB abort slot was a plain thread_local). Large per-thread state
# goes behind a thread_local pointer instead (src/err/err.cpp).
#   check_static_tls.sh BUILD/libchimera.so.X.Y.Z [MAX_BYTES]
set -uo pipefail
lib="$1"
max="${2:-512}"
if ! command -v readelf >/dev/null; then
  echo "static_tls: SKIPPED: readelf not found (binutils)"
  exit 77
fi
# The TLS program header: its MemSiz (hex) is the block every thread gets.
memsz=$(readelf -lW "$lib" | awk '$1 == "TLS" { print $6 }')
if [[ -z "$memsz" ]]; then
  echo "static_tls: $lib has no thread-local storage"
  exit 0
fi
bytes=$((memsz))
echo "static_tls: $lib: TLS block of $bytes bytes (budget $max)"
if (( bytes > max )); then
  echo "static_tls: FAILED: more than $max bytes of TLS in a library other programs dlopen; move large per-thread state behind a thread_local pointer"
  exit 1
fi
