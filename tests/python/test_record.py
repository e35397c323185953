"""Recording at a task's rate through the sampler ring (issue #18.4): every sample once, in order,
and loss counted exactly when the reader falls behind."""

import time

import numpy as np
import pytest

import chimera

SBS_SCRIPT = "spawn ramp; on ramp"  # X += 1 every cycle at 200 Hz


def test_record_returns_every_sample_once_at_the_producers_rate(subsystem):
    with subsystem.master() as m:
        rec = chimera.record(["X", "LIMITS"], seconds=0.5, master=m)
        assert [t["rmod"] for t in m.status()] == ["ramp"], "the sampler task is gone afterwards"
    assert isinstance(rec, chimera.Recording)
    assert (len(rec), rec.rate, rec.lost) == (100, 200.0, 0)
    assert rec.columns == ["X", "LIMITS[0]", "LIMITS[1]", "LIMITS[2]"]
    assert rec.variables == ["X", "LIMITS"]
    assert rec.time_ns.dtype == np.int64 and rec.cycle.dtype == np.uint64 and rec.values.shape == (100, 4)
    # No sample lost or duplicated: the sampling task's cycles are consecutive, time moves on.
    assert np.all(np.diff(rec.cycle.astype(np.int64)) == 1)
    assert np.all(np.diff(rec.time_ns) > 0)
    assert rec.t[0] == 0.0 and rec.t[-1] > 0
    assert rec["X"].shape == (100,) and np.all(np.diff(rec["X"]) >= 0)  # a scalar: one column
    assert rec["LIMITS"].shape == (100, 3)
    assert np.array_equal(rec["LIMITS"][5], np.array([0.5, 1.5, 2.5]))
    assert np.array_equal(rec["LIMITS[1]"], np.full(100, 1.5))
    with pytest.raises(KeyError, match="Y was not recorded"):
        rec["Y"]


def test_a_reader_that_falls_behind_counts_exactly_what_it_lost(subsystem):
    with subsystem.master() as m:
        with chimera.Sampling("X", master=m, rate=1000, capacity=16) as s:
            assert s.ring.capacity == 16 and s.columns == ["X"]
            first = s.read()
            lost_before = first.lost
            for _ in range(400):  # the first samples after the start
                if len(first):
                    break
                time.sleep(0.005)
                first = s.read()
                lost_before += first.lost
            assert len(first) > 0
            time.sleep(0.3)  # 300 samples, 16 kept: this reader is lapped
            later = s.read()
            # The task's own cycle numbers say which samples never reached this reader.
            assert later.lost > 0
            assert later.lost == int(later.cycle[0]) - int(first.cycle[-1]) - 1
            assert np.all(np.diff(later.cycle.astype(np.int64)) == 1)
            assert s.lost == lost_before + later.lost


def test_record_errors_carry_the_masters_message(subsystem):
    with subsystem.master() as m:
        with pytest.raises(chimera.MasterError, match=r"^sample NOPE: table /chimera\.%s\.svar has no variable NOPE$"
                           % subsystem.name):
            chimera.record(["NOPE"], seconds=1, master=m)
        with pytest.raises(ValueError, match="seconds must be positive"):
            chimera.record(["X"], seconds=0, master=m)
        assert [t["rmod"] for t in m.status()] == ["ramp"]


def test_a_recording_as_csv_and_dataframe(subsystem, tmp_path):
    rec = chimera.record("X", seconds=0.1, subsystem=subsystem.name, socket_path=subsystem.socket)
    assert len(rec) == 20
    path = tmp_path / "x.csv"
    rec.to_csv(str(path))
    lines = path.read_text().splitlines()
    assert lines[0] == "t,X" and len(lines) == 21
    assert [float(v) for v in lines[1].split(",")] == [0.0, float(rec.values[0, 0])]
    pandas = pytest.importorskip("pandas")
    frame = rec.to_dataframe()
    assert list(frame.columns) == ["X"] and frame.index.name == "t" and len(frame) == 20
