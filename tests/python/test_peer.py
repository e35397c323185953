"""A Python program as a peer of the master (issue #18.5), like a HAL user-space component: its
declared outputs count as produced for the §3.3.1 verification, a second producer is refused naming
both, status lists it as a background task, and a peer killed -9 goes to ERROR."""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import chimera

SBS_SCRIPT = "spawn ramp; on ramp"  # X, which the peers consume, has a producer

# echo: the ramp module reading Y (which only the peer produces) into TICKS, GAIN x Y.
ECHO_RMOD = """MODULE ramp
DESC echo of the peer's output
SVARALIAS X=TICKS
INVAR Y
OUTVAR X
TASKTYPE periodic
FREQ 100
EOF
"""


@pytest.fixture(scope="module")
def echo(subsystem):
    folder = os.path.dirname(subsystem.process.args[1])
    with open(os.path.join(folder, "echo.rmod"), "w") as f:
        f.write(ECHO_RMOD)
    return "echo"


def row(m, rmod):
    return next((t for t in m.status() if t["rmod"] == rmod), None)


def wait_until(condition, seconds=5.0):
    deadline = time.monotonic() + seconds
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.01)
    return condition()


def test_an_input_with_no_other_producer_is_satisfied_by_the_peer(subsystem, echo):
    table = chimera.attach(subsystem.name)
    with subsystem.master() as m:
        m.spawn(echo)
        # The whole §3.3.1 check (reconfig): an input nobody produces is refused...
        with pytest.raises(chimera.MasterError, match="variable Y read by echo is produced by no module"):
            m.reconfig([("on", echo)])
        with chimera.Peer("vision", produces=["Y"], consumes=["X"], master=m) as p:
            vision = row(m, "vision")
            assert (vision["S"], vision["state"], vision["module"]) == ("B", "ON", "peer")
            assert m.command("show svar Y")["data"]["vars"][0]["producers"] == ["vision"]
            m.reconfig([("on", echo)])  # ...and with the peer, it is produced
            for k in range(1, 4):
                p.write(Y=float(k))
                assert wait_until(lambda: table.read("TICKS")[0] == 2.0 * k), "echo reads what the peer wrote"
            # The runtime never copies a peer's ports: Y stays what the peer wrote.
            time.sleep(0.05)
            assert table.read("Y")[0] == 3.0
            with pytest.raises(chimera.ProducerConflict, match="Y is produced by vision"):
                table.write("Y", 7.0)
            m.off(echo)
        assert row(m, "vision") is None, "close() removes the peer task"
        m.kill(echo)


KILLED_CHILD = """
import sys, chimera
p = chimera.Peer(sys.argv[3], produces=[sys.argv[4]], subsystem=sys.argv[1], socket_path=sys.argv[2]).start()
print("started", flush=True)
for cycle in p.run(hz=50):
    p.write({sys.argv[4]: [cycle] * 6})
"""


def start_peer(subsystem, name, produces):
    """A peer process NAME producing PRODUCES, started."""
    child = subprocess.Popen([sys.executable, "-c", KILLED_CHILD, subsystem.name, subsystem.socket, name, produces],
                             stdout=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == "started"
    return child


def kill_9(subsystem, child, name):
    """CHILD killed -9; the master has seen its task NAME go to ERROR."""
    child.send_signal(signal.SIGKILL)
    child.wait(10)
    with subsystem.master() as m:
        assert row(m, name)["state"] == "ERROR"  # the master checks its peers before every command


def illegal(m):
    return m.command("show graph")["data"]["illegal_configuration"]


def test_a_dead_peer_makes_the_configuration_illegal_only_while_an_on_task_reads_it(subsystem, echo):
    # An observer's death must not hold the robot (tests/safety: the arm held,
    # its PID winding up, then let go at its torque limit).
    kill_9(subsystem, start_peer(subsystem, "observer", "J3"), "observer")  # J3: read by no task
    with subsystem.master() as m:
        assert not illegal(m)
        m.kill("observer")
    feeder = start_peer(subsystem, "feeder", "Y")
    with subsystem.master() as m:
        m.spawn(echo)
        m.reconfig([("on", echo)])  # echo reads Y
        assert not illegal(m)
    kill_9(subsystem, feeder, "feeder")
    with subsystem.master() as m:
        assert illegal(m), "echo reads what the dead peer produced"
        m.off(echo)
        assert not illegal(m), "nobody reads it any more"
        m.on(echo)
        assert illegal(m), "a reader turned on again"
        m.off(echo)
        m.kill(echo)
        m.kill("feeder")
        assert not illegal(m)

def test_two_producers_are_refused_naming_both(subsystem):
    with subsystem.master() as m:
        with chimera.Peer("first", produces=["Y"], master=m):
            with pytest.raises(chimera.MasterError,
                               match="^on second refused: variable Y is already produced by first, which is ON$"):
                chimera.Peer("second", produces=["Y"], master=m).start()
            assert row(m, "second") is None, "a refused peer leaves no task"
            m.spawn("follow")  # follow produces Y too
            with pytest.raises(chimera.MasterError, match="variable Y is already produced by first"):
                m.on("follow")
            with pytest.raises(chimera.MasterError, match="variable Y is produced by both first and follow"):
                m.reconfig([("on", "follow")])
            m.kill("follow")


def test_the_loop_reads_the_consumed_set_and_writes_the_produced_one(subsystem):
    with subsystem.master() as m:
        with chimera.Peer("loop", produces=["J1", "J2"], consumes=["X", "LIMITS"], master=m) as p:
            seen = []
            for cycle in p.run(hz=100, cycles=5):
                inputs = p.read()
                assert set(inputs) == {"X", "LIMITS"}
                seen.append(float(inputs["X"][0]))
                p.outputs["J1"][:] = cycle
                p.write(J2=np.full(6, 2.0 * cycle))
            assert p.cycles == 5 and seen == sorted(seen)
            table = chimera.attach(subsystem.name)
            assert np.array_equal(table.read("J1"), np.full(6, 4.0, np.float32))
            assert np.array_equal(table.read("J2"), np.full(6, 8.0, np.float32))
            with pytest.raises(ValueError, match="Peer loop does not produce X"):
                p.write(X=1.0)


PEER_CHILD = """
import sys, time, chimera
p = chimera.Peer("doomed", produces=["J3"], subsystem=sys.argv[1], socket_path=sys.argv[2]).start()
print("started", flush=True)
for cycle in p.run(hz=50):
    p.write(J3=[cycle] * 6)
"""


def test_a_peer_killed_9_goes_to_error_and_stops_producing(subsystem):
    child = subprocess.Popen([sys.executable, "-c", PEER_CHILD, subsystem.name, subsystem.socket],
                             stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "started"
        with subsystem.master() as m:
            assert row(m, "doomed")["state"] == "ON"
        child.send_signal(signal.SIGKILL)
        child.wait(10)
        with subsystem.master() as m:
            doomed = row(m, "doomed")  # the master checks its peers before every command
            assert doomed["state"] == "ERROR"
            assert "peer process %d is gone" % child.pid in doomed["error"]
            # No longer a producer: another may take J3 over.
            with chimera.Peer("heir", produces=["J3"], master=m):
                assert row(m, "heir")["state"] == "ON"
            m.kill("doomed")
    finally:
        if child.poll() is None:
            child.kill()
