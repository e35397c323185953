"""Harness of the fault-injection suite (issue #29 item 9).

Arm: the Figure 3.7 subsystem (jtraj, jpid, grav_comp and a robot interface
with declared limits, puma_safe.rmod) run by the real `sbs` master under a
subsystem name of its own, served on a Unix socket, TCP (token) and HTTP (the
web console), its stderr in a log file the tests read for the line naming a
cause.

measure(): samples Q^_MEZ (joint speed) and T_MEZ (applied torque) at the
robot's 500 Hz through a sampler task, and the tasks' missed releases, while
an injection runs. A stall detector (a top-priority process sleeping 1 ms
at a time) tells a machine that stopped everything, the only case in which a test
may run again, and says so."""

import glob
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

import chimera

SBS = os.environ.get("SBS_EXE", "sbs")
HERE = os.path.dirname(os.path.abspath(__file__))
TOKEN = "safety-token-%d" % os.getpid()
TASKS = ("puma_safe", "jtraj", "jpid", "grav_comp")

# The limits puma_safe.rmod declares.
VLIMIT = np.array([1, 1, 1, 2, 2, 2], dtype=float)
TLIMIT = np.array([97.6, 186.4, 89.4, 24.2, 20.1, 21.3])

# The stall detector's wake-up later than this (the robot interface's 2 ms
# period) means the machine stopped the arm too (StallDetector says how).
STALL_S = 0.002


def allowed_cpus():
    cpus = sorted(os.sched_getaffinity(0))
    return cpus[0], cpus[-1]


def sbs_source(name):
    """fig3_7.sbs under NAME, its RTPUs on CPUs this process may use, the
    suite's table, the four tasks spawned ON."""
    ctrl, robot = allowed_cpus()
    src = open(os.path.join(HERE, "..", "..", "examples", "fig3_7_pid", "fig3_7.sbs")).read()
    src = src.replace("SUBSYSTEM fig3_7", "SUBSYSTEM " + name)
    src = src.replace("SVARFILE  fig3_7.svar", "SVARFILE  " + os.path.join(HERE, "safety_arm.svar"))
    src = re.sub(r"(?m)^RTPU\s+ctrl\s+\d+", "RTPU      ctrl %d" % ctrl, src)
    src = re.sub(r"(?m)^RTPU\s+robot\s+\d+", "RTPU      robot %d" % robot, src)
    tasks = "".join("TASK %s %s ON\n" % (t, "robot" if t == "puma_safe" else "ctrl") for t in TASKS)
    return src.replace("EOF", tasks + "EOF")


class Arm:
    """One `sbs` master running the arm under `safety<tag><pid>`."""

    def __init__(self, tag, before_start=None):
        self.name = "safety%s%d" % (tag, os.getpid())
        self.dir = tempfile.mkdtemp(prefix="chimera-%s-" % self.name)
        os.chmod(self.dir, 0o700)
        self.sbs = os.path.join(self.dir, self.name + ".sbs")
        with open(self.sbs, "w") as f:
            f.write(sbs_source(self.name))
        shutil.copy(os.path.join(HERE, "puma_safe.rmod"), self.dir)  # found beside the .sbs
        self.token_file = os.path.join(self.dir, "token")
        with open(self.token_file, "w") as f:
            f.write(TOKEN + "\n")
        os.chmod(self.token_file, 0o600)
        self.env = dict(os.environ, XDG_RUNTIME_DIR=self.dir)
        self.socket = os.path.join(self.dir, "chimera", self.name + ".sock")
        self.log_path = os.path.join(self.dir, "sbs.log")
        if before_start:
            before_start(self)
        self.start()

    def start(self):
        self.log = open(self.log_path, "a")
        self.proc = subprocess.Popen(
            [SBS, self.sbs, "--listen", "--tcp", "127.0.0.1:0", "--http", "127.0.0.1:0",
             "--token-file", self.token_file, "--serve", "--no-attach"],
            stdin=subprocess.DEVNULL, stdout=self.log, stderr=self.log, env=self.env)
        self.tcp_port = int(self.wait_log(r"listening on .*TCP 127\.0\.0\.1:(\d+)").group(1))
        self.http_port = int(self.wait_log(r"web console of subsystem \S+ on http://127\.0\.0\.1:(\d+)/").group(1))
        self.wait_on()

    def log_text(self):
        with open(self.log_path) as f:
            return f.read()

    def wait_log(self, pattern, timeout=60):
        deadline = time.time() + timeout
        while time.time() < deadline:
            m = re.search(pattern, self.log_text())
            if m:
                return m
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        raise RuntimeError("sbs: no line matching %r; its log:\n%s" % (pattern, self.log_text()))

    def master(self):
        return chimera.Master(self.name, socket_path=self.socket, token=TOKEN)  # --tcp: every peer gives it

    def wait_on(self, timeout=30):
        deadline = time.time() + timeout
        while time.time() < deadline:
            with self.master() as m:
                if all(self.row(m, t)["state"] == "ON" for t in TASKS):
                    return
            time.sleep(0.1)
        raise RuntimeError("the arm's tasks did not all turn ON")

    @staticmethod
    def row(m, rmod):
        return next(t for t in m.status() if t["rmod"] == rmod)

    def misses(self):
        """Missed releases, summed over the arm's four tasks."""
        with self.master() as m:
            return sum(int(self.row(m, t)["miss"]) for t in TASKS)

    def stop(self):
        """Finishes the master (as the operator would) and removes the folder."""
        if self.proc.poll() is None:
            try:
                with self.master() as m:
                    m.finish()
            except Exception:
                pass
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()
        shutil.rmtree(self.dir, ignore_errors=True)
        return self.proc.returncode


