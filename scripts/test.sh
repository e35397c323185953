#!/usr/bin/env bash
# The whole test suite, as named stages run in order, each timed (CI: .ci/run).
#   scripts/test.sh                        every stage
#   scripts/test.sh --stage asan [--stage tsan]   only those (setup is not implied)
#   scripts/test.sh --list                 the stages
#   scripts/test.sh [--stage …] -- ARGS    ARGS to each stage's `meson test` (e.g. --suite svar)
# What each stage does and its usual time: docs/testing.md.
set -euo pipefail
cd "$(dirname "$0")/.."

# Configures DIR with meson's OPTIONS (again, keeping them, when it exists).
configure() {
  local dir=$1; shift
  if [ -d "$dir" ]; then meson setup --reconfigure "$dir" "$@" >/dev/null; else meson setup "$dir" "$@"; fi
}

# The sanitizer builds leave out what they do not test: benchmarks and the qemu
# guest suite (it boots its own kernel; its programs are not the host's).
# They compile at -O1 with line tables only (-g1): -O2 -g under ASan+UBSan took
# 4x the plain build's time (41 min of CI's 90 for build-asan; a CLI11 tool's
# main.cpp 392 s against 77 s), and -O1 is what the sanitizers' authors advise.
sanitizer_options=(-Db_lundef=false -Dbenchmarks=disabled -Drt_guest_tests=disabled -Doptimization=1)
sanitizer_cpp_args=(-g1)

# Runs `meson test -C BUILD ARGS...`, then tests/check_skips.py on that run's
# log: every optional feature is built here, so a skip other than its listed
# ones by design (the test runs elsewhere) hides a test that did not run, and
# fails the stage too. Its stale log is removed first: a run that never started
# must not be checked as if it had.
meson_test_then_check_skips() {
  local build=$1 rc=0; shift
  rm -f "$build/meson-logs/testlog.json"
  meson test -C "$build" "$@" || rc=$?
  python3 tests/check_skips.py "$build" || rc=1
  return "$rc"
}

stage_setup() { scripts/setup-debian.sh; }
# Every optional feature enabled: one whose library or program is missing
# fails configure with meson's message naming it, instead of leaving its tests
# out. Fuzzing is the fuzz stage's own clang build (scripts/fuzz.sh).
stage_build() {
  configure build -Dauto_features=enabled -Dfuzzing=disabled
  ninja -C build
}
stage_suite() {
  # The network tests and the browser's driver connect to "localhost"; where it
  # does not resolve (a debootstrap root has no /etc/hosts) they would fail late
  # and, the browser's, unclearly.
  getent hosts localhost >/dev/null ||
    { echo "test.sh: the host name localhost does not resolve: add '127.0.0.1 localhost' to /etc/hosts" >&2; return 1; }
  meson_test_then_check_skips build --print-errorlogs --num-processes 2 "${meson_test_args[@]}"
}

# AddressSanitizer + UndefinedBehaviorSanitizer over the host suite; any report
# ends the program (-fno-sanitize-recover=all), so the test fails. Not the
# install suite: it builds a user's program, uninstrumented, against the
# installed library, which cannot load an instrumented one (the sanitizer's
# runtime must come first); it runs in the suite stage. Nor the docs suite: it
# builds sbs.hpp's example program the same way.
stage_asan() {
  configure build-asan "${sanitizer_options[@]}" -Db_sanitize=address,undefined \
    -Dcpp_args="${sanitizer_cpp_args[*]} -fno-sanitize-recover=all" -Dcpp_link_args=-fno-sanitize-recover=all
  timed asan-build ninja -C build-asan
  timed asan-suite meson_test_then_check_skips build-asan --no-rebuild --print-errorlogs --num-processes 2 --no-suite install --no-suite docs \
    "${meson_test_args[@]}"
}

# ThreadSanitizer over the in-process lock-free parts (table lock, TBUF, mail
# rings, MSG): `meson test` builds only these suites' programs. Their tests
# that cross processes skip themselves (CHIMERA_NOT_UNDER_TSAN, with what they
# cross); tests/tsan.supp holds the suppressions, each with its reason.
stage_tsan() {
  configure build-tsan "${sanitizer_options[@]}" -Db_sanitize=thread -Dcpp_args="${sanitizer_cpp_args[*]}"
  meson_test_then_check_skips build-tsan --print-errorlogs --num-processes 2 --suite ipc --suite svar --suite sampler --suite xmail "${meson_test_args[@]}"
}

# Bounded fuzzing in its own clang build (docs/fuzzing.md): a fixed number of
# inputs from a fixed seed, so the stage is a regression check that gives the
# same answer on every run of the same code; open-ended fuzzing is
# `FUZZ_SECONDS=N scripts/fuzz.sh`.
stage_fuzz() {
  local fresh=build-fuzz/corpus
  rm -rf "$fresh"  # from the committed seeds only, as on a fresh clone
  FUZZ_RUNS=${FUZZ_RUNS:-1000000} scripts/fuzz.sh
}

stages=(setup build suite asan tsan fuzz)

# Runs a command and logs how long it took and how it ended in $times_file, a
# file so that the steps a stage times inside its subshell (asan-build,
# asan-suite) are listed too.
timed() {
  local label=$1 start=$SECONDS rc errexit=${-//[^e]/}; shift
  echo "==> $label"
  # In a subshell of its own with set -e: its first failing command ends it.
  # (Run as a condition — `if`, `||` — bash would ignore set -e inside.)
  set +e
  (set -e; "$@")
  rc=$?
  [ -z "$errexit" ] || set -e
  printf '  %-11s %5d s  %s\n' "$label" $((SECONDS - start)) "$( ((rc == 0)) && echo ok || echo "FAILED (exit $rc)")" >>"$times_file"
  return "$rc"
}
print_times() {
  echo "== stage times (total $SECONDS s)"
  cat "$times_file"
  rm -f "$times_file"
}

selected=() meson_test_args=()
while (($#)); do
  case $1 in
    --stage) selected+=("${2:?--stage needs a name}"); shift 2 ;;
    --list) printf '%s\n' "${stages[@]}"; exit 0 ;;
    --) shift; meson_test_args=("$@"); break ;;
    *) meson_test_args+=("$1"); shift ;;  # as before stages: meson test's own options
  esac
done
for s in "${selected[@]}"; do
  [[ " ${stages[*]} " == *" $s "* ]] || { echo "test.sh: no stage '$s' (stages: ${stages[*]})" >&2; exit 2; }
done
((${#selected[@]})) || selected=("${stages[@]}")

times_file=$(mktemp)
trap print_times EXIT

# Every selected stage runs, whatever an earlier one did, so one failure hides
# no other; the script's status is non-zero when any failed.
failed=()
set +e
for s in "${stages[@]}"; do
  [[ " ${selected[*]} " == *" $s "* ]] || continue
  timed "$s" "stage_$s"
  (($? == 0)) || failed+=("$s")
done
set -e
if ((${#failed[@]})); then
  echo "test.sh: failed stages: ${failed[*]}" >&2
  exit 1
fi
