"""The web console's server side (issue 17, items 1, 2, 3, 6, 7) against the
running Fig 3.7 demo: the token rules of --tcp, Host and Origin checks, one
controller at a time, read-only watchers, bad requests answered with an error
while the server keeps serving, the port graph pushed on every change and its
§3.3.1 marks worded exactly as verification words them."""

import subprocess
import time

import pytest

from webharness import SBS, Master, Refused, Socket, http_get, TOKEN


@pytest.fixture(scope="module")
def master():
    m = Master("p")
    yield m
    assert m.close() == 0, m.proc.stderr.read()


def page(master):
    s = Socket(master.port)
    assert s.hello["ok"] and s.hello["auth"] == "token", s.hello
    assert s.authenticate()["ok"]
    return s


def test_http_needs_a_token_like_tcp(tmp_path):
    r = subprocess.run([SBS, "nosuch.sbs", "--http", "0"], capture_output=True, text=True)
    assert r.returncode == 2
    r = subprocess.run([SBS, __file__, "--http", "127.0.0.1:0", "--serve"], capture_output=True, text=True)
    assert r.returncode == 2 and "--http needs --token" in r.stderr


def test_page_and_assets_served_with_a_strict_policy(master):
    status, head, body = http_get(master.port, "/")
    assert status == 200 and b"console.js" in body
    assert "Content-Security-Policy: default-src 'self'" in head and "X-Frame-Options: DENY" in head
    for path in ("/console.js", "/console.css"):
        assert http_get(master.port, path)[0] == 200
    assert http_get(master.port, "/../../etc/passwd")[0] in (400, 404)
    assert http_get(master.port, "/nosuch")[0] == 404


def test_host_header_of_another_name_is_refused(master):
    # DNS rebinding: evil.example resolving to 127.0.0.1 sends its own name.
    status, _, body = http_get(master.port, "/", host="evil.example:%d" % master.port)
    assert status == 403 and b"DNS rebinding" in body
    with pytest.raises(Refused):
        Socket(master.port, host="evil.example:%d" % master.port)
    assert http_get(master.port, "/", host="localhost:%d" % master.port)[0] == 200


def test_cross_site_websocket_is_refused(master):
    with pytest.raises(Refused):
        Socket(master.port, origin="http://evil.example")
    with pytest.raises(Refused):
        Socket(master.port, origin="http://127.0.0.1:1")  # another port is another origin
    s = Socket(master.port, origin=None)  # not a browser: no Origin, the token still required
    assert s.authenticate()["ok"]


def test_wrong_or_missing_token_closes_the_socket(master):
    s = Socket(master.port)
    r = s.authenticate("wrong")
    assert not r["ok"] and r["error"] == "wrong token"
    assert s.closed()
    s = Socket(master.port)
    s.send("status")
    r = s.recv()
    assert not r["ok"] and "authenticate first" in r["error"]
    assert s.closed()
    # Still serving.
    assert page(master).request("status all")["ok"]


def test_watchers_are_read_only(master):
    s = page(master)
    r = s.request("off jpid")
    assert not r["ok"] and "read-only" in r["error"]
    for cmd in ("status all", "display jpid", "show svar", "show rtpu", "module", "set jpid", "help"):
        assert s.request(cmd)["ok"], cmd
    for cmd in ("set jpid KP 1", "setvar Q_REF 0", "status reset", "spawn jpid", "reconfig off jpid"):
        r = s.request(cmd)
        assert not r["ok"] and "read-only" in r["error"], cmd


def test_one_controller_at_a_time(master):
    a, b = page(master), page(master)
    assert a.request("control")["ok"]
    r = b.request("control")
    assert not r["ok"] and "another network peer has control" in r["error"]
    # The Unix socket's peer is refused too: one slot for all interfaces.
    r = master.command_line("status")
    assert r.returncode != 0 and "another network peer has control" in r.stderr
    assert a.request("release")["ok"]
    assert b.request("control")["ok"]
    b.sock.close()  # a lost page gives control back
    c = page(master)
    for _ in range(50):
        if c.request("control")["ok"]:
            break
        time.sleep(0.1)
    else:
        pytest.fail("control not returned after the page was lost")
    c.request("release")