def leftovers(name):
    """What of subsystem NAME is still in /dev/shm or /tmp (names carry it)."""
    return sorted(glob.glob("/dev/shm/*%s*" % name) + glob.glob("/tmp/*%s*" % name) +
                  glob.glob("/tmp/*/*%s*" % name))


# The detector: a process of its own (its own interpreter lock, which a
# thread of this one would wait for as long as 5 ms) at SCHED_FIFO 95, above
# the arm's tasks, sleeping 1 ms at a time; at the end it prints the longest
# any sleep overshot. A top-priority thread woken over a controller period late
# means the machine (vCPU steal, a long non-preemptible kernel section) stopped
# everything, the arm's tasks too: their misses then say nothing of the injection.
_DETECTOR = r"""
import os, sys, time
try:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(95))
except OSError:
    pass  # not root: a plain thread still sees a stopped machine
worst = 0.0
sys.stdin = open(sys.stdin.fileno(), "rb", buffering=0)
os.set_blocking(sys.stdin.fileno(), False)
last = time.monotonic()
while True:
    time.sleep(0.001)
    now = time.monotonic()
    worst = max(worst, now - last - 0.001)
    last = now
    try:
        if sys.stdin.read(1) is not None:
            break
    except BlockingIOError:
        pass
print(worst, flush=True)
"""


class StallDetector:
    """`worst`: the longest a 1 ms sleep of a top-priority process overshot
    while it ran (seconds)."""

    def __init__(self):
        self.worst = 0.0
        self._proc = None

    def start(self):
        self._proc = subprocess.Popen([sys.executable, "-c", _DETECTOR], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, text=True)

    def stop(self):
        out, _ = self._proc.communicate("x", timeout=10)
        self.worst = float(out.strip())

    @property
    def disturbed(self):
        return self.worst > STALL_S


class Measurement:
    """Peaks of |Q^_MEZ| and |T_MEZ| per joint, the sample rate, the misses."""

    def __init__(self, rec, misses, seconds, stall):
        self.samples = len(rec)
        self.rate = self.samples / seconds
        self.lost = rec.lost
        self.peak_speed = np.abs(rec["Q^_MEZ"]).max(axis=0) if self.samples else np.full(6, np.nan)
        self.peak_torque = np.abs(rec["T_MEZ"]).max(axis=0) if self.samples else np.full(6, np.nan)
        self.misses = misses
        self.stall = stall

    def __str__(self):
        return ("%d samples (%.0f Hz, %d lost), peak speed %s rad/s, peak torque %s N m, misses %d, "
                "stall detector %.2f ms" % (self.samples, self.rate, self.lost, np.round(self.peak_speed, 3),
                                             np.round(self.peak_torque, 1), self.misses, self.stall * 1e3))


def measure(arm, seconds, inject=None):
    """Samples the arm for SECONDS while INJECT(arm, stop_event) runs in a thread."""
    stall = StallDetector()
    stall.start()
    misses0 = arm.misses()
    done = threading.Event()
    errors = []

    def injector():
        try:
            inject(arm, done)
        except Exception as e:  # reported by the test, not lost in the thread
            errors.append(e)

    thread = threading.Thread(target=injector, daemon=True) if inject else None
    # The master's connection is held only to start and to kill the sampler:
    # its control slot is one for all interfaces, and injections need it.
    with arm.master() as m:
        started = m.sample(["Q^_MEZ", "T_MEZ"], rtpu="robot")
    ring = chimera.Ring.attach(started["ring"])
    if thread:
        thread.start()
    parts = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        time.sleep(0.05)
        parts.append(read_ring(ring))
    done.set()
    if thread:
        thread.join(timeout=30)
    parts.append(read_ring(ring))
    with arm.master() as m:
        m.kill(started["rmod"])
    rec = chimera.Recording.join(parts)
    stall.stop()
    if errors:
        raise errors[0]
    return Measurement(rec, arm.misses() - misses0, seconds, stall.worst)


def read_ring(ring):
    time_ns, cycle, values, lost = ring.read(None)
    return chimera.Recording(list(ring.channels), time_ns, cycle, values, lost, float(ring.rate))
