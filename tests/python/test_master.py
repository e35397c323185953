"""The master as a client object over its JSON socket (issue #18.3), errors with the master's words."""

import os
import pwd
import select
import shutil
import socket
import tempfile
import time

import pytest

import chimera


def test_session_spawn_on_off_kill_and_status(subsystem):
    with subsystem.master() as m:
        assert m.subsystem == subsystem.name and m.pid == subsystem.process.pid
        data = m.spawn("ramp")
        assert data["rmod"] == "ramp" and data["state"] == "OFF"
        m.on("ramp")
        (row,) = m.status("ramp")
        assert (row["rmod"], row["state"]) == ("ramp", "ON")
        m.off("ramp")
        assert [t["state"] for t in m.status()] == ["OFF"]
        m.kill("ramp")
        assert m.status() == []


def test_refusals_raise_with_the_masters_message(subsystem):
    with subsystem.master() as m:
        with pytest.raises(chimera.MasterError) as e:
            m.on("nosuch")
        assert str(e.value) == "no task nosuch in subsystem %s (no task spawned)" % subsystem.name
        assert e.value.command == "on" and e.value.reply["ok"] is False
        m.spawn("ramp")
        with pytest.raises(chimera.MasterError, match=r"^clear refused for task ramp: it is not in ERROR \(state OFF\)$"):
            m.clear("ramp")
        m.kill("ramp")


def test_reconfig_set_get_freq_and_clear(subsystem):
    with subsystem.master() as m:
        m.spawn("ramp")
        m.spawn("follow")
        assert m.reconfig([("on", "ramp"), ("on", "follow")]) == {"applied": ["on ramp", "on follow"]}
        with pytest.raises(chimera.MasterError, match=r"^reconfig stopped at item 1 \(clear ramp\): clear refused for task ramp: "
                           r"it is not in ERROR \(state ON\) \(1 of 2 items applied\)$"):
            m.reconfig([("off", "follow"), ("clear", "ramp")])
        assert m.freq("ramp") == 200.0
        assert m.freq("ramp", 50) == 50.0 and m.freq("ramp") == 50.0
        assert m.get("ramp", "STEP") == "1"  # LOCAL values are text, as in the .rmod
        m.set("ramp", "STEP", 2.5)
        assert float(m.get("ramp", "STEP")) == 2.5
        with pytest.raises(chimera.MasterError, match="out of range"):
            m.set("ramp", "STEP", 1e9)
        m.set("ramp", "FAIL", 1)  # the next cycle fails: the task goes to ERROR
        deadline = time.monotonic() + 5
        while m.status("ramp")[0]["state"] != "ERROR":
            assert time.monotonic() < deadline
            time.sleep(0.01)
        m.set("ramp", "FAIL", 0)
        m.clear("ramp")
        assert m.status("ramp")[0]["state"] == "OFF"
        m.kill("ramp")
        m.kill("follow")


def test_events_to_an_aperiodic_server(subsystem):
    table = chimera.attach(subsystem.name)
    with subsystem.master() as m:
        m.spawn("tick")
        with pytest.raises(chimera.MasterError, match=r"^event refused for task tick: it is not ON \(state OFF\)$"):
            m.event("tick")
        m.on("tick")
        before = table.read("TICKS")[0]
        m.event("tick")
        m.event("tick", 4)
        deadline = time.monotonic() + 5
        while table.read("TICKS")[0] < before + 5:
            assert time.monotonic() < deadline, "the events were not served"
            time.sleep(0.01)
        time.sleep(0.05)
        assert table.read("TICKS")[0] == before + 5  # one cycle per event, no more
        m.spawn("ramp")
        with pytest.raises(chimera.MasterError, match=r"^event refused for task ramp: it is periodic; events go to "
                                                      r"aperiodic tasks \(TASKTYPE sporadic, deferrable or background\)$"):
            m.event("ramp")
        with pytest.raises(chimera.MasterError, match=r"^event: '0' is not a count of events \(1 to 1000\)$"):
            m.event("tick", 0)
        m.kill("ramp")
        m.kill("tick")


def test_one_peer_at_a_time(subsystem):
    with subsystem.master():
        with pytest.raises(chimera.MasterError, match="another network peer has control of subsystem " + subsystem.name):
            subsystem.master()


