#!/usr/bin/env bash
# The main job: install what is needed, build, and run the example subsystem.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup-debian.sh
if [ -d build ]; then meson setup --reconfigure build >/dev/null; else meson setup build; fi
ninja -C build
exec build/examples/demo "$@"