def test_bad_requests_get_an_error_and_the_server_serves_on(master):
    s = page(master)
    s.send("{not json")
    assert "malformed JSON" in s.recv()["error"]
    s.send('{"cmd": 7}')
    assert "string member" in s.recv()["error"]
    s.send("status\x01")
    assert "control characters" in s.recv()["error"]
    s.send("x" * 5000)
    assert "longer than 4096" in s.recv()["error"]
    s.send_frame(b"\x00\x01", opcode=2)
    assert "text messages only" in s.recv()["error"]
    s.send("nosuchcommand")
    assert not s.recv()["ok"]
    assert s.request("status all")["ok"]
    assert page(master).request("status all")["ok"]


def graph_state(data, rmod):
    return next(t["state"] for t in data["tasks"] if t["rmod"] == rmod)


def test_graph_pushed_on_every_change_whoever_made_it(master):
    watcher = page(master)
    first = watcher.stream("graph")
    assert {t["rmod"] for t in first["tasks"]} == {"puma_torque", "jtraj", "jpid", "grav_comp", "jpidg"}
    assert first["problems"] == []
    # From the command line (attached over the Unix socket), not from a page.
    r = master.command_line("off jpid")
    assert r.returncode == 0, r.stderr
    assert watcher.stream("graph", until=lambda d: graph_state(d, "jpid") == "OFF")
    r = master.command_line("on jpid")
    assert r.returncode == 0, r.stderr
    assert watcher.stream("graph", until=lambda d: graph_state(d, "jpid") == "ON")


def test_refused_reconfig_shown_before_anything_changes(master):
    s = page(master)
    r = s.request("reconfig --check on jpidg")
    assert not r["ok"] and "T_REF is produced by both jpid and jpidg" in r["error"]
    assert r["data"]["problems"][0]["kind"] == "two_producers"
    assert graph_state(s.request("show graph")["data"], "jpidg") == "OFF"
    ok = s.request("reconfig --check off jpid, on jpidg")
    assert ok["ok"] and ok["data"]["verifies"], ok


def test_problem_marks_worded_as_verification_words_them(master):
    s = page(master)
    assert s.request("control")["ok"]
    try:
        refusal = s.request("reconfig off jtraj")["error"]  # verification refuses: nothing happens
        assert graph_state(s.request("show graph")["data"], "jtraj") == "ON"
        assert s.request("off jtraj")["ok"]  # a lone `off` is not verified (§3.3.1 is for reconfig)
        g = s.request("show graph")["data"]
        marks = [p for p in g["problems"] if p["kind"] == "no_producer"]
        assert marks and marks[0]["var"] == "Q_REF" and marks[0]["tasks"] == ["jpid"]
        assert marks[0]["message"] in refusal
    finally:
        s.request("on jtraj")
        s.request("release")
    assert s.request("show graph")["data"]["problems"] == []


def test_local_keys_and_variable_writes_checked_as_the_command_line(master):
    s = page(master)
    assert s.request("control")["ok"]
    try:
        r = s.request("set jpid KD -5")
        assert not r["ok"] and "out of range" in r["error"]
        r = s.request("setvar Q_REF 0")
        assert not r["ok"] and "jtraj" in r["error"]  # produced by a task: refused without --force
        assert s.request("set jpid KP 400 800 400 40 40 20")["ok"]  # the .rmod's own gains
        assert s.request("set jpid")["data"]["local"]["KP"].split()[:2] == ["400", "800"]
    finally:
        s.request("release")


def test_a_silent_socket_is_closed_at_the_auth_timeout(master):
    s = Socket(master.port)
    assert s.hello["auth_timeout_ms"] == 5000
    s.sock.settimeout(30)
    r = s.recv()
    assert not r["ok"] and r["cmd"] == "token" and "no token within 5000 ms" in r["error"]
    assert s.closed()
    assert page(master).request("status all")["ok"]
