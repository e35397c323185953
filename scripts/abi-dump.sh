#!/usr/bin/env bash
# Writes the ABI of a built libchimera.so as libabigail XML: only what the
# public headers (include/chimera) declare, without source paths, so the same
# library gives the same file in any checkout. Used for the baseline
# (scripts/abi-baseline.sh) and by the ABI test (tests/abi/check_abi.sh), so
# both sides of the comparison are made the same way.
#   scripts/abi-dump.sh BUILD/libchimera.so.X.Y.Z OUT.abi
set -euo pipefail
if (($# != 2)); then
  echo "usage: $0 LIBRARY OUT.abi" >&2
  exit 2
fi
root="$(cd "$(dirname "$0")/.." && pwd)"
exec abidw --headers-dir "$root/include/chimera" --drop-private-types \
  --no-show-locs --no-comp-dir-path --no-corpus-path --no-architecture \
  --out-file "$2" "$1"
