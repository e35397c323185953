#!/usr/bin/python3
"""Draws the thesis's Figures 6.4, 6.5 (the effect of data flow on error, measured
on real threads) and 6.7, 6.8, 6.9 (aperiodic server size and schedulable bound,
from the analysis) as PNG into docs/img/, from build/bench/muf/thesis_curves.

    docs/thesis_plots.py [BUILD_DIR] [--servers-only]

Needs python3-matplotlib from Debian (scripts/setup-debian.sh installs it; the
shebang names Debian's python3 so that its matplotlib is the one found) and,
for 6.4/6.5, SCHED_FIFO (root): about four minutes of two real-time threads on
one CPU (20 periods x 4 priority orders x 3 runs of 1 s, the median kept). The numbers behind Figure 6.5 are printed as a table for docs/thesis-results.md.
"""
import csv
import io
import math
import os
import subprocess
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

SERVERS = ["RDS", "RSS", "MDS", "MSS"]
HERE = os.path.dirname(os.path.abspath(__file__))
IMG = os.path.join(HERE, "img")


def curves(build, *args):
    exe = os.path.join(build, "bench/muf/thesis_curves")
    if not os.access(exe, os.X_OK):
        sys.exit(f"thesis_plots: {exe} is not built (ninja -C {build} bench/muf/thesis_curves)")
    r = subprocess.run([exe, *args], capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"thesis_plots: {' '.join([exe, *args])} failed: {r.stderr.strip()}")
    return r.stdout


def save(fig, name):
    os.makedirs(IMG, exist_ok=True)
    fig.tight_layout()
    fig.savefig(os.path.join(IMG, name), dpi=90)
    plt.close(fig)
    print(f"wrote docs/img/{name}")


def server_figures(build):
    rows = list(csv.DictReader(io.StringIO(curves(build, "servers"))))
    u = [float(r["u"]) for r in rows]

    def series(server, key):
        # Against U_p, an RM server has no admissible size once U_p passes its
        # bound (the size comes out negative): those points are not drawn.
        xs, ys = [], []
        for x, r in zip(u, rows):
            if key != "bound_vs_us" and float(r[f"{server}_size"]) < 0:
                continue
            xs.append(x)
            ys.append(float(r[f"{server}_{key}"]))
        return xs, ys

    for name, key, xlabel, ylabel, title in [
        ("fig6_7_server_size.png", "size", "periodic utilisation U_p", "maximum server size U_s",
         "Figure 6.7: server size vs periodic utilisation"),
        ("fig6_8_bound_vs_up.png", "bound_vs_up", "periodic utilisation U_p", "worst-case schedulable bound U_p + U_s",
         "Figure 6.8: schedulable bound vs periodic utilisation"),
        ("fig6_9_bound_vs_us.png", "bound_vs_us", "server size U_s", "worst-case schedulable bound",
         "Figure 6.9: schedulable bound vs server size"),
    ]:
        fig, ax = plt.subplots(figsize=(6, 4))
        for s in SERVERS:
            xs, ys = series(s, key)
            ax.plot(xs, ys, label=s)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.set_title(title, fontsize=10)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
        ax.legend()
        save(fig, name)


def dataflow_figures(build):
    # Figure 6.4: T_a = T_b = 50 ms, y against the input, each priority order.
    out = curves(build, "dataflow", "50", "50", "1.3", "--trace")
    traces = {k: ([], []) for k in ("a_first", "b_first", "static_a", "static_b")}
    errors = {}
    for line in out.splitlines():
        f = line.split(",")
        if f[0] == "trace":
            traces[f[1]][0].append(float(f[2]))
            traces[f[1]][1].append(float(f[3]))
        else:
            errors[f[0]] = float(f[3])
    fig, axes = plt.subplots(2, 1, figsize=(6, 5), sharex=True)
    t = [i / 1000 for i in range(0, 1000)]
    for ax, case, label in [(axes[0], "a_first", "(a) tau_a higher (data flow)"),
                            (axes[1], "b_first", "(b) tau_b higher")]:
        ax.plot(t, [50 * math.sin(10 * x) for x in t], label="input K sin(alpha t)", color="gray")
        xs, ys = traces[case]
        ax.step(xs, ys, where="post", label=f"output y, mean error {errors[case]:.1f}")
        ax.set_xlim(0, 1)
        ax.set_title(label, fontsize=10)
        ax.legend(fontsize=8, loc="lower left")
        ax.grid(alpha=0.3)
    axes[1].set_xlabel("t (s)")
    fig.suptitle("Figure 6.4: the effect of data flow (T_a = T_b = 50 ms, C = 5 ms), real threads", fontsize=10)
    save(fig, "fig6_4_dataflow.png")

    # Figure 6.5: mean error as a function of T_b, T_a = 50 ms.
    tbs = list(range(10, 201, 10))
    cases = {"a_first": "MUF, data-flow user priority (tau_a above on ties)",
             "b_first": "MUF, user priority reversed (tau_b above on ties)",
             "static_a": "fixed order, tau_a above (thesis epsilon_a)",
             "static_b": "fixed order, tau_b above (thesis epsilon_b)"}
    # The median of three runs per point: a run that another engineer's
    # real-time thread disturbed on the shared CPU is an outlier, not the curve.
    err = {k: [] for k in cases}
    for tb in tbs:
        runs = {k: [] for k in cases}
        for _ in range(3):
            for line in curves(build, "dataflow", "50", str(tb), "1.0").splitlines():
                f = line.split(",")
                runs[f[0]].append(float(f[3]))
        for k in cases:
            err[k].append(sorted(runs[k])[1])
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for (k, label), style in zip(cases.items(), ["o-", "s--", "^-", "v--"]):
        ax.plot(tbs, err[k], style, label=label, markersize=4)
    ax.set_xlabel("T_b (ms), T_a = 50 ms")
    ax.set_ylabel("mean error |y - K sin(alpha t)|")
    ax.set_title("Figure 6.5: error due to data flow vs period, real threads", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    save(fig, "fig6_5_error_vs_period.png")
    print("\n| T_b (ms) | " + " | ".join(str(x) for x in tbs) + " |")
    print("|---|" + "---|" * len(tbs))
    for k in cases:
        print(f"| {k} | " + " | ".join(f"{x:.1f}" for x in err[k]) + " |")


def main():
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    build = args[0] if args else "build"
    server_figures(build)
    if "--servers-only" not in sys.argv:
        dataflow_figures(build)


if __name__ == "__main__":
    main()
