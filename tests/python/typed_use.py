"""A typed use of the package, checked by mypy against the shipped stubs (test_stubs.py). Never run."""

from typing import Dict, List, Optional

import numpy as np

import chimera


def use(subsystem: str) -> float:
    table: chimera.Table = chimera.attach(subsystem, lock_timeout=0.5)
    names: List[str] = table.names()
    info: chimera.VarInfo = table.info(names[0])
    low: Optional[np.ndarray] = info.min
    reader: chimera.Reader = table.reader(["Q_REF", "Q_MEZ"])
    views: Dict[str, np.ndarray] = reader.read()
    writer: chimera.Writer = table.writer(["Q_REF"], force=True)
    writer.set("Q_REF", [0.0] * 6)
    writer.write()
    table.write({"Q_REF": np.zeros(6)}, force=False)
    tasks: List[chimera.TaskStatus] = chimera.status(subsystem)
    p99: Optional[float] = tasks[0].lat_p99
    buf = chimera.Tbuf.create(chimera.segment_name(subsystem, "tb"), 48)
    counter: int = buf.write(np.zeros(6), time_ns=5)
    item: chimera.TbufItem = buf.read()
    with chimera.Master(subsystem) as m:
        m.on("jpid")
        rows: List[dict] = m.status()
    rec: chimera.Recording = chimera.record(["Q_REF", "Q_MEZ"], seconds=2.0, subsystem=subsystem)
    q: np.ndarray = rec["Q_MEZ"]
    lost: int = rec.lost
    with chimera.Peer("vision", produces=["TARGET"], consumes=["Q_MEZ"], subsystem=subsystem) as peer:
        for cycle in peer.run(hz=30, cycles=3):
            peer.write(TARGET=peer.read()["Q_MEZ"][:3])
    return float(views["Q_REF"][0]) + (p99 or 0.0) + counter + item.counter + len(rows) + (0 if low is None else 1) + float(q[0, 0]) + lost
