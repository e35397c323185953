#!/usr/bin/env python3
"""check_skips.py on small synthetic testlog.json files: skips by design pass,
any other skip fails naming the test, the build and the reason.

    test_check_skips.py SOURCE_ROOT
"""
import json
import os
import subprocess
import sys
import tempfile

checker = os.path.join(sys.argv[1] if len(sys.argv) > 1 else os.path.dirname(__file__) + "/..",
                       "tests", "check_skips.py")
failures = []


def gtest(*tests):
    """GoogleTest output: each test (name, None) passes, (name, reason) skips."""
    lines = ["[==========] Running tests."]
    for name, reason in tests:
        lines.append(f"[ RUN      ] {name}")
        if reason is None:
            lines.append(f"[       OK ] {name} (1 ms)")
        else:
            lines += ["../tests/x/test_x.cpp:12: Skipped", reason, f"[  SKIPPED ] {name} (0 ms)"]
    skipped = [n for n, r in tests if r is not None]
    if skipped:
        lines.append(f"[  SKIPPED ] {len(skipped)} tests, listed below:")
        lines += [f"[  SKIPPED ] {n}" for n in skipped]
    return "\n".join(lines) + "\n"


def record(name, stdout, result="OK", command=("tests/prog",)):
    return {"name": name, "result": result, "stdout": stdout, "stderr": "", "command": list(command)}


def run(case, records, expect_ok, expect_in=()):
    with tempfile.TemporaryDirectory() as tmp:
        build = os.path.join(tmp, "build-" + case)
        os.makedirs(os.path.join(build, "meson-logs"))
        if records is not None:
            with open(os.path.join(build, "meson-logs", "testlog.json"), "w") as f:
                f.writelines(json.dumps(r) + "\n" for r in records)
        p = subprocess.run([sys.executable, checker, build], capture_output=True, text=True)
    if (p.returncode == 0) != expect_ok:
        failures.append(f"{case}: exit {p.returncode}, expected {'0' if expect_ok else 'non-zero'}:\n{p.stdout}{p.stderr}")
    for text in expect_in:
        if text not in p.stdout:
            failures.append(f"{case}: the output does not say {text!r}:\n{p.stdout}")


run("allowed", [
    record("chimera:sai / canrobot_module", gtest(("CanRobotGuest.Holds", "runs in the rtguest suite (CHIMERA_VCAN not set)"))),
    record("chimera:spp / spp", gtest(("SppPlacement.InTheRtGuestTheKernelIsPreemptRtAndTheExecutiveRealTime",
                                       "not in the PREEMPT_RT guest"))),
    record("chimera:ipc / ipc", gtest(("IpcLock.Across", "crosses processes (a forked child): ThreadSanitizer sees one side only"))),
    record("chimera:rtguest / rtguest", gtest(("CanRobotHost.WithoutAfCanInitFailsNamingTheRmodAndTheReason",
                                               "this kernel has AF_CAN (the guest tests cover the module)"))),
    record("chimera:python / python_svar", ".....\n5 passed in 0.1s\n", command=("python3", "-m", "pytest", "-rs")),
], expect_ok=True, expect_in=["skipped here, run in the rtguest suite", "4 skips by design, 0 not allowed"])

run("privilege", [
    record("chimera:ipc / ipc", gtest(("Squat.RootsCreateReplacesNobodysFake", "needs root (setresuid to nobody)"))),
    record("chimera:python / python_master",
           "..s\nSKIPPED [1] ../tests/python/test_master.py:165: needs root (setresuid to nobody)\n2 passed, 1 skipped in 0.3s\n",
           command=("python3", "-m", "pytest", "-rs")),
    record("chimera:install / system_install", "test_system_install: needs root and unshare\n", result="SKIP"),
], expect_ok=False, expect_in=[
    "chimera:ipc / ipc Squat.RootsCreateReplacesNobodysFake skipped in build-privilege: needs root (setresuid to nobody)",
    "chimera:python / python_master ../tests/python/test_master.py:165 skipped in build-privilege: needs root",
    "chimera:install / system_install skipped in build-privilege: meson SKIP (exit 77): test_system_install: needs root",
    "3 not allowed"])

run("gtest-in-ok-program", [
    record("chimera:muf / muf_rt", gtest(("MufStatic.Runs", None), ("MufFifo.Preempts", "SCHED_FIFO refused on this machine"),
                                        ("MufStatic.Ends", None))),
], expect_ok=False, expect_in=["chimera:muf / muf_rt MufFifo.Preempts skipped in build-gtest-in-ok-program: "
                               "SCHED_FIFO refused on this machine"])

# A guest-only test skipped inside the guest did not run anywhere.
run("guest-test-skipped-in-guest", [
    record("chimera:rtguest / rtguest", gtest(("CanRobotGuest.Holds", "runs in the rtguest suite (CHIMERA_VCAN not set)"))),
], expect_ok=False, expect_in=["CanRobotGuest.Holds skipped in build-guest-test-skipped-in-guest"])

# The deadline tests are allowed their partition's reasons only.
run("deadline-privilege", [
    record("chimera:muf / muf_rt", gtest(("MufDeadline.RefusesAReservationOnACpuThatIsNotAPartition", "no real-time privilege"),
                                        ("MufDeadline.AdmitsAFeasible", "no cgroup v2 hierarchy with the cpuset controller (x)"))),
], expect_ok=False, expect_in=["1 skips by design, 1 not allowed"])

# A sanitizer's precondition is by design; tracefs missing is not.
run("printed-preconditions", [
    record("chimera:muf / muf_rt", "[ RUN      ] MufDynamic.One\nsanitizer build: the dynamic sets' 0.2-1.2 ms jobs do not fit "
           "its release path\n../tests/muf/test_rt.cpp:1320: Skipped\npreconditions (printed above)\n[  SKIPPED ] MufDynamic.One (0 ms)\n"
           "[ RUN      ] MufDynamic.Two\nno raw_syscalls tracepoint: tracefs not mounted\n../tests/muf/test_rt.cpp:1348: Skipped\n"
           "preconditions (printed above)\n[  SKIPPED ] MufDynamic.Two (0 ms)\n"),
], expect_ok=False, expect_in=["MufDynamic.Two skipped in build-printed-preconditions: preconditions (printed above) "
                               "(printed before: no raw_syscalls tracepoint: tracefs not mounted)", "1 skips by design"])

run("pytest-without-rs", [
    record("chimera:web / web_browser", "\n1 skipped in 0.0s\n", command=("python3", "-m", "pytest", "-q")),
], expect_ok=False, expect_in=["1 pytest test(s) skipped"])

run("no-log", None, expect_ok=False, expect_in=["meson test did not run"])

for f in failures:
    print("FAIL", f)
print(f"test_check_skips: {len(failures)} failures")
sys.exit(1 if failures else 0)
