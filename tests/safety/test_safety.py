"""Fault injection on the Figure 3.7 arm (issue #29 item 9), one injection at a
time, each for a few seconds. Every test asserts: joint speed and torque within
the limits puma_safe.rmod declares, the tasks' missed releases within the bound
of a clean run of the same length, nothing of the subsystem left in /dev/shm or
/tmp once it finished, and an error or log line naming the cause.

Left out (see the report of the change): the DDS link cut and return and the
foreign DDS publisher; kill -9 of the robot side is kill -9 of the master (in
Figure 3.7 the robot interface is a task of the master's process)."""

import os
import pwd
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

import chimera
from safety_harness import STALL_S, TASKS, TLIMIT, TOKEN, VLIMIT, Arm, leftovers, measure

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "web"))
import webharness  # noqa: E402  (its WebSocket client)

SECONDS = 3.0


def miss_bound(clean):
    """Misses an injected run of SECONDS may have: those of the clean run,
    doubled, plus 5 for a shared 2-core machine's scheduling noise."""
    return 2 * clean.misses + 5


def check_limits(meas, clean):
    """The arm's safety assertions of one measured run (a list of failures)."""
    failures = []
    if meas.rate < 200:
        failures.append("sampled at %.0f Hz (< 200)" % meas.rate)
    if np.any(meas.peak_speed > VLIMIT):
        failures.append("joint speed %s over VLIMIT %s" % (meas.peak_speed, VLIMIT))
    if np.any(meas.peak_torque > TLIMIT + 1e-9):
        failures.append("joint torque %s over TLIMIT %s" % (meas.peak_torque, TLIMIT))
    if meas.misses > miss_bound(clean):
        failures.append("%d misses, bound %d (clean run: %d)" % (meas.misses, miss_bound(clean), clean.misses))
    return failures


def measure_safely(arm, inject=None, seconds=SECONDS):
    """A clean run, then the injected run of the same length, right after it
    (so the misses' bound reflects the machine's load of the moment), and
    their checks; run once more only when the stall detector says the
    machine stopped this process too (and says so)."""
    clean, meas, failures = measure_pair(arm, inject, seconds)
    if failures and max(clean.stall, meas.stall) > STALL_S:
        print("stall detector: a top-priority process woke %.1f ms late, the machine stopped the arm too: running again (%s)"
              % (max(clean.stall, meas.stall) * 1e3, "; ".join(failures)))
        clean, meas, failures = measure_pair(arm, inject, seconds)
    print("clean:   ", clean)
    print("injected:", meas)
    assert not failures, "; ".join(failures)
    return meas


def measure_pair(arm, inject, seconds):
    clean = measure(arm, seconds)
    meas = measure(arm, seconds, inject)
    return clean, meas, check_limits(clean, clean) + check_limits(meas, clean)


@pytest.fixture(scope="module")
def arm():
    a = Arm("m")
    yield a
    assert a.stop() == 0, a.log_text()
    assert leftovers(a.name) == []


def still_on(arm):
    with arm.master() as m:
        return [t for t in TASKS if Arm.row(m, t)["state"] != "ON"]


def page(arm, control=False):
    s = webharness.Socket(arm.http_port)
    assert s.authenticate(TOKEN)["ok"]
    if control:
        assert s.request("control")["ok"]
    return s


# ------------------------------------------------------------------ injections on the running arm

def test_watcher_command_flood(arm):
    refusals = []

    def flood(arm, done):
        s = page(arm)
        while not done.is_set():
            for cmd in ("off jpid", "kill puma_safe", "set jpid KP 1e6", "setvar T_REF 500 500 500 500 500 500"):
                refusals.append(s.request(cmd))

    measure_safely(arm, flood)
    print("%d watcher commands refused; first: %s" % (len(refusals), refusals[0]["error"]))
    assert len(refusals) > 20 and all(not r["ok"] for r in refusals)
    assert all("read-only: this page is watching" in r["error"] for r in refusals)
    assert still_on(arm) == []


def test_scope_abuse(arm):
    errors = []

    def abuse(arm, done):
        s = page(arm, control=True)
        try:
            while not done.is_set():
                for cmd in ("scope start Q_MEZ --rate 100000 --rtpu robot", "scope start Q_MEZ --rate 100000 --rtpu ctrl",
                            "scope start Q_MEZ Q_REF T_REF --capacity 1073741824"):
                    r = s.request(cmd)
                    if r["ok"]:
                        s.request("scope stop")
                    else:
                        errors.append(r["error"])
        finally:
            s.request("scope stop")
            s.request("release")

    measure_safely(arm, abuse)
    print("%d scope starts refused; e.g. %s" % (len(errors), sorted(set(errors))[:3]))
    assert errors, "no abusive scope was refused"
    assert all("rate" in e or "capacity" in e or "admission" in e or "deadline" in e for e in errors), set(errors)
    assert still_on(arm) == []


