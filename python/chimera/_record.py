"""Sampling and recording at a task's rate (issue #18.4, docs/python.md).

A ``sample`` task of the master reads the chosen elements at its rate, one
consistent set per cycle, into a shared-memory ring (include/chimera/sampler.hpp);
this process follows the ring. Every sample arrives once; if the reader falls
behind the ring, the samples it lost are counted, never silently skipped.

    rec = chimera.record(["Q_REF", "Q_MEZ"], seconds=2.0, subsystem="fig3_7")
    plt.plot(rec.t, rec["Q_MEZ"][:, 1])

    with chimera.Sampling(["Q_MEZ[1]"], subsystem="fig3_7") as s:   # a live stream
        for _ in range(100):
            chunk = s.read(); ...; time.sleep(0.05)
"""

from __future__ import annotations

import glob
import os
import re
import time
import warnings
from typing import Any, List, Optional, Sequence, Union

import numpy

from ._core import Ring, SubsystemGone, _master_alive
from ._master import Master

_COLUMN = re.compile(r"^(.*)\[(\d+)\]$")


class Recording:
    """Samples taken at a task's rate: ``time_ns`` (CLOCK_MONOTONIC, int64), ``t`` (seconds from the first
    sample), ``cycle`` (the sampling task's cycle, uint64), ``values`` (float64, one column per element),
    ``columns`` (their names), ``lost`` (samples the reader missed), ``rate`` (Hz).
    ``rec["Q_REF"]`` is the variable's elements as an (n, nelem) array ((n,) for a scalar), ``rec["Q_REF[2]"]``
    one column."""

    def __init__(self, columns: Sequence[str], time_ns: numpy.ndarray, cycle: numpy.ndarray,
                 values: numpy.ndarray, lost: int, rate: float):
        self.columns: List[str] = list(columns)
        self.time_ns = time_ns
        self.cycle = cycle
        self.values = values
        self.lost = int(lost)
        self.rate = float(rate)

    @classmethod
    def join(cls, parts: Sequence["Recording"]) -> "Recording":
        """One Recording of consecutive parts (Sampling.read()'s chunks) of the same columns."""
        if not parts:
            raise ValueError("Recording.join: no part")
        return cls(parts[0].columns, numpy.concatenate([p.time_ns for p in parts]),
                   numpy.concatenate([p.cycle for p in parts]), numpy.concatenate([p.values for p in parts]),
                   sum(p.lost for p in parts), parts[0].rate)

    @property
    def t(self) -> numpy.ndarray:
        """Each sample's time in seconds from the first sample (float64)."""
        return (self.time_ns - self.time_ns[0]) / 1e9 if len(self.time_ns) else numpy.zeros(0)

    @property
    def variables(self) -> List[str]:
        """The variables recorded, in column order."""
        names: List[str] = []
        for c in self.columns:
            m = _COLUMN.match(c)
            name = m.group(1) if m else c
            if name not in names:
                names.append(name)
        return names

    def __len__(self) -> int:
        return len(self.time_ns)

    def __getitem__(self, key: str) -> numpy.ndarray:
        if key in self.columns:
            return self.values[:, self.columns.index(key)]
        picked = [i for i, c in enumerate(self.columns) if (_COLUMN.match(c) or [None, c])[1] == key]
        if not picked:
            raise KeyError("%s was not recorded (columns: %s)" % (key, " ".join(self.columns)))
        return self.values[:, picked]

    def to_dataframe(self):
        """A pandas DataFrame indexed by t, one column per element (ImportError without pandas)."""
        import pandas  # optional

        frame = pandas.DataFrame(self.values, columns=self.columns)
        frame.insert(0, "t", self.t)
        return frame.set_index("t")

    def to_csv(self, path: str) -> None:
        """The CSV `sbs ... record` writes: t, then one column per element."""
        with open(path, "w") as f:
            f.write(",".join(["t"] + self.columns) + "\n")
            for t, row in zip(self.t, self.values):
                f.write(",".join(repr(float(x)) for x in (t, *row)) + "\n")

    def __repr__(self) -> str:
        return "<chimera.Recording %d samples x %d columns at %g Hz, %d lost>" % (
            len(self), len(self.columns), self.rate, self.lost)


def running_subsystems() -> List[str]:
    """The subsystems whose master runs on this machine: a state-variable table (/dev/shm/chimera.NAME.svar)
    whose master's status segment is published and whose master process lives (a table a crashed master
    left, or one made without a master, is not listed)."""
    names = (os.path.basename(p)[len("chimera."):-len(".svar")] for p in glob.glob("/dev/shm/chimera.*.svar"))
    return sorted(n for n in names if _master_alive(n))


