#!/usr/bin/env python3
"""Step response of one joint of the Figure 3.7 subsystem (the README's demo), from Python.

Runs the demo's PID joint controller (jpid) and simulated PUMA 560 (puma_torque) with the
reference coming from a triple buffer a Python script writes (jstep.rmod: the teleop module,
rate limit lifted) and its velocity from the differentiator (qrdiff); lets the arm settle,
steps one joint's reference, records Q_REF and Q_MEZ, prints rise time (10-90 %), overshoot
and settling time (2 % band), and saves a plot.

    PYTHONPATH=build/python SBS_EXE=build/tools/sbs/sbs \\
        /usr/bin/python3 examples/python/step_response.py [--joint 2] [--step 0.2] [--out step.png]

The real-time tasks run in the master process on their RTPUs; this script only writes the
set-point, and Q_REF and Q_MEZ are sampled on the real-time side at jpid's rate (500 Hz) by a
`sample` task of the master (chimera.Sampling): every cycle one consistent set, none lost.
"""

import argparse
import os
import time

import numpy as np

import chimera

HERE = os.path.dirname(os.path.abspath(__file__))
SBS = os.path.join(HERE, "..", "fig3_7_pid", "fig3_7.sbs")


def step_metrics(t, y, y0, y1):
    """Rise time 10-90 %, overshoot in % of the step, settling time into the 2 % band (s, from the step)."""
    span = y1 - y0
    frac = (y - y0) / span
    rise = t[np.argmax(frac >= 0.9)] - t[np.argmax(frac >= 0.1)] if (frac >= 0.9).any() else float("nan")
    overshoot = max(0.0, float(frac.max()) - 1.0) * 100.0
    outside = np.nonzero(np.abs(frac - 1.0) > 0.02)[0]
    settling = float("nan") if len(outside) and outside[-1] == len(t) - 1 else \
        (t[outside[-1] + 1] if len(outside) else t[0])
    return rise, overshoot, settling


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--joint", type=int, default=2, help="joint number, 1..6 (default 2, the shoulder)")
    ap.add_argument("--step", type=float, default=0.2, help="step size in rad")
    ap.add_argument("--settle", type=float, default=1.0, help="seconds to let the arm settle first")
    ap.add_argument("--seconds", type=float, default=2.0, help="seconds recorded after the step")
    ap.add_argument("--out", default="step_response.png")
    args = ap.parse_args()
    j = args.joint - 1

    script = ";".join([
        "spawn puma_torque robot",  # first: it produces the in-consts NDOF and DH
        "spawn %s ctrl" % os.path.join(HERE, "jstep.rmod"),
        "spawn qrdiff ctrl", "spawn jpid ctrl",
        "reconfig on puma_torque, on jpid, on qrdiff, on jstep",
    ])
    with chimera.serve(SBS, script) as sub, sub.master() as master:
        table = chimera.attach(sub.name)
        feed = chimera.Tbuf.attach(chimera.segment_name("tbuf", "step"))
        time.sleep(args.settle)
        start_ref = table.read("Q_REF")
        target = start_ref.copy()
        target[j] += args.step
        step_at = 0.2
        chunks = []
        with chimera.Sampling(["Q_REF", "Q_MEZ"], master=master) as sampling:  # at the producers' rate
            begin = time.monotonic()
            while time.monotonic() - begin < step_at:
                chunks.append(sampling.read())
                time.sleep(0.02)
            feed.write(target.astype(np.float64))
            stepped_ns = time.monotonic_ns()  # CLOCK_MONOTONIC, as the samples' time-stamps
            while time.monotonic() - begin < step_at + args.seconds:
                chunks.append(sampling.read())
                time.sleep(0.02)
            chunks.append(sampling.read())
        # Let the feed go before the subsystem finishes: the teleop module, killed
        # then, is its last user and removes it (an attacher only detaches).
        feed.detach()
        rec = chimera.Recording.join(chunks)
        status = {s.rmod: s for s in chimera.status(sub.name)}

    t = (rec.time_ns - stepped_ns) / 1e9 + step_at
    q_ref, q_mez = rec["Q_REF"], rec["Q_MEZ"]
    after = t >= step_at
    y0 = float(q_mez[after][0, j])
    rise, overshoot, settling = step_metrics(t[after] - step_at, q_mez[after][:, j], y0, float(target[j]))
    print("joint %d step %+.3f rad (from %.4f to %.4f), %d samples at %g Hz, %d lost"
          % (args.joint, args.step, start_ref[j], target[j], len(t), rec.rate, rec.lost))
    print("rise time (10-90 %%): %.1f ms" % (rise * 1e3))
    print("overshoot:           %.1f %%" % overshoot)
    print("settling time (2 %%): %.1f ms" % (settling * 1e3))
    print("final error:         %.4f rad" % (target[j] - q_mez[-1, j]))
    for name in ("jstep", "jpid", "puma_torque"):
        s = status[name]
        print("%-12s %s  cycles %d  missed %d  mezF %.1f Hz" % (name, s.state, s.cycle, s.miss, s.mez_f))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=110)
    ax.plot((t - step_at) * 1e3, q_ref[:, j], label="Q_REF (reference)", drawstyle="steps-post")
    ax.plot((t - step_at) * 1e3, q_mez[:, j], label="Q_MEZ (measured)")
    ax.axhspan(target[j] - 0.02 * args.step, target[j] + 0.02 * args.step, color="0.85", label="2 % band")
    ax.set_xlabel("time from the step [ms]")
    ax.set_ylabel("joint %d [rad]" % args.joint)
    ax.set_title("PUMA 560 joint %d, PID (jpid, 500 Hz): rise %.0f ms, overshoot %.1f %%, settling %.0f ms"
                 % (args.joint, rise * 1e3, overshoot, settling * 1e3), fontsize=9)
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(args.out)
    print("plot: %s" % args.out)


if __name__ == "__main__":
    main()
