#!/usr/bin/env python3
"""Python against the JSON socket, same run (issue #18.7): a consistent read of 6 x float[6], a
write, a status snapshot and a command round trip, each done through the bindings and through
the master's JSON socket by a minimal hand-written client (one line out, one line in).

    PYTHONPATH=build/python SBS_EXE=build/tools/sbs/sbs CHIMERA_MODULE_PATH=build/tests/tools \\
        /usr/bin/python3 bench/python/bench_python.py [--rounds 9] [--seconds 0.2]

Each round times a batch of each operation in turn (interleaved, so both sides see the same
load); the figure is the median over rounds of the batch's time per operation. Results and
how to read them: bench/results/python.md.
"""

import argparse
import json
import os
import socket
import statistics
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "..", "tests", "python"))

import chimera  # noqa: E402
from conftest import start_subsystem  # noqa: E402  (the tests' subsystem: py.svar, ramp)

JOINTS = ["J1", "J2", "J3", "J4", "J5", "J6"]


class RawClient:
    """The JSON socket as a hand-written client speaks it: a line out, a line in."""

    def __init__(self, path):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.connect(path)
        self.file = self.sock.makefile("rb")
        assert json.loads(self.file.readline())["ok"]

    def __call__(self, line):
        self.sock.sendall(line.encode() + b"\n")
        reply = json.loads(self.file.readline())
        assert reply["ok"], reply
        return reply

    def close(self):
        self.sock.sendall(b"quit\n")
        self.file.close()
        self.sock.close()


def per_op(fn, seconds):
    """Seconds per call of FN over a batch of about SECONDS."""
    n, start = 0, time.perf_counter()
    deadline = start + seconds
    while True:
        for _ in range(16):
            fn()
        n += 16
        now = time.perf_counter()
        if now >= deadline:
            return (now - start) / n


def run(rounds, seconds, cpu):
    folder = tempfile.mkdtemp(prefix="bench-python-")
    sub = start_subsystem("benchpy%d" % os.getpid(), folder, "spawn ramp; spawn follow; on ramp")
    os.sched_setaffinity(0, {cpu})  # after the master started: it keeps every CPU
    try:
        table = chimera.attach(sub.name, lock_timeout=1.0)
        status = chimera.StatusReader(sub.name)
        reader = table.reader(JOINTS)
        writer = table.writer(["J1"])
        writer.arrays["J1"][:] = np.linspace(0, 1, 6)
        j1 = np.linspace(0, 1, 6)
        setvar = "setvar J1 " + " ".join("%g" % x for x in j1)
        display = "display all " + " ".join(JOINTS)
        ops = {
            "read 6 x float[6]": {
                "python Reader.read()": reader.read,
                "python Table.read(names)": lambda: table.read(JOINTS),
            },
            "write float[6]": {
                "python Writer.write()": writer.write,
                "python Table.write(name, values)": lambda: table.write("J1", j1),
            },
            "status snapshot (2 tasks)": {
                "python StatusReader.snapshot()": status.snapshot,
                "python StatusReader.take()": status.take,
            },
        }
        socket_ops = {"read 6 x float[6]": display, "write float[6]": setvar, "status snapshot (2 tasks)": "status"}
        times = {(group, name): [] for group, fns in ops.items() for name in fns}
        times.update({(group, "JSON socket `%s`" % line.split(" ")[0]): [] for group, line in socket_ops.items()})
        times[("command round trip", "python Master.freq('ramp')")] = []
        times[("command round trip", "JSON socket `freq ramp`")] = []
        for _ in range(rounds):
            raw = RawClient(sub.socket)
            for group, fns in ops.items():
                for name, fn in fns.items():
                    times[(group, name)].append(per_op(fn, seconds))
                line = socket_ops[group]
                times[(group, "JSON socket `%s`" % line.split(" ")[0])].append(per_op(lambda: raw(line), seconds))
            times[("command round trip", "JSON socket `freq ramp`")].append(per_op(lambda: raw("freq ramp"), seconds))
            raw.close()
            with sub.master() as m:
                times[("command round trip", "python Master.freq('ramp')")].append(per_op(lambda: m.freq("ramp"), seconds))
        return {k: statistics.median(v) for k, v in times.items()}
    finally:
        sub.stop()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=9)
    ap.add_argument("--seconds", type=float, default=0.2, help="length of one batch")
    ap.add_argument("--cpu", type=int, default=1, help="CPU this client runs on (the tasks run on cpu0)")
    args = ap.parse_args()
    load_before = os.getloadavg()
    medians = run(args.rounds, args.seconds, args.cpu)
    load_after = os.getloadavg()
    print("load average before %.2f %.2f %.2f, after %.2f %.2f %.2f; client on CPU %d; %d rounds of %.2f s batches"
          % (load_before + load_after + (args.cpu, args.rounds, args.seconds)))
    print("| operation | how | median per op [us] | ratio to the JSON socket |")
    print("|---|---|---|---|")
    groups = []
    for group, _ in medians:
        if group not in groups:
            groups.append(group)
    for group in groups:
        socket_time = next(t for (g, n), t in medians.items() if g == group and n.startswith("JSON socket"))
        for (g, name), t in medians.items():
            if g == group:
                print("| %s | %s | %.2f | %.3f |" % (group, name, t * 1e6, t / socket_time))


if __name__ == "__main__":
    main()
