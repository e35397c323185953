#!/usr/bin/env python3
"""Lists every skip of a `meson test` run and fails on any not skipped by design.

    check_skips.py BUILD_DIR [BUILD_DIR...]

Reads BUILD_DIR/meson-logs/testlog.json (one JSON object per test) and finds
  - meson-level skips: result SKIP (exit 77), the reason in the test's output;
  - GoogleTest skips: "[  SKIPPED ] Suite.Name (N ms)", the reason the lines
    after "file:line: Skipped" (and what the test printed before them);
  - pytest skips: "SKIPPED [N] file:line: reason" (pytest -rs), or only a
    count "N skipped" where pytest ran without -rs.
scripts/test.sh runs it after each stage's `meson test`: there every optional
feature is built and the machine is CI's, so a skip for missing privilege,
SCHED_FIFO, tracefs or a library would hide a test that did not run. Only the
skips of ALLOWED pass, listed as "skipped here, run in ...". Exit 1 when any
other skip (or no log) was found, naming the test, the build and the reason.
"""
import json
import os
import re
import sys

GUEST_SUITE = "chimera:rtguest / rtguest"  # its output holds the guest's test programs'

# The skips by design: each test runs elsewhere. Fields:
#   test     regex the GoogleTest name must fully match (None: any test)
#   message  regex the skip message must fully match
#   printed  regex searched in what the test printed before its skip (optional)
#   where    "host": allowed outside the rtguest suite only (inside the guest
#            the test must run); "guest": inside it only; "any": both
#   runs_in  where the test does run, printed with the skip
ALLOWED = [
    # tests/support/guest_env.hpp CHIMERA_REQUIRE_GUEST_ENV: the guest programs
    # (iod, dio, canrobot) need gpio-sim or vcan0, which guest-init.sh sets up.
    dict(test=None, message=r"runs in the rtguest suite \(\w+ not set\)", where="host",
         runs_in="the rtguest suite (PREEMPT_RT guest under qemu, suite stage)"),
    # tests/spp/test_rt.cpp: test_spp is one of spp_guest_tests.
    dict(test=r"SppPlacement\.InTheRtGuestTheKernelIsPreemptRtAndTheExecutiveRealTime",
         message=r"not in the PREEMPT_RT guest", where="host",
         runs_in="the rtguest suite (PREEMPT_RT guest under qemu, suite stage)"),
    # tests/muf/test_rt.cpp: an exclusive cpuset partition for SCHED_DEADLINE
    # (tests/support/cpu_partition.hpp's reasons); tests/rtguest/meson.build
    # runs test_muf_rt@MufDeadline.* in the guest, where one is made.
    dict(test=r"MufDeadline\..*",
         message=r"(one CPU only: a partition would take.*|no cgroup v2 hierarchy with the cpuset controller.*"
                 r"|cannot make .*|CPU \d+ did not become a partition.*|cannot move this process into .*)",
         where="host", runs_in="the rtguest suite (PREEMPT_RT guest under qemu, suite stage)"),
    # tests/sai/canrobot/test_canrobot_guest.cpp: the error of a kernel without
    # AF_CAN. The guest's kernel has it; a host's may too, and then the
    # CanRobotGuest tests in the guest cover the module.
    dict(test=r"CanRobotHost\.WithoutAfCanInitFailsNamingTheRmodAndTheReason",
         message=r"this kernel has AF_CAN \(the guest tests cover the module\)", where="any",
         runs_in="the suite stage on a host without AF_CAN (the module: CanRobotGuest.* in the rtguest suite)"),
    # tests/support/sanitizer.hpp CHIMERA_NOT_UNDER_TSAN: TSan's shadow memory
    # is per process, so a test crossing processes proves nothing under it.
    dict(test=None, message=r"crosses processes \(.*\): ThreadSanitizer sees one side only", where="host",
         runs_in="the suite and asan stages"),
    # tests/muf/test_rt.cpp dynamic_counter_preconditions(): the dynamic sets'
    # jobs do not fit a sanitizer build's release path.
    dict(test=r"MufDynamic\..*", message=r"preconditions \(printed above\)",
         printed=r"sanitizer build: the dynamic sets' .* do not fit its release path", where="host",
         runs_in="the suite stage (the plain build)"),
]