def test_pre_authentication_flood(arm):
    counts = {"connects": 0}

    def flood(arm, done):
        idle = []
        while not done.is_set():
            try:
                c = socket.socket()
                c.bind(("127.0.0.2", 0))
                c.settimeout(1)
                c.connect(("127.0.0.1", arm.tcp_port))
                counts["connects"] += 1
                if counts["connects"] % 10 == 0:
                    idle.append(c)  # held open, silent, until the flood ends
                else:
                    c.close()
            except OSError:
                time.sleep(0.001)  # refused or timed out: the server's limits, not this test's business
        for c in idle:
            c.close()

    measure_safely(arm, flood)
    print("%d connections from 127.0.0.2 in %.0f s" % (counts["connects"], SECONDS))
    assert counts["connects"] > 50
    # The master still serves TCP, and a command before the token is refused, naming why.
    with pytest.raises(chimera.MasterError, match="token") as wrong:
        chimera.Master(tcp=("127.0.0.1", arm.tcp_port), token="not-the-token").status()
    # A wrong token makes this address wait before its next is judged (issue #29.3).
    time.sleep(wrong.value.reply.get("data", {}).get("retry_after_ms", 0) / 1000)
    with chimera.Master(tcp=("127.0.0.1", arm.tcp_port), token=TOKEN) as m:
        assert len(m.status()) >= len(TASKS)
    assert still_on(arm) == []


PEER_CHILD = """
import sys, chimera
m = chimera.Master(sys.argv[1], socket_path=sys.argv[2], token=sys.argv[3])
p = chimera.Peer("safetypeer", produces=["PEER_OUT"], consumes=["Q_MEZ"], master=m)
p.start()
m.close()  # the master's control slot is free again; the peer task stays, bound to this pid
print("started", flush=True)
for cycle in p.run(hz=200):
    p.write(PEER_OUT=p.read()["Q_MEZ"])
"""


def test_python_peer_killed_9(arm):
    child = subprocess.Popen([sys.executable, "-c", PEER_CHILD, arm.name, arm.socket, TOKEN], stdout=subprocess.PIPE,
                             text=True, env=arm.env)
    try:
        assert child.stdout.readline().strip() == "started"

        def kill_peer(arm, done):
            time.sleep(1.0)
            child.send_signal(signal.SIGKILL)
            child.wait(10)

        measure_safely(arm, kill_peer)
        with arm.master() as m:
            row = Arm.row(m, "safetypeer")  # the master checks its peers before every command
            print("peer task:", row["state"], row["error"])
            assert row["state"] == "ERROR" and "peer process %d is gone" % child.pid in row["error"]
            m.kill("safetypeer")
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert still_on(arm) == []


# ------------------------------------------------------------------ injections on an arm of their own

def measure_after_its_cause(arm, cause, label):
    """The arm's start logs a line naming the cause (regex CAUSE), then a
    measured run within the limits; the master stops cleanly either way."""
    try:
        print(label, arm.wait_log(cause).group(0))
        measure_safely(arm)
    finally:
        assert arm.stop() == 0, arm.log_text()


def test_master_killed_9_leaves_the_next_start_working():
    """In Figure 3.7 the robot interface is a task of the master's process:
    kill -9 of the master is kill -9 of the robot side too. What must hold:
    the next start of the same subsystem takes over what the dead one left,
    saying so, runs within the limits, and leaves nothing when it finishes."""
    first = Arm("k")
    try:
        measure_safely(first)
    except BaseException:
        first.stop()  # a failed check must not leave a master running (its tasks would load later tests)
        raise
    first.proc.send_signal(signal.SIGKILL)
    first.proc.wait(10)
    print("left by the killed master:", leftovers(first.name))
    first.log.close()
    second = Arm("k")  # same subsystem name
    measure_after_its_cause(second, r"chimera: segment \S+, .*: left by a process that died: removed.*", "next start:")
    shutil.rmtree(first.dir, ignore_errors=True)  # the killed master's socket folder
    assert leftovers(first.name) == []


def squat_as_nobody(arm):
    """As `nobody`, creates the arm's table segment name, writable by all."""
    nobody = pwd.getpwnam("nobody")
    pid = os.fork()
    if pid == 0:
        try:
            os.setgid(nobody.pw_gid)
            os.setuid(nobody.pw_uid)
            os.umask(0)
            fd = os.open("/dev/shm/chimera.%s.svar" % arm.name, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
            os.write(fd, b"squatter" * 512)
            os._exit(0)
        except BaseException:
            os._exit(1)
    _, status = os.waitpid(pid, 0)
    assert status == 0, "nobody could not plant the squat"


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root (to become nobody)")
def test_squatting_user():
    a = Arm("s", before_start=squat_as_nobody)
    measure_after_its_cause(a, r"chimera: segment \S+, nobody's .*squatted.*: removed.*", "squat:")
    assert leftovers(a.name) == []
