"""Chimera for Linux from Python: the host-workstation side (thesis §5.3.2).

    import chimera
    table = chimera.attach("fig3_7")              # the running subsystem's SVAR table
    q = table.read(["Q_REF", "Q_MEZ"])            # one consistent set, one table lock
    table.write("Q_REF", [0, 0.8, 3.1, 0, 0.8, 0])  # range- and producer-checked
    for t in chimera.status("fig3_7"): print(t.rmod, t.state, t.mez_f)
    with chimera.Master("fig3_7") as m: m.on("jpid")  # the master over its socket
    rec = chimera.record(["Q_REF", "Q_MEZ"], seconds=2.0)  # at a task's rate, every sample once
    with chimera.Peer("vision", produces=["TARGET"], consumes=["Q_MEZ"]) as p: ...  # a producer the master knows

When a subsystem's master finishes, every call on a Table, Tbuf, StatusReader or
Sampling of it raises chimera.SubsystemGone (a ChimeraError) and the object lets
go of its segments: attach again once the subsystem runs again.

Nothing here runs on a real-time thread: every call that may wait for the table
lock releases the GIL, and no Python code runs while the lock is held.

chimera.__version__ is the project's version; TASK_STATUS_FIELDS names TaskStatus's fields in
to_dict() and to_dataframe() order. Every public name says what it is under help().
"""

# The namespace is the API (__all__): helpers are imported under private names and the
# parts live in private modules (_core, _master, _peer, _record, _serve).
from typing import Iterable as _Iterable, List as _List, Optional as _Optional

from ._core import (  # noqa: F401  (re-exported)
    TASK_STATUS_FIELDS,
    __version__,
    ChimeraError,
    LockTimeout,
    ProducerConflict,
    Reader,
    Ring,
    StatusReader,
    SubsystemGone,
    SvarError,
    Table,
    TaskStatus,
    Tbuf,
    TbufError,
    TbufItem,
    VarInfo,
    Writer,
    segment_name,
)
from ._master import Master, MasterError  # noqa: F401
from ._peer import Peer  # noqa: F401
from ._record import Recording, Sampling, record, running_subsystems  # noqa: F401
from ._serve import ServedSubsystem, serve  # noqa: F401

__all__ = [
    "attach", "status", "to_dataframe", "segment_name",
    "Table", "VarInfo", "Reader", "Writer", "Tbuf", "TbufItem", "StatusReader", "TaskStatus",
    "Master", "MasterError", "serve", "ServedSubsystem", "ChimeraError", "SvarError", "LockTimeout", "ProducerConflict", "TbufError",
    "SubsystemGone",
    "TASK_STATUS_FIELDS", "record", "Recording", "Sampling", "Ring", "Peer", "running_subsystems",
]


def attach(subsystem: str, lock_timeout: float = 0.1) -> Table:
    """The global state-variable table of the running subsystem SUBSYSTEM."""
    return Table.attach(subsystem, lock_timeout)


def status(subsystem: str) -> _List[TaskStatus]:
    """Every task's status (§4.4.1), counted since its RTPU's last reset."""
    return StatusReader(subsystem).snapshot()


def to_dataframe(records: _Iterable[TaskStatus], index: _Optional[str] = "rmod"):
    """Task status records as a pandas DataFrame, one row per task (ImportError without pandas)."""
    import pandas  # optional: only this function needs it

    frame = pandas.DataFrame([r.to_dict() for r in records], columns=list(TASK_STATUS_FIELDS))
    return frame.set_index(index) if index else frame
