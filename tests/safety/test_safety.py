"""Fault injection on the Figure 3.7 arm (issue #29 item 9), one injection at a
time, each for a few seconds. Every test asserts: joint speed and torque within
the limits puma_safe.rmod declares, the tasks' missed releases within the bound
of a clean run of the same length, nothing of the subsystem left in /dev/shm or
/tmp once it finished, and an error or log line naming the cause.

The DDS injections (the link cut and returned, a foreign publisher) run the
arm split over the DDS bridge as examples/two_machines does (DdsArm), in two
network namespaces; they skip, saying why, without the bridge or root. kill -9
of the robot side is kill -9 of the master (in Figure 3.7 the robot interface
is a task of the master's process)."""

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
from safety_harness import (EXAMPLE, PERIOD, STALL_S, TASKS, TLIMIT, TOKEN, TORQUE_TOPIC, TRATE, VLIMIT, Arm,
                            DdsArm, NetnsPair, leftovers, measure)

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "web"))
import webharness  # noqa: E402  (its WebSocket client)

SECONDS = 3.0
# jpid.rmod's SLEW (N m/s): after a hold, T_REF moves from the held value at this rate.
SLEW = np.array([250, 500, 250, 50, 50, 50], dtype=float)


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


def measure_safely(arm, inject=None, seconds=SECONDS, extra=(), check=None):
    """A clean run, then the injected run of the same length, right after it
    (so the misses' bound reflects the machine's load of the moment), and
    their checks (and CHECK(clean, injected)'s, a list of failures; EXTRA:
    variables sampled beside Q^_MEZ and T_MEZ); run once more only when the
    stall detector says the machine stopped this process too (and says so)."""
    def measure_pair():
        clean = measure(arm, seconds, extra=extra)
        meas = measure(arm, seconds, inject, extra=extra)
        return clean, meas, check_limits(clean, clean) + check_limits(meas, clean) + (check(clean, meas) if check else [])

    clean, meas, failures = measure_pair()
    if failures and max(clean.stall, meas.stall) > STALL_S:
        print("stall detector: a top-priority process woke %.1f ms late, the machine stopped the arm too: running again (%s)"
              % (max(clean.stall, meas.stall) * 1e3, "; ".join(failures)))
        clean, meas, failures = measure_pair()
    print("clean:   ", clean)
    print("injected:", meas)
    assert not failures, "; ".join(failures)
    return meas


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
            # No task reads PEER_OUT: the observer's death must not hold the
            # robot (held, jpid wound T_REF up to its limit and the arm lunged
            # when let go).
            assert not m.command("show graph")["data"]["illegal_configuration"]
            m.kill("safetypeer")
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert still_on(arm) == []


READER_CHILD = """
import sys, chimera
m = chimera.Master(sys.argv[1], socket_path=sys.argv[2], token=sys.argv[3])
p = chimera.Peer("safetyreader", consumes=["PEER_OUT"], master=m)
p.start()
m.close()
print("started", flush=True)
for cycle in p.run(hz=20):
    p.read()
"""

ERROR_S = 2.0  # how long a task stays halted in ERROR


def tref_restart(clean, meas):
    """T_REF held exactly while illegal (for at least 90% of ERROR_S in
    samples); its largest step within twice the clean run's plus SLEW x one
    period (the restart's own step); its peak within 1.5 x the clean run's
    plus 2 N m (wound up, it went to its ULIMIT: 186.4 N m on joint 2, 21.9
    on joint 4, where the clean run needs 57 and 2)."""
    failures = []
    peak = 1.5 * clean.peak_tref + 2
    if np.any(meas.peak_tref > peak):
        failures.append("T_REF reached %s N m, bound %s (clean: %s)"
                        % (np.round(meas.peak_tref, 1), np.round(peak, 1), np.round(clean.peak_tref, 1)))
    if meas.tref_held < 0.9 * ERROR_S * meas.rate:
        failures.append("T_REF held for %d samples at most, expected >= %d" % (meas.tref_held, 0.9 * ERROR_S * meas.rate))
    bound = 2 * clean.peak_tref_step + SLEW * PERIOD
    if np.any(meas.peak_tref_step > bound):
        failures.append("T_REF jumped %s N m in one sample, bound %s (clean: %s)"
                        % (np.round(meas.peak_tref_step, 2), np.round(bound, 2), np.round(clean.peak_tref_step, 2)))
    return failures


def peer_child(arm, code, children):
    """A peer process running CODE, once it says it started (one at a time:
    the master's control slot is one)."""
    child = subprocess.Popen([sys.executable, "-c", code, arm.name, arm.socket, TOKEN], stdout=subprocess.PIPE,
                             text=True, env=arm.env)
    children.append(child)
    assert child.stdout.readline().strip() == "started"
    return child


