#!/usr/bin/env python3
"""Tables 1, 2 and 3 of the thesis (§6.6.1) regenerated on this machine, printed
beside the thesis's numbers with the ratio (thesis time / today's time).

    bench/thesis_tables.py [--quick] [BUILD_DIR]        (default: build)

Runs, one after the other in one session (the numbers of one run belong together):
  - build/bench/modules/bench_modules --benchmark_filter=^table1/  (Table 1: the
    modules of Figure 6.10 as examples/fig6_10_teleop runs them, built by the
    runtime's own TaskCore: puma_pidg (the simulated PUMA 560), grav_comp,
    qrdiff, and jtball reading trackball_sim on a pseudo-terminal through the
    SIO driver; their in-var and out-var transfers apart and one whole task cycle)
  - build/bench/svar/bench_svar, the locking, raw copy and transfer benchmarks
    (Tables 2 and 3: float[6], float[32], float[256], one to six variables)
Medians of 5 repetitions of CPU time. Prints Markdown (the machine, the build,
the load before and after, the date, then the tables) for docs/thesis-results.md.
--quick: 3 short repetitions (seconds, not minutes), for the smoke test
(bench/test_thesis_tables.py): its numbers are not for the doc. Speed is never
asserted: this is a measurement, not a test.
"""
import argparse
import json
import os
import platform
import subprocess
import sys
import time

# Table 1, the thesis's rows (µs): module -> processor -> (N in-var, t in-vars,
# N out-var, t out-vars, total CPU time of task, percent transfer time). jtball
# used the MC68030 board's own serial port, so it has no MC68020 row.
THESIS_TABLE1 = {
    "puma_pidg": {"MC68020": (3, 92, 2, 74, 1100, 15.0), "MC68030": (3, 67, 2, 54, 840, 14.0)},
    "grav_comp": {"MC68020": (1, 60, 1, 60, 1632, 7.4), "MC68030": (1, 51, 1, 52, 1315, 7.8)},
    "diff": {"MC68020": (1, 60, 1, 60, 296, 40.0), "MC68030": (1, 51, 1, 52, 240, 43.0)},
    "jtball": {"MC68030": (0, 12, 1, 48, 250, 24.0)},
}
# Table 2 (µs).
THESIS_LOCK = 5 + 2           # obtaining (TAS) + releasing the table lock
THESIS_SINGLE_OVERHEAD = 34   # total overhead for a single variable read/write
THESIS_PER_VAR_OVERHEAD = 5   # additional overhead per variable, multi-variable copy
THESIS_RAW = {6: 9, 32: 31, 256: 237}
# Table 3 (µs): single-variable time, multi-variable time, savings %.
THESIS_TABLE3 = {
    (1, 6): (43, 48, -12), (1, 32): (65, 72, -11), (1, 256): (264, 273, -3),
    (2, 6): (86, 64, 26), (2, 32): (130, 100, 23), (2, 256): (528, 505, 4),
    (6, 6): (258, 120, 53), (6, 32): (390, 250, 36), (6, 256): (1584, 1480, 9),
}
REPS = {False: ["--benchmark_repetitions=5", "--benchmark_min_time=0.2"],
        True: ["--benchmark_repetitions=3", "--benchmark_min_time=0.005"]}
JSON = ["--benchmark_report_aggregates_only=true", "--benchmark_format=json"]


def run_bench(cmd):
    run = subprocess.run(cmd, capture_output=True, text=True)
    if run.returncode != 0:
        sys.exit(f"thesis_tables: {' '.join(cmd)} failed (exit {run.returncode}):\n{run.stderr}")
    out = run.stdout
    medians = {}
    for b in json.loads(out)["benchmarks"]:
        if b.get("aggregate_name") == "median":
            scale = {"ns": 1.0, "us": 1e3, "ms": 1e6}[b.get("time_unit", "ns")]
            medians[b["run_name"]] = (b["cpu_time"] * scale, b)
    return medians


def ns(medians, name):
    return medians[name][0]


def machine():
    model = "?"
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} CPUs, Linux {platform.release()}"