GTEST_RUN = re.compile(r"\[ RUN      \] (\S+)$")
GTEST_SKIPPED = re.compile(r"\[  SKIPPED \] (\S+) \(\d+ ms\)$")
GTEST_SKIP_SITE = re.compile(r"\S+:\d+: Skipped$")
PYTEST_SKIPPED = re.compile(r"SKIPPED \[(\d+)\] (\S+:\d+): (.*)$")
PYTEST_COUNT = re.compile(r"\b(\d+) skipped\b")


class Skip:
    def __init__(self, meson_test, test, message, printed=""):
        self.meson_test, self.test, self.message, self.printed = meson_test, test, message, printed

    def name(self):
        return self.meson_test + (" " + self.test if self.test else "")


def gtest_skips(meson_test, out):
    skips, current, block = [], None, []
    for line in out:
        run = GTEST_RUN.match(line)
        if run:
            current, block = run.group(1), []
            continue
        skipped = GTEST_SKIPPED.match(line)
        if skipped and skipped.group(1) == current:
            sites = [i for i, l in enumerate(block) if GTEST_SKIP_SITE.match(l)]
            at = sites[-1] if sites else -1
            message = " ".join(l.strip() for l in block[at + 1:] if l.strip())
            printed = "\n".join(block[:at]) if sites else ""
            skips.append(Skip(meson_test, current, message, printed))
            current = None
        elif current:
            block.append(line)
    return skips


def pytest_skips(meson_test, out):
    skips = [Skip(meson_test, m.group(2), m.group(3)) for m in map(PYTEST_SKIPPED.match, out) if m]
    if not skips:
        counts = [PYTEST_COUNT.search(l) for l in out if re.search(r"\b(passed|failed|skipped)\b.* in [\d.]+s", l)]
        n = sum(int(c.group(1)) for c in counts if c)
        if n:
            skips.append(Skip(meson_test, None, f"{n} pytest test(s) skipped; reasons not shown (run pytest with -rs)"))
    return skips


def skips_of(record):
    name = record.get("name", "?")
    out = ((record.get("stdout") or "") + "\n" + (record.get("stderr") or "")).replace("\r", "").splitlines()
    if record.get("result") == "SKIP":
        reason = " / ".join(l.strip() for l in out if l.strip())[-400:] or "(no output)"
        return [Skip(name, None, "meson SKIP (exit 77): " + reason)]
    command = " ".join(record.get("command") or [])
    if "pytest" in command:
        return pytest_skips(name, out)
    return gtest_skips(name, out)


def allowed_by(skip):
    in_guest = skip.meson_test == GUEST_SUITE
    for entry in ALLOWED:
        if entry["where"] == "host" and in_guest or entry["where"] == "guest" and not in_guest:
            continue
        if entry["test"] is not None and not (skip.test and re.fullmatch(entry["test"], skip.test)):
            continue
        if not re.fullmatch(entry["message"], skip.message):
            continue
        if "printed" in entry and not re.search(entry["printed"], skip.printed):
            continue
        return entry
    return None


def check(build_dir):
    build = os.path.basename(os.path.normpath(build_dir))
    log = os.path.join(build_dir, "meson-logs", "testlog.json")
    try:
        with open(log) as f:
            records = [json.loads(line) for line in f if line.strip()]
    except OSError as e:
        print(f"check_skips: {build}: no test log ({e.strerror}: {log}): meson test did not run")
        return False
    by_design, failures = [], []
    for record in records:
        for skip in skips_of(record):
            entry = allowed_by(skip)
            (by_design if entry else failures).append((skip, entry))
    for skip, entry in by_design:
        why = re.search(entry["printed"], skip.printed).group(0) if "printed" in entry else skip.message
        print(f"check_skips: {build}: skipped here, run in {entry['runs_in']}: {skip.name()}: {why}")
    for skip, _ in failures:
        printed = [l.strip() for l in skip.printed.splitlines() if l.strip()][-3:]
        also = f" (printed before: {' / '.join(printed)})" if printed else ""
        print(f"check_skips: FAILED: {skip.name()} skipped in {build}: {skip.message}{also}")
    print(f"check_skips: {build}: {len(records)} tests, {len(by_design)} skips by design, "
          f"{len(failures)} not allowed" + (" (under scripts/test.sh every test must run: docs/testing.md)"
                                            if failures else ""))
    return not failures


def main(argv):
    if len(argv) < 2:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    ok = True
    for build_dir in argv[1:]:
        ok = check(build_dir) and ok
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
