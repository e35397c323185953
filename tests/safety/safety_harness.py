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
TRATE = np.array([1000, 2000, 1000, 200, 200, 200], dtype=float)
PERIOD = 0.002  # the robot interface's (FREQ 500)

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
    """One `sbs` master running the arm under `safety<tag><pid>`. SOURCE(name)
    gives another .sbs than the arm's (TASKS its tasks), PREFIX a command it
    runs under (ip netns exec), ENV more of its environment; WEB=False serves
    the Unix socket only (TCP and HTTP inside a network namespace would be out
    of this process's reach)."""

    def __init__(self, tag, before_start=None, source=sbs_source, tasks=TASKS, prefix=(), env=None, web=True):
        self.name = "safety%s%d" % (tag, os.getpid())
        self.tasks = tasks
        self.prefix = list(prefix)
        self.web = web
        self.dir = tempfile.mkdtemp(prefix="chimera-%s-" % self.name)
        os.chmod(self.dir, 0o700)
        self.sbs = os.path.join(self.dir, self.name + ".sbs")
        with open(self.sbs, "w") as f:
            f.write(source(self.name))
        shutil.copy(os.path.join(HERE, "puma_safe.rmod"), self.dir)  # found beside the .sbs
        self.token_file = os.path.join(self.dir, "token")
        with open(self.token_file, "w") as f:
            f.write(TOKEN + "\n")
        os.chmod(self.token_file, 0o600)
        self.env = dict(os.environ, XDG_RUNTIME_DIR=self.dir, **(env or {}))
        self.socket = os.path.join(self.dir, "chimera", self.name + ".sock")
        self.log_path = os.path.join(self.dir, "sbs.log")
        if before_start:
            before_start(self)
        try:
            self.start()
        except BaseException:
            self.stop()  # a master that never came up must not stay behind
            raise

    def start(self):
        self.log = open(self.log_path, "a")
        web = ["--tcp", "127.0.0.1:0", "--http", "127.0.0.1:0", "--token-file", self.token_file] if self.web else []
        self.proc = subprocess.Popen(
            self.prefix + [SBS, self.sbs, "--listen"] + web + ["--serve", "--no-attach"],
            stdin=subprocess.DEVNULL, stdout=self.log, stderr=self.log, env=self.env)
        if self.web:
            self.tcp_port = int(self.wait_log(r"listening on .*TCP 127\.0\.0\.1:(\d+)").group(1))
            self.http_port = int(self.wait_log(r"web console of subsystem \S+ on http://127\.0\.0\.1:(\d+)/").group(1))
        else:
            self.wait_log(r"subsystem \S+ listening on ")
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
                if all(self.row(m, t)["state"] == "ON" for t in self.tasks):
                    return
            time.sleep(0.1)
        raise RuntimeError("the arm's tasks did not all turn ON")

    @staticmethod
    def row(m, rmod):
        return next(t for t in m.status() if t["rmod"] == rmod)

    def misses(self):
        """Missed releases, summed over the arm's tasks."""
        with self.master() as m:
            return sum(int(self.row(m, t)["miss"]) for t in self.tasks)

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
    """Peaks of |Q^_MEZ| and |T_MEZ| per joint, of the torque rate, the
    sample rate, the misses. The sampler runs on the arm's RTPU at its rate,
    released with it: between two samples n periods apart (by the sampler's
    cycle count or the time, whichever says more) at most n + 1 of the
    arm's cycles ran, whatever the two tasks' order, each changing the
    torque by at most TRATE x period; the torque rate of the two samples is
    |dT| / ((n + 1) x period), which never reads above TRATE while the limit
    holds (at the limit it reads TRATE / 2 when each sample follows one
    cycle, as measured)."""

    def __init__(self, rec, misses, seconds, stall):
        self.samples = len(rec)
        self.rate = self.samples / seconds
        self.lost = rec.lost
        self.peak_speed = np.abs(rec["Q^_MEZ"]).max(axis=0) if self.samples else np.full(6, np.nan)
        self.peak_torque = np.abs(rec["T_MEZ"]).max(axis=0) if self.samples else np.full(6, np.nan)
        if self.samples > 1:
            periods = np.maximum(np.diff(np.asarray(rec.cycle, dtype=float)),
                                 np.round(np.diff(np.asarray(rec.time_ns, dtype=float)) * 1e-9 / PERIOD))
            self.peak_trate = (np.abs(np.diff(rec["T_MEZ"], axis=0)) / ((periods + 1) * PERIOD)[:, None]).max(axis=0)
        else:
            self.peak_trate = np.full(6, np.nan)
        self.misses = misses
        self.stall = stall
        # With T_REF sampled (the robot's torque command as its bridge wrote
        # it): the largest change between two samples, per joint.
        self.peak_tref_step = (np.abs(np.diff(rec["T_REF"], axis=0)).max(axis=0)
                               if "T_REF" in rec.variables and self.samples > 1 else None)
        # ... its peak per joint, and the longest run of samples in which it did not change at all.
        self.peak_tref = np.abs(rec["T_REF"]).max(axis=0) if "T_REF" in rec.variables and self.samples else None
        self.tref_held = longest_run(np.all(np.diff(rec["T_REF"], axis=0) == 0, axis=1)) \
            if "T_REF" in rec.variables and self.samples > 1 else None

    def __str__(self):
        return ("%d samples (%.0f Hz, %d lost), peak speed %s rad/s, peak torque %s N m, peak torque rate %s N m/s, "
                "misses %d, stall detector %.2f ms" % (self.samples, self.rate, self.lost, np.round(self.peak_speed, 3),
                                                       np.round(self.peak_torque, 1), np.round(self.peak_trate, 0),
                                                       self.misses, self.stall * 1e3) +
                ("" if self.peak_tref_step is None else ", peak T_REF step %s N m" % np.round(self.peak_tref_step, 1)) +
                ("" if self.peak_tref is None else ", peak |T_REF| %s N m, held %d samples"
                 % (np.round(self.peak_tref, 1), self.tref_held)))