def _subsystem(subsystem: Optional[str]) -> str:
    if subsystem:
        return subsystem
    running = running_subsystems()
    if len(running) == 1:
        return running[0]
    raise ValueError("name the subsystem (subsystem=...): %s" % (
        "none is running" if not running else "several are running: " + " ".join(running)))


class Sampling:
    """A ``sample`` task and this process's reader of its ring; ``read()`` gives the samples since the
    last read as a Recording (``lost`` counts what this reader missed). ``close()`` (or leaving the
    ``with`` block) kills the task. MASTER: a Master to use (else one is opened for the start and the
    stop only, so control stays free meanwhile)."""

    def __init__(self, variables: Union[str, Sequence[str]], *, subsystem: Optional[str] = None,
                 master: Optional[Master] = None, socket_path: Optional[str] = None, rate: Optional[float] = None,
                 rtpu: Optional[str] = None, capacity: Optional[int] = None):
        names = [variables] if isinstance(variables, str) else list(variables)
        self._master = master
        self._socket_path = socket_path
        self._subsystem = master.subsystem if master else _subsystem(subsystem)
        started = self._with_master(lambda m: m.sample(names, rate=rate, rtpu=rtpu, capacity=capacity))
        self.task: str = started["rmod"]
        try:
            self.ring = Ring.attach(started["ring"])
        except Exception:
            self._with_master(lambda m: m.kill(self.task))
            raise
        self.columns: List[str] = list(self.ring.channels)
        self.rate: float = float(self.ring.rate)
        self._open = True

    def _with_master(self, action: Any) -> Any:
        if self._master is not None:
            return action(self._master)
        with Master(self._subsystem, socket_path=self._socket_path) as m:
            return action(m)

    @property
    def lost(self) -> int:
        """Samples this reader lost since the start."""
        return int(self.ring.lost)

    def read(self, max_samples: Optional[int] = None) -> Recording:
        """The samples written since the last read (never waits)."""
        time_ns, cycle, values, lost = self.ring.read(max_samples)
        return Recording(self.columns, time_ns, cycle, values, lost, self.rate)

    def close(self) -> None:
        """Kills the sampling task. Once the subsystem has finished there is nothing to kill: close() then
        only lets go of the ring (it does not raise, so a ``with`` block ends with the error that ended it)."""
        if self._open:
            self._open = False
            try:
                self.ring.position  # SubsystemGone once the master has finished: the task ended with it
            except SubsystemGone:
                return
            self._with_master(lambda m: m.kill(self.task))

    def __enter__(self) -> "Sampling":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def record(variables: Union[str, Sequence[str]], seconds: float, *, subsystem: Optional[str] = None,
           master: Optional[Master] = None, socket_path: Optional[str] = None, rate: Optional[float] = None,
           rtpu: Optional[str] = None, capacity: Optional[int] = None, timeout: Optional[float] = None) -> Recording:
    """Record VARIABLES ('Q_REF', 'Q_REF[2]', 'Q_REF[0:2]') for SECONDS at a task's rate (RATE Hz; default
    the fastest producer's): round(SECONDS x rate) consecutive samples, each once. If this process fell
    behind the ring, ``lost`` says how many samples are missing (and a RuntimeWarning is issued).
    SUBSYSTEM: the running one when only one runs. Waits at most TIMEOUT seconds (default 2 x SECONDS + 2)."""
    if not seconds > 0:
        raise ValueError("record: seconds must be positive, not %r" % (seconds,))
    with Sampling(variables, subsystem=subsystem, master=master, socket_path=socket_path, rate=rate, rtpu=rtpu,
                  capacity=capacity) as s:
        want = max(1, int(round(seconds * s.rate)))
        chunks: List[Recording] = []
        got = 0
        deadline = time.monotonic() + (timeout if timeout is not None else 2 * seconds + 2)
        while got < want:
            chunk = s.read(want - got)
            if len(chunk) or chunk.lost:
                chunks.append(chunk)
                got += len(chunk)
                continue
            if s.ring.closed:
                raise RuntimeError("record: the sampler task %s was stopped after %d of %d samples" % (s.task, got, want))
            if time.monotonic() > deadline:
                raise TimeoutError("record: the sampler task %s gave %d of %d samples in time" % (s.task, got, want))
            time.sleep(min(0.01, max(0.001, (want - got) / s.rate / 4)))
    result = Recording.join(chunks) if chunks else Recording(s.columns, numpy.zeros(0, numpy.int64),
                                                              numpy.zeros(0, numpy.uint64),
                                                              numpy.zeros((0, len(s.columns))), 0, s.rate)
    lost = result.lost
    if lost:
        warnings.warn("record: %d samples lost (this process fell behind the ring)" % lost, RuntimeWarning, stacklevel=2)
    return result


