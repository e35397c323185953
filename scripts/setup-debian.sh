#!/usr/bin/env bash
# Installs the Debian 12 packages Chimera builds with (see README, "Dependencies").
#   scripts/setup-debian.sh          everything: the full build and the test suite (scripts/test.sh)
#   scripts/setup-debian.sh --demo   only what configuring and building the demo needs (scripts/demo.sh)
# Idempotent: packages already installed are not fetched again.
set -euo pipefail
# What `meson setup` requires and what `ninja -C build demo-only` builds with;
# every other feature is 'auto' and stays off without its packages.
demo_packages=(
  meson ninja-build pkg-config g++               # build
  dpkg-dev                                       # dpkg-architecture: meson then installs into lib/<multiarch>, where Debian's loader and pkg-config look
  libgtest-dev                                   # configure requires it (-Dtests is on by default, and the demo shares build/ with scripts/test.sh)
  libcli11-dev nlohmann-json3-dev libedit-dev    # configure requires them: every tool's options, --json output, sbs line editing
  libeigen3-dev liborocos-kdl-dev libkdl-parser-dev liburdfdom-dev  # robotics modules: the demo's trajectory generator, PID and PUMA simulator
  libncurses-dev                                 # chimtop, which the README runs beside the demo
)
test_packages=(
  make                                           # the Makefile chimgen writes for a module built outside the tree
  libgmock-dev libbenchmark-dev                  # the tests' mocks, bench/
  libgpiod-dev gpiod                             # PIO driver (optional)
  liblttng-ust-dev lttng-tools babeltrace2       # tracing (optional)
  linux-libc-dev                                 # SocketCAN, perf_event, futex headers
  rt-tests tmux util-linux                       # cyclictest (bench), terminal tests, taskset
  help2man                                       # the programs' man pages, from their --help
  strace                                         # the no-system-call check of the SVAR hot path (test)
  clang libclang-rt-14-dev                       # scripts/fuzz.sh: libFuzzer (-fsanitize=fuzzer needs the runtime, only recommended by clang)
  abigail-tools                                  # abidw/abidiff: the ABI check against abi/libchimera.abi (tests/abi)
  pybind11-dev python3-dev python3-numpy         # the Python bindings, import chimera (optional: -Dpython)
  python3-pytest mypy python3-pandas             # their tests: pytest, the stubs checked by mypy, to_dataframe()
  python3-matplotlib                             # examples/python/step_response.py's plot; docs/thesis_plots.py (the thesis's figures)
  cyclonedds-dev cyclonedds-tools                # ddsbridge: Cyclone DDS C API, idlc (the wire types from IDL) and ddsperf (bench) (optional: -Ddds)
  iproute2                                       # ip: the two network namespaces and their veth pair of the two-machines test and bench/dds (a minbase Debian has none)
  libcivetweb-dev libjs-chart.js                 # the web console, sbs --http (optional: -Dweb): HTTP + WebSocket server, the page's charts
  chromium chromium-driver python3-selenium      # the web console's tests in headless Chromium (suite web; skipped without them)
)
case ${1-} in
  --demo) packages=("${demo_packages[@]}") ;;
  "") packages=("${demo_packages[@]}" "${test_packages[@]}") ;;
  *) echo "setup-debian.sh: unknown argument '$1' (--demo, or none for everything)" >&2; exit 2 ;;
esac
missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  echo "setup: installing ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi
# The watch group: its members may run chimtop and read-only queries on every
# subsystem (the status and SVAR segments are theirs to read; docs/permissions.md).
# A build configured with another -Dwatch_group needs that group instead.
getent group chimera >/dev/null || groupadd --system chimera