def longest_run(flags):
    """The most consecutive True in FLAGS."""
    longest = run = 0
    for f in flags:
        run = run + 1 if f else 0
        longest = max(longest, run)
    return longest


def measure(arm, seconds, inject=None, extra=()):
    """Samples the arm for SECONDS while INJECT(arm, stop_event) runs in a
    thread (EXTRA: variables sampled beside Q^_MEZ and T_MEZ)."""
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
        started = m.sample(["Q^_MEZ", "T_MEZ"] + list(extra), rtpu="robot")
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


# ------------------------------------------------------------------ the arm over DDS

EXAMPLE = os.path.join(HERE, "..", "..", "examples", "two_machines")
ROBOT_TASKS = ("puma_safe", "robot_bridge")
CTRL_TASKS = ("jtraj_hold", "jpid_hold", "controller_bridge")
TORQUE_TOPIC = "rt/puma/joint_torques"


class NetnsPair:
    """Two network namespaces joined by a veth pair (scripts/netns_pair.sh,
    as tests/ddsbridge/test_two_machines.sh makes them): nothing in them but
    loopback and an end of the pair, so no DDS traffic leaves them, and the
    link can be cut. `reason` says why not, when they cannot be made."""

    def __init__(self):
        script = os.path.join(HERE, "..", "..", "scripts", "netns_pair.sh")
        self.names = []
        self.reason = None
        if os.geteuid() != 0:
            self.reason = "network namespaces need CAP_NET_ADMIN (run as root)"
            return
        # The pair's names carry this shell's pid; 10.223.0/30 lives only inside them.
        r = subprocess.run(["bash", "-c", '. "$0" && netns_pair_up sf 10.223.0 && echo "$NETNS_A $NETNS_B $VETH_A $VETH_B"',
                            script], capture_output=True, text=True)
        if r.returncode != 0:
            self.reason = "cannot create a network namespace: " + r.stderr.strip()
            return
        self.ns_a, self.ns_b, self.veth_a, self.veth_b = r.stdout.split()
        self.names = [self.ns_a, self.ns_b]

    def link(self, up):
        subprocess.run(["ip", "-n", self.ns_a, "link", "set", self.veth_a, "up" if up else "down"], check=True)

    def down(self):
        for ns in self.names:
            subprocess.run(["ip", "netns", "del", ns], stderr=subprocess.DEVNULL)

    def left(self):
        """Those of the pair's namespaces that still exist."""
        listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
        return [ns for ns in self.names if re.search(r"(?m)^%s\b" % re.escape(ns), listed)]


def dds_sbs_source(side, rtpu, cpu, tasks):
    """An .sbs of one side of examples/two_machines (its table) under the
    suite's name, its RTPU on CPU, TASKS spawned ON."""
    def source(name):
        return ("SUBSYSTEM %s\nSVARFILE  %s\nMASTER    %s\n\nRTPU      %s %d\nSCHEDULER RM\nERRPRINT  warnings\n"
                "MINFREQ   1.0\nMAXFREQ   1000.0\n%sEOF\n" % (
                    name, os.path.abspath(os.path.join(EXAMPLE, "two_machines.svar")), rtpu, rtpu, cpu,
                    "".join("TASK %s %s ON\n" % (t, rtpu) for t in tasks)))
    return source


