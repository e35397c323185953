#!/usr/bin/env python3
"""Smoke test of the one command that regenerates the thesis's Tables 1, 2, 3
(bench/thesis_tables.py --quick BUILD_DIR): it runs, and its output has every
row of the thesis's tables with a measured number in each of today's columns,
and Table 1's modules move as many variables as Figure 6.10's do (the thesis's
N in-var, N out-var). Timing is never asserted (a shared, noisy machine).

    bench/test_thesis_tables.py SCRIPT BUILD_DIR
"""
import re
import subprocess
import sys

# The thesis's rows (§6.6.1), written out here rather than taken from the script.
TABLE1 = [("puma_pidg", "MC68020", 3, 2), ("puma_pidg", "MC68030", 3, 2),
          ("grav_comp", "MC68020", 1, 1), ("grav_comp", "MC68030", 1, 1),
          ("diff", "MC68020", 1, 1), ("diff", "MC68030", 1, 1),
          ("jtball", "MC68030", 0, 1)]
TABLE2 = ["table lock: obtain (TAS) + release", "total overhead, single-variable read",
          "additional overhead per variable", "raw data transfer, 6 floats",
          "raw data transfer, 32 floats", "raw data transfer, 256 floats"]
TABLE3 = [f"{count} × float[{nelem}]" for count in (1, 2, 6) for nelem in (6, 32, 256)]
NUMBER = r"-?[\d,]*\.?\d+"


def fail(msg, out):
    sys.exit(f"test_thesis_tables: {msg}\n--- output ---\n{out}")


def cells(line):
    return [c.strip() for c in line.strip().strip("|").split("|")]


def section(out, title):
    start = out.find(title)
    if start < 0:
        fail(f"no section '{title}'", out)
    end = out.find("\n### ", start + 1)
    return out[start:end if end > 0 else len(out)]


def main():
    script, build = sys.argv[1], sys.argv[2]
    run = subprocess.run([sys.executable, script, "--quick", build], capture_output=True, text=True)
    out = run.stdout
    if run.returncode != 0:
        fail(f"exit {run.returncode}: {run.stderr}", out)
    if not re.search(r"^Machine: .+ load average \(1/5/15 min\) [\d.]+ / [\d.]+ / [\d.]+ at the start", out, re.M):
        fail("no machine and load line", out)

    t1 = [cells(l) for l in section(out, "### Table 1").splitlines() if l.startswith("| ") and "---" not in l][1:]
    got1 = {(c[0], c[1]): c for c in t1}
    if len(t1) != len(TABLE1):
        fail(f"Table 1 has {len(t1)} rows, the thesis {len(TABLE1)}", out)
    for mod, cpu, n_in, n_out in TABLE1:
        c = got1.get((mod, cpu))
        if c is None:
            fail(f"Table 1 has no row {mod} {cpu}", out)
        if c[2] != str(n_in) or c[3] != str(n_out):
            fail(f"Table 1 {mod}: {c[2]} in-vars and {c[3]} out-vars, Figure 6.10's has {n_in} and {n_out}", out)
        for col in c[4:7]:  # thesis µs / today ns / ratio
            if not re.fullmatch(rf"{NUMBER} / {NUMBER} / {NUMBER}×", col):
                fail(f"Table 1 {mod} {cpu}: '{col}' is not thesis / today / ratio", out)

    t2 = section(out, "### Table 2")
    for op in TABLE2:
        line = next((l for l in t2.splitlines() if l.startswith(f"| {op}")), None)
        if line is None or not re.fullmatch(NUMBER, cells(line)[2]):
            fail(f"Table 2 has no measured row '{op}'", out)

    t3 = section(out, "### Table 3")
    for transfer in TABLE3:
        line = next((l for l in t3.splitlines() if l.startswith(f"| {transfer} |")), None)
        if line is None:
            fail(f"Table 3 has no row '{transfer}'", out)
        c = cells(line)
        for k in (4, 5, 7, 8):  # read ×n, copy_from, write ×n, copy_to
            if not re.fullmatch(NUMBER, c[k]):
                fail(f"Table 3 {transfer}: '{c[k]}' is not a time", out)
    print(out)


if __name__ == "__main__":
    main()