def test_tcp_with_a_token(tmp_path):
    import os
    import re
    import shutil
    from conftest import DATA, TOOLS_DATA

    shutil.copy(os.path.join(DATA, "py.svar"), tmp_path)
    shutil.copy(os.path.join(TOOLS_DATA, "ramp.rmod"), tmp_path)
    (tmp_path / "tcp.sbs").write_text("SUBSYSTEM pytcp%d\nSVARFILE py.svar\nRTPU cpu0\nBACKEND other\nEOF\n" % os.getpid())
    token = tmp_path / "token"
    token.write_text("s3cret\n")
    token.chmod(0o600)
    with chimera.serve(str(tmp_path / "tcp.sbs"), "spawn ramp",
                       options=["--tcp", "127.0.0.1:0", "--token-file", str(token)], token="s3cret") as sub:
        port = int(re.search(r"TCP 127.0.0.1:(\d+)", sub.output()).group(1))
        with pytest.raises(chimera.MasterError, match=r"^the master asks for a token"):
            chimera.Master(tcp=("127.0.0.1", port))
        with pytest.raises(chimera.MasterError, match="^wrong token$") as wrong:
            chimera.Master(tcp=("127.0.0.1", port), token="guess")
        # A wrong token makes this address wait before its next is judged (issue #29.3).
        time.sleep(wrong.value.reply["data"]["retry_after_ms"] / 1000)
        with chimera.Master(tcp=("127.0.0.1", port), token="s3cret") as m:
            assert m.status("ramp")[0]["state"] == "OFF"


def test_no_master_listening(tmp_path):
    with pytest.raises(chimera.MasterError, match="cannot reach the master of nobody at .*nobody.sock"):
        chimera.Master("nobody", socket_path=str(tmp_path / "nobody.sock"))


def test_a_master_that_never_answers_is_stopped_when_serve_fails(tmp_path):
    # A master that says it listens but refuses every connection: serve() must
    # raise and leave nothing running (it used to leave the process behind).
    import os
    fake = tmp_path / "fake-sbs"
    pid_file = tmp_path / "pid"
    fake.write_text('#!/bin/sh\necho $$ > %s\necho "sbs: subsystem fake listening on unix socket $5" >&2\nexec sleep 60\n'
                    % pid_file)
    fake.chmod(0o755)
    (tmp_path / "fake.sbs").write_text("SUBSYSTEM fake\nEOF\n")
    with pytest.raises(chimera.MasterError, match="cannot reach the master"):
        chimera.serve(str(tmp_path / "fake.sbs"), sbs_exe=str(fake), timeout=5)
    pid = int(pid_file.read_text())
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def _squat_socket_as_nobody(path, ready, hold):
    """In a forked child: as nobody, listen on PATH and greet every peer as a master would, until HOLD closes."""
    try:
        nobody = pwd.getpwnam("nobody")
        os.setgroups([])
        os.setresgid(nobody.pw_gid, nobody.pw_gid, nobody.pw_gid)
        os.setresuid(nobody.pw_uid, nobody.pw_uid, nobody.pw_uid)
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        listener.bind(path)
        listener.listen(4)
        os.write(ready, b"x")
        while hold not in select.select([listener, hold], [], [])[0]:
            listener.accept()[0].sendall(b'{"ok":true,"cmd":"hello","subsystem":"fake","auth":"none"}\n')
    finally:
        os._exit(0)


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root (setresuid to nobody)")
def test_a_socket_another_user_listens_on_is_refused_naming_the_user():
    """A local user may listen first on the path root's client uses (issue #29.5): refused before a word is read."""
    folder = tempfile.mkdtemp(prefix="chimera-pysquat-")
    os.chmod(folder, 0o777)  # nobody may create its socket there
    path = os.path.join(folder, "squatted.sock")
    ready_r, ready_w = os.pipe()
    hold_r, hold_w = os.pipe()
    squatter = os.fork()
    if squatter == 0:
        os.close(ready_r)
        os.close(hold_w)
        _squat_socket_as_nobody(path, ready_w, hold_r)
    os.close(ready_w)
    os.close(hold_r)
    try:
        assert os.read(ready_r, 1) == b"x"
        with pytest.raises(chimera.MasterError) as e:
            chimera.Master(socket_path=path, timeout=5)
        assert str(e.value) == (
            "socket %s is served by nobody's (uid %d) process, pid %d, not by this user's or root's: not trusted; "
            "stop that process or remove the socket (sudo rm %s), then start the master again"
            % (path, pwd.getpwnam("nobody").pw_uid, squatter, path))
    finally:
        os.close(hold_w)
        os.close(ready_r)
        os.waitpid(squatter, 0)
        shutil.rmtree(folder)