def load():
    return " / ".join(f"{x:.2f}" for x in os.getloadavg())


def fmt(x):
    return f"{x:.1f}" if abs(x) < 100 else f"{x:.0f}"


def ratio(thesis_us, today_ns):
    return f"{thesis_us * 1000 / today_ns:,.0f}×" if today_ns > 0 else "–"


def table1(m):
    print("### Table 1: SVAR transfers of the Figure 6.10 modules\n")
    print("Thesis: MC68020 and MC68030 boards, the table on a remote VMEbus memory board. Today: the "
          "modules of examples/fig6_10_teleop with their .rmod files (`diff` is `qrdiff`; `jtball` reads "
          "`trackball_sim` on a pseudo-terminal through the SIO driver, the trackball idle at 50 packets/s), "
          "the table in POSIX shared memory. *in-vars*, *out-vars*: one multi-variable transfer with its "
          "table lock. *task*: in-vars copy + cycle + out-vars copy, as one release minus the wake-up. "
          "Each thesis row beside today's one measurement; ratio: thesis time / today's.\n")
    print("| module | thesis processor | N in | N out | in-vars: thesis µs / today ns / ratio "
          "| out-vars: thesis µs / today ns / ratio | task: thesis µs / today ns / ratio "
          "| transfer % of task: thesis / today |")
    print("|---|---|---|---|---|---|---|---|")
    for mod, rows in THESIS_TABLE1.items():
        base = f"table1/{mod}"
        i, o, t = ns(m, base + "/in"), ns(m, base + "/out"), ns(m, base + "/task")
        counters = m[base + "/in"][1]
        got_in, got_out = int(counters.get("n_in", -1)), int(counters.get("n_out", -1))
        for cpu, (n_in, t_in, n_out, t_out, t_task, pct) in rows.items():
            n_in_s = f"{got_in}" + ("" if got_in == n_in else f" (thesis {n_in})")
            n_out_s = f"{got_out}" + ("" if got_out == n_out else f" (thesis {n_out})")
            print(f"| {mod} | {cpu} | {n_in_s} | {n_out_s} | {t_in} / {fmt(i)} / {ratio(t_in, i)} "
                  f"| {t_out} / {fmt(o)} / {ratio(t_out, o)} | {t_task} / {fmt(t)} / {ratio(t_task, t)} "
                  f"| {pct:.1f} / {100 * (i + o) / t:.1f} |")
    print()


def table2(s):
    def t(name, nelem, count=1):
        return ns(s, f"{name}/nelem:{nelem}/count:{count}")
    lock = ns(s, "BM_TableLockUnlock")
    single_overhead = t("BM_SvarRead", 6) - t("BM_Memcpy", 6)
    per_var = (t("BM_SvarCopyFrom", 6, 6) - t("BM_SvarCopyFrom", 6, 1)) / 5 - t("BM_Memcpy", 6)
    print("### Table 2: locking overhead and raw transfer\n")
    print("| operation | thesis µs | today ns | ratio |")
    print("|---|---|---|---|")
    print(f"| table lock: obtain (TAS) + release (`ipc::lock`/`ipc::unlock`) | {THESIS_LOCK} | {fmt(lock)} | {ratio(THESIS_LOCK, lock)} |")
    print("| locking / releasing the CPU (interrupts off) | 8 + 8 | – | none: a user-space lock on Linux does not mask interrupts |")
    print(f"| total overhead, single-variable read (svarRead 1×float[6] − its memcpy) | {THESIS_SINGLE_OVERHEAD} | {fmt(single_overhead)} | {ratio(THESIS_SINGLE_OVERHEAD, single_overhead)} |")
    print(f"| additional overhead per variable, multi-variable copy ((copy_from 6×float[6] − 1×float[6]) / 5 − memcpy) | {THESIS_PER_VAR_OVERHEAD} | {fmt(per_var)} | {ratio(THESIS_PER_VAR_OVERHEAD, per_var) if per_var > 0 else '–'} |")
    print("| remote semaphores / message passing / SMP (with a context switch) | 200+ / 300+ / 300+ | – | not measured here (bench/results/xmail.md has message passing) |")
    for nelem, us in THESIS_RAW.items():
        raw = t("BM_Memcpy", nelem)
        print(f"| raw data transfer, {nelem} floats (memcpy) | {us} | {fmt(raw)} | {ratio(us, raw)} |")
    print()