def test_task_in_error_holds_then_restarts_without_a_jump(arm):
    """A task halted in ERROR (a Python peer killed -9 while an ON task, a
    second peer, reads its output) makes the configuration illegal (§3.10)
    for ERROR_S while the arm moves; killing that task clears it. The robot
    interface holds the arm meanwhile, and jtraj and jpid hold with it
    (STALE hold): T_REF stays exactly what it was and, once the flag
    clears, never jumps (tref_restart). Before, the trajectory ran on and
    jpid's integral wound up against the held arm: let go, it lunged (joint
    6 at -1.9 then +1.9 rad/s, T_REF at its 21.3 N m limit)."""
    children, seen = [], {}

    def error_for_a_while(arm, done):
        producer = seen["producer"] = peer_child(arm, PEER_CHILD, children)  # each run its own
        time.sleep(0.5)
        seen["log"] = len(arm.log_text())
        producer.send_signal(signal.SIGKILL)
        producer.wait(10)
        with arm.master() as m:  # the master finds the peer gone on its next command
            row = Arm.row(m, "safetypeer")
            seen["error"] = row["state"], row["error"]
            seen["illegal"] = m.command("show graph")["data"]["illegal_configuration"]
        time.sleep(ERROR_S)
        with arm.master() as m:
            m.kill("safetypeer")
            seen["legal_again"] = not m.command("show graph")["data"]["illegal_configuration"]
        cleared = time.monotonic()
        done.wait()
        seen["after"] = time.monotonic() - cleared

    try:
        peer_child(arm, READER_CHILD, children)
        measure_safely(arm, error_for_a_while, seconds=1.0 + ERROR_S + 2.5, extra=["T_REF"], check=tref_restart)
        print("peer task:", *seen["error"])
        assert seen["error"][0] == "ERROR" and "peer process %d is gone" % seen["producer"].pid in seen["error"][1]
        assert seen["illegal"] and seen["legal_again"] and seen["after"] >= 2.0, seen
        log = arm.log_text()[seen["log"]:]
        line = next((line for line in log.splitlines() if "safetypeer" in line and "gone" in line), None)
        assert line, log[-2000:]
        print(line)
    finally:
        remove_peers(arm, children, ("safetypeer", "safetyreader"))
    assert still_on(arm) == []


def remove_peers(arm, children, names):
    """Kills the peer processes and removes their tasks; none may be left."""
    for child in children:
        if child.poll() is None:
            child.kill()
            child.wait()
    with arm.master() as m:
        for name in names:
            if any(t["rmod"] == name for t in m.status()):
                m.kill(name)
        assert not set(names) & {t["rmod"] for t in m.status()}


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


# ------------------------------------------------------------------ injections on the arm over DDS

def within_trate(clean, meas):
    """The torque rate within TRATE. Asserted on the DDS runs only, as
    test_two_machines.sh does: robotsim applies its speed envelope after
    the rate limit (robotics/limits.hpp: a speed limit is never traded for a
    smooth torque), so where the envelope acts the applied torque changes
    faster, by design; the arm over DDS tracks well inside it."""
    return ["joint torque rate %s over TRATE %s (%s run)" % (np.round(m.peak_trate, 0), TRATE, which)
            for m, which in ((clean, "clean"), (meas, "injected")) if np.any(m.peak_trate > TRATE)]


@pytest.fixture(scope="module")
def dds_arm():
    if not os.environ.get("DDS_FOREIGN_WRITER"):
        pytest.skip("built without the DDS bridge (-Ddds: Cyclone DDS's cyclonedds-dev, cyclonedds-tools)")
    pair = NetnsPair()
    if pair.reason:
        pytest.skip(pair.reason)
    a = DdsArm(pair)
    yield a
    assert a.stop() == [0, 0], a.robot.log_text() + a.ctrl.log_text()
    for name in a.names:
        assert leftovers(name) == []
    assert pair.left() == []


CUT_S = 3.0  # longer than cyclone.xml's 2 s lease: the peers forget each other and must rediscover


def test_dds_link_cut_and_return(dds_arm):
    """The robot's veth down for CUT_S, then up: the robot's bridge says its
    torques are stale (illegal configuration: the arm holds), the
    controller's its measurements; both fresh again within 5 s (the bound of
    test_two_machines.sh); the limits hold from the cut until 2 s after."""
    arm = dds_arm
    seen = {}

    def cut(arm, done):
        time.sleep(0.5)
        seen["logs"] = len(arm.robot.log_text()), len(arm.ctrl.log_text())
        arm.pair.link(False)
        try:
            time.sleep(CUT_S)
            seen["during"] = arm.status()
        finally:
            arm.pair.link(True)
        seen["fresh_after"] = arm.wait_fresh(5)
        fresh_at = time.monotonic()
        done.wait()
        seen["window_after_fresh"] = time.monotonic() - fresh_at

    # 0.5 s before the cut, CUT_S, fresh data about 0.5 s later, then 2 s and a margin.
    measure_safely(arm, cut, seconds=CUT_S + 4.5, check=within_trate)
    robot_log = arm.robot.log_text()[seen["logs"][0]:]
    ctrl_log = arm.ctrl.log_text()[seen["logs"][1]:]
    robot, ctrl = seen["during"]
    print("during the cut: robot T_REF %s; controller Q_MEZ %s" % (robot, ctrl))
    print("fresh again %.2f s after the link returned, measured %.2f s after that"
          % (seen["fresh_after"] or -1, seen["window_after_fresh"]))
    assert robot.get("stale") == "yes" and ctrl.get("stale") == "yes"
    assert seen["fresh_after"] is not None, "no fresh data within 5 s of the link's return: %s" % (arm.status(),)
    assert seen["window_after_fresh"] >= 2.0
    stale = "T_REF from %s: stale (no value newer than 0.05 s; illegal)" % TORQUE_TOPIC
    assert stale in robot_log, robot_log[-2000:]
    print("robot:", next(line for line in robot_log.splitlines() if stale in line))
    assert "T_REF from %s: fresh values again" % TORQUE_TOPIC in robot_log, robot_log[-2000:]
    assert "Q_MEZ from rt/puma/joint_positions: stale (no value newer than 0.05 s; warn)" in ctrl_log, ctrl_log[-2000:]


