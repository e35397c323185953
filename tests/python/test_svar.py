"""The state-variable table from Python (issue #18.2): listing, whole-set reads, checked writes."""

import time

import numpy as np
import pytest

import chimera
from conftest import run_python

# ramp writes X; follow (also MODULE ramp) reads X and writes Y.
SBS_SCRIPT = "spawn ramp; spawn follow"


@pytest.fixture(scope="module")
def table(subsystem):
    return chimera.attach(subsystem.name)


def test_variables_list_type_size_units_range_and_users(table):
    assert table.names()[:3] == ["X", "Y", "LIMITS"]
    info = {v.name: v for v in table.variables()}
    lim = info["LIMITS"]
    assert (lim.type, lim.nelem, lim.elem_size, lim.units, lim.desc) == ("float", 3, 4, "rad", "limits")
    assert lim.dtype == np.dtype("float32") and lim.shape == (3,)
    assert list(lim.init) == [0.5, 1.5, 2.5]
    assert list(lim.min) == [0, 0, 0] and list(lim.max) == [10, 10, 3]
    assert info["X"].min is None and info["X"].max is None
    assert info["X"].producers == ["ramp"] and info["X"].consumers == ["follow"]
    assert info["Y"].producers == ["follow"] and info["LIMITS"].producers == []
    assert info["COUNT"].dtype == np.dtype("int16") and info["MODE"].dtype == np.dtype("uint8")
    blob = info["BLOB"]
    assert (blob.type, blob.shape, blob.dtype, blob.init) == ("struct[16]", (2, 16), np.dtype("uint8"), None)


def test_read_one_and_several_as_numpy(table):
    assert table.read("COUNT").tolist() == [-3, 7]
    got = table.read(["LIMITS", "COUNT"])
    assert list(got) == ["LIMITS", "COUNT"]
    assert got["LIMITS"].dtype == np.float32 and got["LIMITS"].tolist() == [0.5, 1.5, 2.5]
    got["COUNT"][0] = 99  # a copy: the table is untouched
    assert table.read("COUNT").tolist() == [-3, 7]


def test_unknown_names_and_subsystems_are_named(table, subsystem):
    with pytest.raises(KeyError, match="table /chimera.%s.svar has no variable NOPE" % subsystem.name):
        table.read(["LIMITS", "NOPE"])
    with pytest.raises(chimera.SvarError, match=r"^no subsystem nosuchsub is running \(no segment /chimera.nosuchsub.svar\)$"):
        chimera.attach("nosuchsub")


def test_write_checks_type_and_range_like_setvar(table, subsystem):
    seg = "/chimera.%s.svar" % subsystem.name
    table.write("LIMITS", [1, 2, 3])
    assert table.read("LIMITS").tolist() == [1, 2, 3]
    table.write("LIMITS", 2)  # one value for all, as `setvar LIMITS 2`
    assert table.read("LIMITS").tolist() == [2, 2, 2]
    with pytest.raises(ValueError, match=r"^%s: LIMITS\[2\]: 4.0 is outside the .svar range \[0, 3\]$" % seg):
        table.write("LIMITS", [1, 2, 4])
    with pytest.raises(ValueError, match=r"COUNT\[1\]: 40000.0 does not fit type short\[2\]$"):
        table.write("COUNT", [1, 40000])
    with pytest.raises(ValueError, match=r"MODE\[0\]: nan is not a finite number$"):
        table.write("MODE", float("nan"))
    with pytest.raises(ValueError, match="LIMITS has 3 elements: give one value for all or every value, not 2"):
        table.write("LIMITS", [1, 2])
    # a refused set writes nothing, not even the variables before the bad one
    with pytest.raises(ValueError):
        table.write({"COUNT": [5, 6], "LIMITS": [1, 1, 9]})
    assert table.read("COUNT").tolist() == [-3, 7] and table.read("LIMITS").tolist() == [2, 2, 2]
    # the command line refuses the same value with the same reason
    with subsystem.master() as m:
        with pytest.raises(chimera.MasterError, match=r"LIMITS\[2\]: 4 is outside the .svar range \[0, 3\]$"):
            m.setvar("LIMITS", 1, 2, 4)
    table.write({"COUNT": [-1.5, 2.5], "MODE": 255})  # integers rounded half away from zero, as setvar
    assert table.read("COUNT").tolist() == [-2, 3] and table.read("MODE").tolist() == [255]


def test_struct_takes_exact_bytes(table):
    table.write("BLOB", bytes(range(32)))
    assert table.read("BLOB").tobytes() == bytes(range(32))
    with pytest.raises(ValueError, match="BLOB is struct\\[16\\]\\[2\\]: give exactly 32 bytes, not 3"):
        table.write("BLOB", b"abc")


