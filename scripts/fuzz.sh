#!/usr/bin/env bash
# A bounded fuzz run (docs/fuzzing.md): builds the libFuzzer harnesses of fuzz/
# with clang, AddressSanitizer and UndefinedBehaviorSanitizer in their own build
# folder, then runs each for FUZZ_SECONDS (default 60), FUZZ_JOBS at a time
# (default: the number of CPUs), starting from its seed corpus.
#
#   scripts/fuzz.sh [HARNESS...]      default: every fuzz/fuzz_*.cpp
#
# Fails when a harness finds a crash, a sanitizer report, a broken invariant,
# a leak, a timeout or an out-of-memory; the input that did it is kept in
# build-fuzz/crashes/HARNESS/ (replay it: build-fuzz/fuzz/fuzz_HARNESS FILE).
# New inputs the fuzzer finds go to build-fuzz/corpus/HARNESS/, not into the
# repository: add the ones worth keeping to fuzz/corpus/HARNESS/ by hand.
set -euo pipefail
cd "$(dirname "$0")/.."
seconds=${FUZZ_SECONDS:-60}
jobs=${FUZZ_JOBS:-$(nproc)}
# FUZZ_RUNS=N: N inputs per harness from FUZZ_SEED (default 1) instead of a time
# — the same exploration on every run of the same code, so a test command that
# passed here passes in CI (a timed run explores as far as the machine's speed
# lets it, and a finding there is a coin toss). FUZZ_SECONDS then caps each
# harness (a slow machine stops early, without failing).
runs=${FUZZ_RUNS:-}
seed=${FUZZ_SEED:-1}
if [[ -n $runs ]]; then
  limit="-runs=$runs -seed=$seed -max_total_time=$((seconds * 5))"
  budget="$runs inputs each from seed $seed (at most $((seconds * 5)) s)"
else
  limit="-max_total_time=$seconds"
  budget="${seconds} s each"
fi
build=${FUZZ_BUILD:-build-fuzz}

if (($# > 0)); then
  harnesses=("$@")
else
  harnesses=()
  for f in fuzz/fuzz_*.cpp; do harnesses+=("$(basename "$f" .cpp | sed 's/^fuzz_//')"); done
fi

start=$(date +%s)
# Only what the harnesses need: no tests, benchmarks or optional drivers.
# Sanitizer findings abort (no recovery), so libFuzzer keeps the input.
if [ ! -d "$build" ]; then
  CC=clang CXX=clang++ CXXFLAGS="-fno-sanitize-recover=all -Wno-unknown-warning-option" meson setup "$build" \
    -Dfuzzing=enabled -Db_sanitize=address,undefined -Db_lundef=false -Dbuildtype=debugoptimized \
    -Dtests=false -Dbenchmarks=disabled -Dlttng=disabled -Dgpiod=disabled -Dsocketcan=disabled \
    -Dkdl=disabled -Drt_guest_tests=disabled -Dman=disabled
fi
ninja -C "$build" "${harnesses[@]/#/fuzz/fuzz_}"
echo "fuzz: build $(($(date +%s) - start)) s; ${#harnesses[@]} harnesses, ${budget}, ${jobs} at a time"

# One harness: fuzz from a scratch copy of the corpus (the seeds stay as they
# are), then print one summary line. Exit status 0 when nothing was found.
run_one() {
  local name=$1 out="$build/fuzz-logs/$1.log"
  local corpus="$build/corpus/$name" crashes="$build/crashes/$name"
  mkdir -p "$corpus" "$crashes" "$build/fuzz-logs"
  local t0 status=0
  t0=$(date +%s)
  # shellcheck disable=SC2086  # $limit is a list of options
  "$build/fuzz/fuzz_$name" "$corpus" "fuzz/corpus/$name" $limit \
    -artifact_prefix="$crashes/" -max_len=8192 -timeout=10 -rss_limit_mb=2048 -print_final_stats=1 \
    >"$out" 2>&1 || status=$?
  local execs rate
  execs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$out" | tail -1)
  rate=$(sed -n 's/^stat::average_exec_per_sec: *//p' "$out" | tail -1)
  if ((status == 0)); then
    printf 'fuzz: %-11s ok     %4d s  %9s execs  %6s/s  corpus %s\n' "$name" $(($(date +%s) - t0)) \
      "${execs:-?}" "${rate:-?}" "$(find "$corpus" -type f | wc -l)"
  else
    printf 'fuzz: %-11s FAILED %4d s  (exit %d) input kept in %s; log %s\n' "$name" $(($(date +%s) - t0)) \
      "$status" "$crashes" "$out"
    grep -m 5 -E 'ERROR|invariant broken|runtime error|terminate' "$out" | sed 's/^/      /' || true
  fi
  return "$status"
}
export -f run_one
export build limit

# Each harness a job; xargs' status is nonzero when any of them failed.
if printf '%s\n' "${harnesses[@]}" | xargs -P "$jobs" -I{} bash -c 'run_one "$@"' _ {}; then
  echo "fuzz: no crash; all done in $(($(date +%s) - start)) s"
else
  echo "fuzz: FAILED, crash inputs in $build/crashes/ (all done in $(($(date +%s) - start)) s)" >&2
  exit 1
fi
