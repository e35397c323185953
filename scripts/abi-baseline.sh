#!/usr/bin/env bash
# Regenerates the ABI baseline abi/libchimera.abi from a build (default:
# build/). Run it on a deliberate ABI change, after bumping the soname when
# the change is incompatible (docs/abi.md), and commit the new file with the
# change.
#   scripts/abi-baseline.sh [BUILD_DIR]
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
build="${1:-$root/build}"
lib="$(find "$build" -maxdepth 1 -name 'libchimera.so.*.*.*' -type f | head -n 1)"
if [[ -z "$lib" ]]; then
  echo "abi-baseline: no libchimera.so.X.Y.Z in $build (ninja -C $build first)" >&2
  exit 1
fi
"$root/scripts/abi-dump.sh" "$lib" "$root/abi/libchimera.abi"
echo "abi-baseline: wrote abi/libchimera.abi from $lib ($(grep -c '<elf-symbol ' "$root/abi/libchimera.abi") symbols)"
