#!/usr/bin/env bash
# The ABI test: the libchimera.so just built against the baseline
# abi/libchimera.abi (libabigail's abidiff over the public headers' types).
# Passes when nothing changed or functions/variables were only added; fails on
# any other change (removed or changed function or variable, a public type's
# size, layout or vtable) unless the soname differs from the baseline's, i.e.
# was bumped for it. docs/abi.md says how to update the baseline.
#   check_abi.sh BUILD/libchimera.so.X.Y.Z SOURCE_ROOT
set -uo pipefail
lib="$1"
root="$2"
baseline="$root/abi/libchimera.abi"
if ! command -v abidiff >/dev/null; then
  echo "abi: SKIPPED: abidiff not found (Debian package abigail-tools, installed by scripts/setup-debian.sh)"
  exit 77
fi
if ! readelf -S "$lib" | grep -q '\.debug_info'; then
  echo "abi: SKIPPED: $lib has no debug information (a build without -g): abidiff has no types to compare"
  exit 77
fi
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
"$root/scripts/abi-dump.sh" "$lib" "$tmp/current.abi" || { echo "abi: abidw failed on $lib"; exit 1; }

soname_now="$(readelf -d "$lib" | sed -n 's/.*(SONAME).*\[\(.*\)\]/\1/p')"
soname_base="$(sed -n "s/.*<abi-corpus [^>]*soname='\([^']*\)'.*/\1/p" "$baseline" | head -n 1)"

abidiff "$baseline" "$tmp/current.abi" >"$tmp/all"
all=$?
abidiff --no-added-syms "$baseline" "$tmp/current.abi" >"$tmp/changed"
changed=$?
if (((all | changed) & 1)); then
  echo "abi: abidiff failed (exit $all/$changed):"
  cat "$tmp/all" "$tmp/changed"
  exit 1
fi
if ((changed == 0)); then
  if ((all != 0)); then
    cat "$tmp/all"
    echo "abi: ok: only additions to the ABI of $soname_now (record them: scripts/abi-baseline.sh)"
  else
    echo "abi: ok: the ABI of $soname_now is the baseline's"
  fi
  exit 0
fi
cat "$tmp/changed"
if [[ "$soname_now" != "$soname_base" ]]; then
  echo "abi: ok: the ABI changed and the soname was bumped ($soname_base -> $soname_now):"
  echo "     regenerate the baseline with scripts/abi-baseline.sh and commit it"
  exit 0
fi
kind="changed"
((changed & 8)) && kind="changed incompatibly (abidiff: removed symbols or vtable changes)"
echo "abi: FAILED: the ABI of $soname_now $kind against abi/libchimera.abi, and the soname was not bumped."
echo "     Undo the change, or bump chimera_soversion in meson.build and run scripts/abi-baseline.sh (docs/abi.md)."
exit 1