def test_producer_rule_and_force(table, subsystem):
    with pytest.raises(chimera.ProducerConflict,
                       match=r"X is produced by ramp: its next cycle overwrites it \(write\(..., force=True\) writes it anyway\)$"):
        table.write("X", 5.0)
    table.write("X", 5.0, force=True)  # ramp is OFF: nothing overwrites it
    assert table.read("X").tolist() == [5.0]
    assert table.writer(["X"], force=True).force


def test_reader_views_are_refreshed_in_place_and_read_only(table):
    r = table.reader(["J1", "J2"])
    views = r.read()
    j1 = views["J1"]
    assert j1.shape == (6,) and j1.dtype == np.float32 and not j1.flags.writeable
    table.write({"J1": np.arange(6), "J2": 1})
    assert j1.tolist() == [0, 0, 0, 0, 0, 0]  # not read yet
    r.read()
    assert j1.tolist() == [0, 1, 2, 3, 4, 5] and r.arrays["J2"].tolist() == [1] * 6
    assert r.last_status == "ok"
    with pytest.raises(ValueError):
        j1[0] = 3


def test_writer_fills_views_then_checks_on_write(table):
    w = table.writer(["J3", "LIMITS"])
    a = w.arrays
    a["J3"][:] = np.linspace(0, 1, 6)
    a["LIMITS"][:] = [1, 1, 1]
    w.write()
    got = table.read(["J3", "LIMITS"])
    assert np.allclose(got["J3"], np.linspace(0, 1, 6)) and got["LIMITS"].tolist() == [1, 1, 1]
    a["LIMITS"][2] = 7
    with pytest.raises(ValueError, match=r"LIMITS\[2\]: 7.0 is outside the .svar range \[0, 3\]$"):
        w.write()
    assert table.read("LIMITS").tolist() == [1, 1, 1]


WRITER = """
import sys, numpy as np, chimera
t = chimera.attach(sys.argv[1])
w = t.writer(["J1", "J2", "J3", "J4", "J5", "J6"])
arrays = list(w.arrays.values())
k = 0
while True:
    k = (k + 1) % 1000
    for a in arrays:
        a[:] = k / 100.0
    w.write()
    if k == 1:
        print("ready", flush=True)
"""


def test_a_set_is_read_whole_while_another_process_writes_it(table, subsystem):
    """Six variables written as one set are never seen half old, half new (one lock, §5.5)."""
    child = run_python(WRITER, subsystem.name)
    try:
        assert child.stdout.readline().strip() == "ready"
        r = table.reader(["J1", "J2", "J3", "J4", "J5", "J6"])
        distinct = set()
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline:
            values = [a.copy() for a in r.read().values()]
            joined = np.concatenate(values)
            assert (joined == joined[0]).all(), "a torn set: %s" % joined
            distinct.add(float(joined[0]))
        assert len(distinct) > 10  # the writer really ran meanwhile
    finally:
        child.kill()
        child.wait()


def test_producers_follow_spawn_and_kill(table, subsystem):
    table.write("Y", 1.0, force=True)
    with pytest.raises(chimera.ProducerConflict, match="Y is produced by follow"):
        table.write("Y", 2.0)
    with subsystem.master() as m:
        m.kill("follow")
        table.write("Y", 2.0)  # nobody produces it now
        assert table.info("Y").producers == [] and table.info("X").consumers == []
        m.spawn("follow")
    with pytest.raises(chimera.ProducerConflict, match="Y is produced by follow"):
        table.write("Y", 3.0)
    assert table.read("Y").tolist() == [2.0]


def test_without_a_status_segment_the_producer_rule_refuses(tmp_path):
    """A master's table whose producers cannot be read is not written unchecked."""
    import os
    from conftest import DATA

    name = "pynostatus%d" % os.getpid()
    owner = chimera.Table.create(name, os.path.join(DATA, "py.svar"))  # a table with no master, no status
    try:
        owner.write("LIMITS", 1)  # made here: nobody can produce it
        attached = chimera.attach(name)  # as if a master's: its status names the producers
        with pytest.raises(chimera.ProducerConflict,
                           match=r"^/chimera.%s.svar: cannot tell which tasks produce LIMITS \(status of subsystem %s: .+\); "
                                 r"write\(..., force=True\) writes anyway$" % (name, name)):
            attached.write("LIMITS", 2)
        attached.write("LIMITS", 2, force=True)
        assert owner.read("LIMITS").tolist() == [2, 2, 2]
    finally:
        # The bindings leave a table's segment to its master: this one has none.
        segment = "/dev/shm" + owner.segment
        if os.path.exists(segment):
            os.remove(segment)
