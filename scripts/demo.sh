#!/usr/bin/env bash
# The main job: install what is needed, build the demo (only what it needs,
# and chimtop and sbs, which the README runs beside it), and run the example
# subsystem. Package and build output go to
# build/demo-setup.log; the screen shows the demo.
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p build
log=build/demo-setup.log
: > "$log"
step() {  # step WHAT COMMAND...: runs quietly, shows the log's tail on failure
    echo "demo: $1 (log: $log)"
    if ! "${@:2}" >>"$log" 2>&1; then
        echo "demo: $1 failed; the end of $log:" >&2
        tail -n 30 "$log" >&2
        exit 1
    fi
}
step "installing the Debian packages it needs" scripts/setup-debian.sh --demo
if [ -f build/build.ninja ]; then
    step "configuring" meson setup --reconfigure build
else
    step "configuring" meson setup build
fi
step "building the demo, its modules, chimtop and sbs" ninja -C build demo-only
echo
exec build/examples/demo "$@"
