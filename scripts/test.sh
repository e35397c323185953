#!/usr/bin/env bash
# The whole test suite: install what is needed, configure, build, run every test.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup-debian.sh
if [ -d build ]; then meson setup --reconfigure build >/dev/null; else meson setup build; fi
ninja -C build
meson test -C build --print-errorlogs --num-processes 2 "$@"
scripts/fuzz.sh  # stage: bounded fuzzing, its own clang build (docs/fuzzing.md)
