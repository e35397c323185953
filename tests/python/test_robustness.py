"""Never in the way of real time (issue #18.6): the GIL is released while a call waits for the
table lock, and a Python process killed -9 in the middle of a read or a write leaves the table
consistent (the same dead-holder recovery and rollback as for C++ peers, tests/svar)."""

import os
import random
import signal
import threading
import time

import numpy as np
import pytest

import chimera
from conftest import run_python

BIG = ["BIG1", "BIG2", "BIG3"]  # 3 MiB per set: a copy takes long enough to be caught inside the lock

READ_LOOP = """
import sys, chimera
r = chimera.attach(sys.argv[1], lock_timeout=5).reader(["BIG1", "BIG2", "BIG3"])
print("ready", flush=True)
while True:
    r.read()
"""


def stop_inside_the_lock(child, table):
    """SIGSTOP the child until it is stopped holding the table lock (a read then times out)."""
    probe = table.reader(["MODE"])
    for _ in range(200):
        os.kill(child.pid, signal.SIGSTOP)
        os.waitpid(child.pid, os.WUNTRACED)  # stopped now, wherever it was
        try:
            probe.read()
        except chimera.LockTimeout:
            return
        os.kill(child.pid, signal.SIGCONT)
        time.sleep(0.001)
    pytest.fail("the reading child was never caught holding the table lock")


def test_a_call_waiting_for_the_lock_releases_the_gil(subsystem):
    table = chimera.attach(subsystem.name, lock_timeout=0.02)
    # Made before the lock is held: making a reader takes the lock once.
    waiting = chimera.attach(subsystem.name, lock_timeout=3).reader(["J1"])
    child = run_python(READ_LOOP, subsystem.name)
    try:
        assert child.stdout.readline().strip() == "ready"
        stop_inside_the_lock(child, table)
        with pytest.raises(chimera.LockTimeout, match=r"^/chimera.%s.svar: read: the table lock was not obtained in time "
                                                      r"\(nothing transferred\)$" % subsystem.name):
            table.read("MODE")
        result = {}
        thread = threading.Thread(target=lambda: result.setdefault("J1", waiting.read()["J1"].copy()))
        thread.start()
        # While that thread waits for the lock, this one keeps running Python code.
        spins, until = 0, time.monotonic() + 0.3
        while time.monotonic() < until:
            spins += 1
        assert thread.is_alive() and not result, "the read did not wait for the held lock"
        assert spins > 1000, "Python code did not run while a read waited for the lock (the GIL was held)"
        # The waiting reader's local table is that thread's: another thread is refused, not let race.
        with pytest.raises(chimera.SvarError, match="a Reader or Writer is one thread's at a time"):
            waiting.read()
        os.kill(child.pid, signal.SIGCONT)
        thread.join(10)
        assert result["J1"].shape == (6,)
    finally:
        child.kill()
        child.wait()


def child_loop(name, write, ready_fd):
    """In a forked child: read or write BIG1..3 as one set forever (the k-th set all bytes k)."""
    table = chimera.attach(name, lock_timeout=5)
    if write:
        w = table.writer(BIG)
        arrays = list(w.arrays.values())
        k = 0
        while True:
            k = (k + 1) % 256
            for a in arrays:
                a.fill(k)
            w.write()
            if ready_fd is not None:
                os.write(ready_fd, b"r")
                ready_fd = None
    r = table.reader(BIG)
    r.read()
    os.write(ready_fd, b"r")
    while True:
        r.read()


def test_processes_killed_mid_transfer_leave_the_table_consistent(subsystem):
    table = chimera.attach(subsystem.name, lock_timeout=5)
    before = table.stats()
    reader = table.reader(BIG)
    rng = random.Random(18)
    for round in range(50):
        write = round % 2 == 0
        rfd, wfd = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child never returns into pytest
            try:
                os.close(rfd)
                child_loop(subsystem.name, write, wfd)
            finally:
                os._exit(1)
        os.close(wfd)
        assert os.read(rfd, 1) == b"r"
        os.close(rfd)
        time.sleep(rng.uniform(0, 0.02))
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        views = reader.read()  # recovers the lock from the dead child, rolling back its half-written set
        first = views["BIG1"].reshape(-1)[0]
        for name in BIG:
            assert (views[name] == first).all(), "round %d: %s is not the whole set %d" % (round, name, first)
    after = table.stats()
    # The kills did land inside the lock, of readers and of writers.
    assert after["recoveries"] > before["recoveries"]
    assert after["rollbacks"] > before["rollbacks"]
    assert after["forced"] == before["forced"]
    table.write("MODE", 3)  # and the table works on
    assert table.read("MODE").tolist() == [3]