def bridge_rmod(side, domain, extra=""):
    """A before_start that writes examples/two_machines' SIDE_bridge.rmod beside
    the .sbs on this run's DDS domain (and copies the .rmod files the side's
    tasks need)."""
    def write(arm):
        text = open(os.path.join(EXAMPLE, side + "_bridge.rmod")).read()
        text = re.sub(r"(?m)^DOMAIN .*", "DOMAIN    %d" % domain, text)
        text = re.sub(r"(?m)^CONFIG .*", "CONFIG    " + os.path.abspath(os.path.join(EXAMPLE, "cyclone.xml")), text)
        text = text.replace("\nEOF", "\n" + extra + "EOF") if extra else text
        with open(os.path.join(arm.dir, side + "_bridge.rmod"), "w") as f:
            f.write(text)
        for r in ("jtraj_hold.rmod", "jpid_hold.rmod"):
            shutil.copy(os.path.join(EXAMPLE, r), arm.dir)
    return write


def port_status(status, port):
    """The counts of PORT's line of a bridge's `get STATUS` (name -> int or
    'yes'/'no')."""
    m = re.search(r"(?m)^%s (counter .*)$" % re.escape(port), status)
    if not m:
        return {}
    words = m.group(1).split()
    return {k: (int(v) if re.fullmatch(r"\d+", v) else v) for k, v in zip(words[::2], words[1::2])}


class DdsArm:
    """The arm split over DDS as in examples/two_machines: the robot subsystem
    (puma_safe, the declared limits, and the robot's bridge: torques in, stale
    after 50 ms -> illegal configuration, the arm holds; a torque command must
    name every joint, JOINT_SUBSET refuse) in one network namespace, the
    controller (jtraj_hold, jpid_hold: STALE hold, and its bridge) in the
    other, on a DDS domain id of this run. measure() samples the robot side;
    misses() sums both subsystems' tasks."""

    def __init__(self, pair):
        self.pair = pair
        self.domain = 1 + os.getpid() % 230  # ports of domain 230: 64900..
        ctrl_cpu, robot_cpu = allowed_cpus()
        self.robot = self.ctrl = None
        try:
            self.robot = Arm("dr", bridge_rmod("robot", self.domain, "JOINT_SUBSET refuse\n"),
                             source=dds_sbs_source("robot", "robot", robot_cpu, ROBOT_TASKS), tasks=ROBOT_TASKS,
                             prefix=["ip", "netns", "exec", pair.ns_a], env={"CHIMERA_DDS_INTERFACE": pair.veth_a},
                             web=False)
            self.ctrl = Arm("dc", bridge_rmod("controller", self.domain),
                            source=dds_sbs_source("controller", "ctrl", ctrl_cpu, CTRL_TASKS), tasks=CTRL_TASKS,
                            prefix=["ip", "netns", "exec", pair.ns_b], env={"CHIMERA_DDS_INTERFACE": pair.veth_b},
                            web=False)
            self.wait_fresh(10)
        except BaseException:
            self.stop()
            raise
        self.names = [self.robot.name, self.ctrl.name]

    def master(self):
        return self.robot.master()

    def misses(self):
        return self.robot.misses() + self.ctrl.misses()

    def status(self):
        """(robot's T_REF, controller's Q_MEZ) port counts."""
        with self.robot.master() as m:
            robot = port_status(m.get("robot_bridge", "STATUS"), "T_REF")
        with self.ctrl.master() as m:
            ctrl = port_status(m.get("controller_bridge", "STATUS"), "Q_MEZ")
        return robot, ctrl

    def fresh(self):
        robot, ctrl = self.status()
        return robot.get("stale") == "no" and ctrl.get("stale") == "no"

    def wait_fresh(self, timeout):
        """Seconds until both sides have fresh data, None after TIMEOUT."""
        start = time.monotonic()
        while time.monotonic() - start < timeout:
            if self.fresh():
                return time.monotonic() - start
            time.sleep(0.02)
        return None

    def stop(self):
        """Both masters finished, the namespaces deleted; the masters' exit codes."""
        codes = [a.stop() for a in (self.robot, self.ctrl) if a]
        self.pair.down()
        return codes
