"""Test harness of the web console (issue 17): starts `sbs --http` on the
Fig 3.7 demo subsystem (a name of its own per test run: subsystem names are
machine-wide) and speaks WebSocket to it with a minimal client (RFC 6455:
handshake, masked text frames), so the tests control the Host and Origin
headers a browser would not let them forge."""

import base64
import json
import os
import re
import shutil
import socket
import struct
import subprocess
import tempfile
import time

SBS = os.environ.get("SBS_EXE", "sbs")
FIG3_7 = os.path.abspath(os.environ.get("FIG3_7_DIR", "."))
TOKEN = "web-test-token-%d" % os.getpid()

TASKS = """
TASK puma_torque robot ON
TASK jtraj ctrl ON
TASK jpid ctrl ON
TASK grav_comp ctrl ON
TASK jpidg ctrl
"""


class Master:
    """`sbs DEMO.sbs --http 127.0.0.1:0 --token-file F --serve`, Fig 3.7's
    five tasks spawned from TASK lines (jpidg OFF, the others ON)."""

    def __init__(self, tag, extra=()):
        self.dir = tempfile.mkdtemp(prefix="chimera-web-")
        self.name = "web%s%d" % (tag, os.getpid())
        src = open(os.path.join(FIG3_7, "fig3_7.sbs")).read()
        src = src.replace("SUBSYSTEM fig3_7", "SUBSYSTEM " + self.name)
        src = src.replace("SVARFILE  fig3_7.svar", "SVARFILE  " + os.path.join(FIG3_7, "fig3_7.svar"))
        src = re.sub(r"(?m)^RTPU\s+(\w+)\s+\d+", lambda m: "RTPU      %s %d" % (m.group(1), allowed_cpu(m.group(1))), src)
        self.sbs = os.path.join(self.dir, self.name + ".sbs")
        with open(self.sbs, "w") as f:
            f.write(src.replace("EOF", TASKS + "EOF") if "EOF" in src else src + TASKS)
        self.token_file = os.path.join(self.dir, "token")
        with open(self.token_file, "w") as f:
            f.write(TOKEN + "\n")
        os.chmod(self.token_file, 0o600)
        env = dict(os.environ, XDG_RUNTIME_DIR=self.dir)
        os.chmod(self.dir, 0o700)
        self.env = env
        self.proc = subprocess.Popen([SBS, self.sbs, "--http", "127.0.0.1:0", "--token-file", self.token_file,
                                      "--serve", "--no-attach", *extra],
                                     stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, env=env)
        self.port = None
        deadline = time.time() + 60
        self.stderr = ""
        while time.time() < deadline:
            line = self.proc.stderr.readline()
            if not line:
                break
            self.stderr += line
            m = re.search(r"web console of subsystem \S+ on http://127\.0\.0\.1:(\d+)/", line)
            if m:
                self.port = int(m.group(1))
                break
        if self.port is None:
            self.proc.kill()
            out, err = self.proc.communicate()
            raise RuntimeError("sbs --http did not start: " + self.stderr + err + out)

    @property
    def url(self):
        return "http://127.0.0.1:%d/" % self.port

    def command_line(self, script):
        """`sbs FILE.sbs -c SCRIPT` run beside the master: it attaches over the
        master's Unix socket, as an engineer at another terminal would."""
        return subprocess.run([SBS, self.sbs, "-c", script], capture_output=True, text=True, env=self.env, timeout=60)

    def close(self):
        if self.proc.poll() is None:
            try:
                s = Socket(self.port)
                s.authenticate()
                s.request("control")
                s.request("finish")
            except Exception:
                pass
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        shutil.rmtree(self.dir, ignore_errors=True)  # the .sbs, the token, the master's socket
        return self.proc.returncode


def allowed_cpu(rtpu):
    cpus = sorted(os.sched_getaffinity(0))
    return cpus[0] if rtpu == "ctrl" or len(cpus) == 1 else cpus[1]


