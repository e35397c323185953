"""Python sees the end of a subsystem (issue #29.8): once its master has finished, every call on a Table,
Tbuf, StatusReader or Sampling of it raises SubsystemGone (a ChimeraError), the object unmaps its
segments, nothing of the subsystem stays in /dev/shm, and running_subsystems() no longer lists it.

Each test starts a master of its own (the real sbs, conftest.start_subsystem) under a name of its own,
and ends it itself."""

import glob
import os
import signal

import numpy as np
import pytest

import chimera
from conftest import start_subsystem

GONE = r"^subsystem %s has finished \(its master, pid \d+, is gone\): this %s is closed; attach again once the subsystem runs$"


@pytest.fixture
def served(tmp_path, request):
    """A master of a subsystem named for this process and test, with ramp spawned and on."""
    name = "pygone%d%s" % (os.getpid(), request.node.name.replace("test_", "")[:8].replace("_", ""))
    s = start_subsystem(name, str(tmp_path), "spawn ramp; on ramp")
    yield s
    s.stop()
    for left in glob.glob("/dev/shm/chimera.%s.*" % name):  # a failed test's leftovers, not another test's
        os.unlink(left)


def in_shm(name):
    return sorted(glob.glob("/dev/shm/chimera.%s.*" % name))


def mapped_here(name):
    """The segments of NAME this process still maps (deleted ones included)."""
    with open("/proc/self/maps") as f:
        return [line.split(None, 5)[-1].strip() for line in f if "/dev/shm/chimera.%s." % name in line]


def test_subsystem_gone_is_a_chimera_error():
    assert issubclass(chimera.SubsystemGone, chimera.ChimeraError)
    assert "SubsystemGone" in chimera.__all__


def test_a_table_kept_after_its_master_finished_raises_and_lets_go(served):
    table = chimera.attach(served.name)
    reader = table.reader(["X"])
    assert table.read("Y").shape == (1,) and "X" in table
    served.stop()
    assert in_shm(served.name) == [], "the master removed its table although this process maps it"
    calls = [lambda: table.read("X"), lambda: table.write("Y", 1.0, force=True), table.names, table.variables,
             lambda: table.info("X"), lambda: len(table), lambda: "X" in table, table.stats,
             lambda: table.lock_timeout, lambda: table.segment, lambda: table.reader(["X"]), reader.read]
    for call in calls:
        with pytest.raises(chimera.SubsystemGone, match=GONE % (served.name, "Table")):
            call()
    assert mapped_here(served.name) == []
    assert repr(table) == "<chimera.Table of subsystem %s, finished>" % served.name


def test_a_status_reader_kept_after_its_master_finished_raises_and_lets_go(served):
    reader = chimera.StatusReader(served.name)
    assert [t.rmod for t in reader.snapshot()] == ["ramp"] and reader.alive
    served.stop()
    for call in (reader.snapshot, reader.take, lambda: reader.alive, lambda: reader.master_pid):
        with pytest.raises(chimera.SubsystemGone, match=GONE % (served.name, "StatusReader")):
            call()
    assert mapped_here(served.name) == [] and in_shm(served.name) == []


def test_an_attached_tbuf_raises_and_is_removed_by_its_last_user(served):
    segment = chimera.segment_name(served.name, "force")
    writer = chimera.Tbuf.create(segment, 8)
    reader = chimera.Tbuf.attach(segment)
    writer.write(np.float64(1.5).tobytes())
    assert reader.read().status == "fresh"
    del writer  # this reader is its last user now: it keeps the segment
    served.stop()
    assert in_shm(served.name) == ["/dev/shm" + segment]
    for call in (reader.read, lambda: reader.write(bytes(8)), lambda: reader.read_into(np.zeros(1)),
                 lambda: reader.item_size, lambda: reader.missed_total, reader.detach):
        with pytest.raises(chimera.SubsystemGone, match=GONE % (served.name, "Tbuf")):
            call()
    assert in_shm(served.name) == [] and mapped_here(served.name) == []


def test_a_sampling_kept_after_its_master_finished_raises_and_closes_quietly(served):
    sampling = chimera.Sampling("X", subsystem=served.name, socket_path=served.socket, rate=200)
    sampling.read()
    served.stop()
    for call in (sampling.read, lambda: sampling.lost):
        with pytest.raises(chimera.SubsystemGone, match=GONE % (served.name, "Ring")):
            call()
    sampling.close()  # nothing left to kill: it only lets go
    assert mapped_here(served.name) == [] and in_shm(served.name) == []


def test_running_subsystems_lists_only_live_masters(served):
    assert served.name in chimera.running_subsystems()
    table = chimera.attach(served.name)
    served.process.send_signal(signal.SIGKILL)  # a crash: the master removes nothing
    served.process.wait()
    svar = "/dev/shm/chimera.%s.svar" % served.name
    assert svar in in_shm(served.name)
    assert served.name not in chimera.running_subsystems(), "its table is there, its master is not"
    with pytest.raises(chimera.SubsystemGone, match=GONE % (served.name, "Table")):
        table.names()
    assert svar not in in_shm(served.name), "this process was its last user: it removed it"
    assert mapped_here(served.name) == []
