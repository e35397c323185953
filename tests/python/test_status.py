"""Task status from Python (issue #18.3): typed records of every task, and a DataFrame."""

import time

import pytest

import chimera

SBS_SCRIPT = "spawn ramp; spawn follow; on ramp"


def wait_for(predicate, timeout=5.0):
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_every_task_as_a_typed_record(subsystem):
    reader = chimera.StatusReader(subsystem.name)
    assert reader.alive and reader.subsystem == subsystem.name and reader.master_pid == subsystem.process.pid
    wait_for(lambda: next(t for t in reader.snapshot() if t.rmod == "ramp").cycle >= 5)
    tasks = {t.rmod: t for t in reader.snapshot()}
    assert sorted(tasks) == ["follow", "ramp"]
    ramp, follow = tasks["ramp"], tasks["follow"]
    assert (ramp.state, follow.state) == ("ON", "OFF")
    assert (ramp.type, ramp.rtpu, ramp.ref_f, ramp.ref_t) == ("P", "cpu0", 200.0, 0.005)
    assert ramp.outputs == ["X"] and follow.inputs == ["X"] and follow.outputs == ["Y"]
    assert ramp.tid > 0 and ramp.miss >= 0 and ramp.max_c >= ramp.min_c > 0
    assert ramp.cyc_p50 is not None and ramp.cyc_p50 <= ramp.cyc_max
    assert follow.cycle == 0 and follow.cyc_p50 is None
    assert list(ramp.to_dict()) == list(chimera.TASK_STATUS_FIELDS)
    assert [t.rmod for t in chimera.status(subsystem.name)] == ["ramp", "follow"]


def test_take_counts_since_this_readers_last_take(subsystem):
    reader = chimera.StatusReader(subsystem.name)  # its window starts here
    ramp_cycles = lambda: next(t for t in reader.snapshot() if t.rmod == "ramp").cycle
    at_attach = ramp_cycles()
    wait_for(lambda: ramp_cycles() >= at_attach + 40)
    first = next(t for t in reader.take() if t.rmod == "ramp")
    assert first.windowed and 40 <= first.cycle < ramp_cycles()
    second = next(t for t in reader.take() if t.rmod == "ramp")
    assert second.cycle < first.cycle  # a new window; the counts since the reset run on
    assert ramp_cycles() >= at_attach + 40


def test_unknown_subsystem(subsystem):
    with pytest.raises(chimera.SvarError, match=r"^no subsystem nosuchsub is running \(no status segment\)$"):
        chimera.StatusReader("nosuchsub")


def test_to_dataframe(subsystem):
    pandas = pytest.importorskip("pandas")
    frame = chimera.to_dataframe(chimera.status(subsystem.name))
    assert isinstance(frame, pandas.DataFrame)
    assert list(frame.index) == ["ramp", "follow"] and frame.loc["ramp", "state"] == "ON"