class Refused(Exception):
    pass


class Socket:
    """One WebSocket to the master: send(text), recv() -> dict."""

    def __init__(self, port, host=None, origin="same", path="/ws"):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        host = host or "127.0.0.1:%d" % port
        key = base64.b64encode(os.urandom(16)).decode()
        lines = ["GET %s HTTP/1.1" % path, "Host: " + host, "Upgrade: websocket", "Connection: Upgrade",
                 "Sec-WebSocket-Key: " + key, "Sec-WebSocket-Version: 13"]
        if origin == "same":
            lines.append("Origin: http://" + host)
        elif origin:
            lines.append("Origin: " + origin)
        self.sock.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(1)
            if not chunk:
                raise Refused("closed during the handshake: " + head.decode(errors="replace"))
            head += chunk
        if not head.startswith(b"HTTP/1.1 101"):
            raise Refused(head.decode(errors="replace"))
        self.buffer = b""
        self.id = 0
        self.scope_backlog = []  # scope batches that came while a request waited for its reply
        self.hello = self.recv()

    def _read(self, n):
        while len(self.buffer) < n:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("connection closed")
            self.buffer += chunk
        out, self.buffer = self.buffer[:n], self.buffer[n:]
        return out

    def send_frame(self, payload, opcode=1, fin=True):
        header = bytes([(0x80 if fin else 0) | opcode])
        n = len(payload)
        if n < 126:
            header += bytes([0x80 | n])
        elif n < 65536:
            header += bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            header += bytes([0x80 | 127]) + struct.pack(">Q", n)
        mask = os.urandom(4)
        self.sock.sendall(header + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload)))

    def send(self, text):
        self.send_frame(text.encode())

    def recv_frame(self):
        b0, b1 = self._read(2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", self._read(2))[0]
        elif n == 127:
            n = struct.unpack(">Q", self._read(8))[0]
        return b0 & 0x0F, self._read(n)

    def recv(self, skip_streams=True):
        """The next message (a reply or, unless skipped, a stream); raises
        ConnectionError when the server closed the socket. Scope batches a
        request skipped come first: a test counting samples sees them all."""
        if not skip_streams and self.scope_backlog:
            return self.scope_backlog.pop(0)
        while True:
            op, data = self.recv_frame()
            if op == 8:
                raise ConnectionError("closed by the server")
            if op != 1:
                continue
            m = json.loads(data)
            if skip_streams and "stream" in m:
                if m["stream"] == "scope":
                    self.scope_backlog.append(m)
                continue
            return m

    def stream(self, name, timeout=10, until=lambda d: True):
        deadline = time.time() + timeout
        self.sock.settimeout(timeout)
        while time.time() < deadline:
            m = self.recv(skip_streams=False)
            if m.get("stream") == name and until(m["data"]):
                return m["data"]
        raise TimeoutError("no %s stream matching" % name)

    def request(self, cmd):
        self.id += 1
        self.send(json.dumps({"cmd": cmd, "id": self.id}))
        while True:
            m = self.recv()
            if m.get("id") == self.id:
                return m

    def authenticate(self, token=TOKEN):
        self.send("token " + token)
        return self.recv()

    def closed(self):
        """True when the server has closed this socket (close frame or EOF)."""
        try:
            self.sock.settimeout(10)
            while True:
                op, _ = self.recv_frame()
                if op == 8:
                    return True
        except (ConnectionError, OSError):
            return True


def http_get(port, path="/", host=None):
    s = socket.create_connection(("127.0.0.1", port), timeout=10)
    s.sendall(("GET %s HTTP/1.1\r\nHost: %s\r\nConnection: close\r\n\r\n" %
               (path, host or "127.0.0.1:%d" % port)).encode())
    data = b""
    while True:
        chunk = s.recv(65536)
        if not chunk:
            break
        data += chunk
    s.close()
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split()[1]), head.decode(errors="replace"), body
