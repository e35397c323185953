"""A Python program as a peer of the master (issue #18.5, docs/python.md), like a LinuxCNC HAL
user-space component: it declares the variables it produces and consumes and runs its own
non-real-time loop against the table.

    with chimera.Peer("vision", produces=["TARGET"], consumes=["Q_MEZ"], subsystem="arm") as p:
        for cycle in p.run(hz=30):            # absolute deadlines; p.overruns counts late cycles
            q = p.read()["Q_MEZ"]              # the consumed set, one table lock
            p.write(TARGET=estimate(q))        # the produced set, one table lock

The master holds a peer task NAME (module ``peer``, TASKTYPE background) for the process: the
§3.3.1 verification counts it as the producer of its outputs (a task reading them may be turned
on; a second producer is refused, naming both), ``status`` lists it, and when the process ends
without close() (killed, crashed) the task goes to ERROR the next time the master is commanded,
so it is no longer counted as a producer.
"""

from __future__ import annotations

import os
import sys
import time
from typing import Any, Dict, Iterator, List, Optional, Sequence

import numpy

from . import _core
from ._master import Master, MasterError
from ._record import _subsystem


class Peer:
    """The process as the producer of PRODUCES and a consumer of CONSUMES in SUBSYSTEM (the running
    one when only one runs), declared to its master as task NAME. MASTER: a Master to use (else one is
    opened for start and close only, so control stays free meanwhile)."""

    def __init__(self, name: str, *, produces: Sequence[str] = (), consumes: Sequence[str] = (),
                 subsystem: Optional[str] = None, master: Optional[Master] = None,
                 socket_path: Optional[str] = None, lock_timeout: float = 0.1):
        self.name = name
        self.produces: List[str] = list(produces)
        self.consumes: List[str] = list(consumes)
        if not self.produces and not self.consumes:
            raise ValueError("Peer %s: it produces and consumes nothing" % name)
        self._master = master
        self._socket_path = socket_path
        self.subsystem = master.subsystem if master else _subsystem(subsystem)
        self._lock_timeout = lock_timeout
        self.overruns = 0
        self.cycles = 0
        self._started = False
        self.table: Optional[_core.Table] = None

    # -- life ----------------------------------------------------------------------------

    def start(self) -> "Peer":
        """Declare the peer to the master and map the table. Turning the peer task on is checked as `on`
        is: MasterError when another ON task produces one of PRODUCES. (As for any task, an input nobody
        produces is found by the whole-configuration check of `reconfig`, not by `on`.)"""
        if self._started:
            return self
        self.table = _core.Table.attach(self.subsystem, self._lock_timeout)
        for n in self.produces + self.consumes:
            self.table.info(n)  # SvarError naming the variable before the master is asked
        self._reader = self.table.reader(self.consumes) if self.consumes else None
        program = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else "python"
        self._with_master(lambda m: m.peer(self.name, os.getpid(), self.produces, self.consumes, program))
        self._started = True
        # The peer is the producer: its writes pass the producer rule (force), nothing else's do.
        self._writer = self.table.writer(self.produces, force=True) if self.produces else None
        return self

    def close(self) -> None:
        """Remove the peer task (`kill NAME`): its outputs keep their last values and have no producer."""
        if not self._started:
            return
        self._started = False
        try:
            self._with_master(lambda m: m.kill(self.name))
        except MasterError as e:
            if "no task" not in e.message:
                raise

    def _with_master(self, action: Any) -> Any:
        if self._master is not None:
            return action(self._master)
        with Master(self.subsystem, socket_path=self._socket_path) as m:
            return action(m)

    def __enter__(self) -> "Peer":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the loop --------------------------------------------------------------------------

    def read(self) -> Dict[str, numpy.ndarray]:
        """The consumed variables as one consistent set (one table lock): read-only views refreshed in
        place by the next read (copy what you keep)."""
        if self._reader is None:
            raise ValueError("Peer %s consumes nothing" % self.name)
        return dict(self._reader.read())

    def write(self, values: Optional[Dict[str, Any]] = None, **named: Any) -> None:
        """Write produced variables (a dict and/or NAME=value), checked as `sbs setvar` checks them, then the
        whole produced set in one table lock (the ones not given keep what this peer last wrote)."""
        if self._writer is None:
            raise ValueError("Peer %s produces nothing" % self.name)
        given = dict(values or {}, **named)
        for n in given:
            if n not in self.produces:
                raise ValueError("Peer %s does not produce %s (it produces %s)" % (self.name, n, " ".join(self.produces)))
        for n, v in given.items():
            self._writer.set(n, v)
        self._writer.write()

    @property
    def outputs(self) -> Dict[str, numpy.ndarray]:
        """The produced set's arrays, to fill in place before ``write()`` with no argument."""
        if self._writer is None:
            raise ValueError("Peer %s produces nothing" % self.name)
        return dict(self._writer.arrays)

    def run(self, hz: float, cycles: Optional[int] = None) -> Iterator[int]:
        """Yield cycle numbers at HZ against absolute deadlines (a late cycle is counted in ``overruns`` and
        the schedule moves on, not bunched up); stops after CYCLES when given."""
        if not hz > 0:
            raise ValueError("run: hz must be positive")
        period = 1.0 / hz
        next_release = time.monotonic()
        n = 0
        while cycles is None or n < cycles:
            yield n
            n += 1
            self.cycles += 1
            next_release += period
            late = time.monotonic() - next_release
            if late > 0:
                self.overruns += 1
                next_release += period * (int(late / period) + 1) - period
            else:
                time.sleep(-late)