def table3(s):
    def t(name, nelem, count):
        return ns(s, f"{name}/nelem:{nelem}/count:{count}")
    print("### Table 3: single-variable vs multi-variable transfers\n")
    print("Thesis: one time per transfer (svarRead()/svarWrite() vs svarCopyFromShm()/svarCopyToShm()). "
          "Today: reads (`LocalTable::read` ×n vs `copy_from_global`) and writes (`LocalTable::write` ×n vs "
          "`copy_to_global`, which also saves the undo record) apart. Ratio: thesis single / today's single read.\n")
    print("| transfer | thesis single µs | thesis multi µs | thesis saving | read ×n ns | copy_from ns | saving | "
          "write ×n ns | copy_to ns | saving | ratio |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for (count, nelem), (single, multi, saving) in THESIS_TABLE3.items():
        r, cf = t("BM_SvarRead", nelem, count), t("BM_SvarCopyFrom", nelem, count)
        w, ct = t("BM_SvarWrite", nelem, count), t("BM_SvarCopyTo", nelem, count)
        print(f"| {count} × float[{nelem}] | {single} | {multi} | {saving} % | {fmt(r)} | {fmt(cf)} | "
              f"{100 * (1 - cf / r):.0f} % | {fmt(w)} | {fmt(ct)} | {100 * (1 - ct / w):.0f} % | {ratio(single, r)} |")
    print()


def build_type(build):
    """The build's buildtype and C++ compiler, from meson's introspection files."""
    info = os.path.join(build, "meson-info")
    try:
        with open(os.path.join(info, "intro-buildoptions.json")) as f:
            buildtype = {o["name"]: o["value"] for o in json.load(f)}.get("buildtype", "?")
        with open(os.path.join(info, "intro-targets.json")) as f:
            cxx = next(src["compiler"] for t in json.load(f) for src in t.get("target_sources", [])
                       if src.get("language") == "cpp")
        version = subprocess.run(cxx + ["--version"], capture_output=True, text=True).stdout.splitlines()[0]
        return f"{buildtype}, {version}"
    except (OSError, KeyError, ValueError, StopIteration, IndexError):
        return "?"


def main():
    ap = argparse.ArgumentParser(description="Regenerate the thesis's Tables 1, 2 and 3 on this machine.")
    ap.add_argument("--quick", action="store_true", help="short runs for the smoke test; numbers not for the doc")
    ap.add_argument("build", nargs="?", default="build", help="the meson build folder (default: build)")
    args = ap.parse_args()
    build = args.build
    modules = os.path.join(build, "bench/modules/bench_modules")
    svar = os.path.join(build, "bench/svar/bench_svar")
    for exe in (modules, svar):
        if not os.access(exe, os.X_OK):
            sys.exit(f"thesis_tables: {exe} is not built (ninja -C {build} {os.path.relpath(exe, build)})")
    reps = REPS[args.quick] + JSON
    start = (time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), load())
    m = run_bench([modules, "--benchmark_filter=^table1/"] + reps)
    s = run_bench([svar, "--benchmark_filter=^BM_(TableLockUnlock|Memcpy|SvarRead|SvarWrite|SvarCopyFrom|SvarCopyTo)"]
                  + reps)
    how = "3 short repetitions (--quick: not for the doc)" if args.quick else "5 repetitions"
    print(f"Machine: {machine()}. Build: {build_type(build)}. Run {start[0]}; load average (1/5/15 min) "
          f"{start[1]} at the start, {load()} at the end. Medians of {how} of CPU time "
          f"(`bench/thesis_tables.py{' --quick' if args.quick else ''} {build}`).\n")
    table1(m)
    table2(s)
    table3(s)


if __name__ == "__main__":
    main()