# Each reason the robot's bridge refuses a foreign sample for, and the start
# of its warning (dds_link.cpp's describe_refusal).
REFUSALS = {
    "partial": "T_REF refused a sample: 2 of 6 joints named (JOINT_SUBSET refuse)",
    "unknown": "T_REF refused a sample: unknown joint 'joint7'",
    "length": "T_REF refused a sample: 100000 effort values for 6 names",
    "unnamed": "T_REF refused a sample: no joint names (UNNAMED refuse)",
    "reordered": "T_REF refused a sample: stamp ",
}


def test_dds_foreign_publisher(dds_arm):
    """A foreign participant on the robot's side of the link writes, on the
    torque topic, the controller's newest command with its joints reversed,
    a subset of them, 64 joints, 100000 efforts and no names, and the first
    command it read again with its old stamp (dds_foreign_writer.cpp): the
    reversed ones are the same command by name, every other one is refused
    whole (the replayed one as reordered: older than the newest taken),
    counted and told with its reason and topic; the limits hold and T_REF, the
    robot's torque command, never jumps (tref_steps)."""
    arm = dds_arm
    seen = {}
    before, _ = arm.status()

    def foreign(arm, done):
        # From the first attempt: a warning is told at most once every 5 s per reason.
        seen.setdefault("log", len(arm.robot.log_text()))
        writer = subprocess.run(
            ["ip", "netns", "exec", arm.pair.ns_a, os.environ["DDS_FOREIGN_WRITER"], str(arm.domain),
             os.path.abspath(os.path.join(EXAMPLE, "cyclone.xml")), TORQUE_TOPIC, str(SECONDS - 0.5)],
            capture_output=True, text=True, timeout=30, env=dict(os.environ, CHIMERA_DDS_INTERFACE=arm.pair.veth_a))
        seen["writer"] = writer.returncode, writer.stdout, writer.stderr

    def tref_steps(clean, meas):
        """A JointState taken by position would put joint 6's torque on
        joint 1 (and so on) for a cycle: T_REF would jump by tens of N m.
        By name, a reversed copy of a command a few ms old changes it by a
        few cycles' worth of the controller's own change: the bound is five
        times the clean run's largest step, plus 5 N m."""
        bound = 5 * clean.peak_tref_step + 5
        if np.any(meas.peak_tref_step > bound):
            return ["T_REF jumped %s N m in one sample, bound %s (clean: %s)"
                    % (np.round(meas.peak_tref_step, 1), np.round(bound, 1), np.round(clean.peak_tref_step, 1))]
        return within_trate(clean, meas)

    measure_safely(arm, foreign, extra=["T_REF"], check=tref_steps)
    code, out, err = seen["writer"]
    print("foreign writer:", out.strip(), err.strip()[-500:])
    assert code == 0, out + err
    sent = {k: int(v) for k, v in (w.split("=") for w in out.split()[1:])}
    assert sent["reversed"] > 0 and sent["replayed"] > 0 and sent["read"] > 0, sent
    after, ctrl = arm.status()
    counts = {k: after[k] - before[k]
              for k in ("rejected", "partial", "unknown", "length", "unnamed", "reordered", "duplicate")}
    print("robot T_REF refusals during the run:", counts)
    for reason in REFUSALS:
        assert counts[reason] > 0, "no %s sample refused: %s, sent %s" % (reason, counts, sent)
    assert counts["rejected"] == sum(counts[r] for r in REFUSALS) and counts["duplicate"] == 0, counts
    log = arm.robot.log_text()[seen["log"]:]
    for reason, text in REFUSALS.items():
        line = next((line for line in log.splitlines() if text in line), None)
        assert line and ("topic " + TORQUE_TOPIC) in line, "no warning %r naming the topic:\n%s" % (text, log[-3000:])
        print(line)
    # The arm followed the controller, never stale: every refused sample left
    # the port alone (tref_steps: a reversed one gave each joint its own torque).
    assert after["stale"] == "no" and ctrl["stale"] == "no"
