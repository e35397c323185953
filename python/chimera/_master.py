"""The subsystem's master as a client object over its JSON socket (docs/cli.md).

A master started with ``sbs FILE.sbs --serve`` (or ``--listen`` and ``network``
at its prompt) takes one command per line and answers one JSON object per line.
Master wraps that protocol: one method per command, replies as dicts, and every
refusal raised as MasterError carrying the master's own message.
"""

from __future__ import annotations

import json
import os
import pwd
import socket
import struct
from typing import Any, Dict, Iterable, List, Optional, Sequence, Tuple, Union


class MasterError(RuntimeError):
    """A command the master refused or failed; str() is the master's message."""

    def __init__(self, command: str, message: str, reply: Dict[str, Any]):
        super().__init__(message)
        self.command = command
        self.message = message
        self.reply = reply


def default_socket_path(subsystem: str) -> str:
    """Where ``sbs --listen`` opens its socket (tools/sbs/server.cpp's default_socket_path)."""
    xdg = os.environ.get("XDG_RUNTIME_DIR", "")
    folder = xdg + "/chimera" if xdg.startswith("/") else "/tmp/chimera-%d" % os.getuid()
    return os.path.join(folder, subsystem + ".sock")


def _untrusted_master(sock: socket.socket, path: str) -> str:
    """Why not to talk to the master reached at PATH, or "" when it runs as this user or root (issue #29.5).

    Any local user may listen first on a path another user's client will use. The
    text is tools/sbs/peer_user.cpp's untrusted_master(): keep them alike.
    """
    pid, uid, _gid = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i")))
    if uid in (0, os.geteuid()):
        return ""
    try:
        user = pwd.getpwuid(uid).pw_name
    except KeyError:
        user = "uid %d" % uid
    return ("socket %s is served by %s's (uid %d) process, pid %d, not by this user's or root's: not trusted; "
            "stop that process or remove the socket (sudo rm %s), then start the master again" % (path, user, uid, pid, path))


Word = Union[str, int, float]


class Master:
    """A network peer of the master of SUBSYSTEM (Unix socket; or TCP with a token).

    Only one peer has control of a master at a time: close() (or leaving the
    ``with`` block) hands control back, and the master keeps running.
    """

    def __init__(self, subsystem: Optional[str] = None, *, socket_path: Optional[str] = None,
                 tcp: Optional[Tuple[str, int]] = None, token: Optional[str] = None,
                 timeout: float = 30.0):
        if tcp is not None:
            self._sock = socket.create_connection(tcp, timeout=timeout)
        else:
            path = socket_path or default_socket_path(_required(subsystem))
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            self._sock.settimeout(timeout)
            try:
                self._sock.connect(path)
            except OSError as e:
                self._sock.close()
                raise MasterError("hello", "cannot reach the master of %s at %s: %s (is it running with "
                                  "--listen or --serve?)" % (subsystem, path, e.strerror), {}) from None
            why = _untrusted_master(self._sock, path)
            if why:
                self._sock.close()
                raise MasterError("hello", why, {})
        self._file = self._sock.makefile("rb")
        self._next_id = 1
        self.hello = self._receive(None)
        if not self.hello.get("ok"):
            self.close()
            raise MasterError("hello", self.hello.get("error", "refused"), self.hello)
        self.subsystem: str = self.hello.get("subsystem", subsystem or "")
        self.pid: int = self.hello.get("pid", 0)
        if self.hello.get("auth") == "token":
            if token is None:
                self.close()
                raise MasterError("token", "the master asks for a token (Master(..., token=...))", self.hello)
            self.command("token " + token)

    # -- the protocol -------------------------------------------------------

    def command(self, line: str) -> Dict[str, Any]:
        """Send one command line; return the reply, or raise MasterError with the master's message."""
        request_id = self._next_id
        self._next_id += 1
        data = json.dumps({"cmd": line, "id": request_id}).encode() + b"\n"
        self._sock.sendall(data)
        reply = self._receive(request_id)
        if not reply.get("ok"):
            raise MasterError(reply.get("cmd", line.split(" ")[0]), reply.get("error", "failed"), reply)
        return reply

    def _receive(self, request_id: Optional[int]) -> Dict[str, Any]:
        while True:
            line = self._file.readline()
            if not line:
                raise MasterError("", "the master closed the connection", {})
            reply = json.loads(line)
            if request_id is None or reply.get("id") in (request_id, None):
                return reply

    def close(self) -> None:
        """Leave the session (`quit`): control goes back to the master; it runs on."""
        if self._sock is None:
            return
        try:
            self._sock.sendall(b"quit\n")
        except OSError:
            pass
        self._file.close()
        self._sock.close()
        self._sock = None  # type: ignore[assignment]

    def __enter__(self) -> "Master":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- one method per command ---------------------------------------------

    def _do(self, *words: Word) -> Dict[str, Any]:
        return self.command(" ".join(str(w) for w in words if w is not None))

    def spawn(self, rmod: Union[str, Sequence[str]], rtpu: Optional[str] = None) -> Dict[str, Any]:
        """Create a task from RMOD.rmod (a list: one combined task) on RTPU; it ends OFF."""
        name = rmod if isinstance(rmod, str) else "+".join(rmod)
        return self._do("spawn", name, rtpu).get("data", {})

    def on(self, rmod: str) -> None:
        """Turn task RMOD on (`on`); MasterError when its state or a second producer of a variable forbids it."""
        self._do("on", rmod)

    def off(self, rmod: str) -> None:
        """Turn task RMOD off (`off`); MasterError when its state forbids it."""
        self._do("off", rmod)

    def kill(self, rmod: str) -> None:
        """Destroy task RMOD (`kill`), turning it off first when it is ON."""
        self._do("kill", rmod)

    def clear(self, rmod: str) -> None:
        """Clear task RMOD out of ERROR (`clear`)."""
        self._do("clear", rmod)

    def reconfig(self, items: Iterable[Tuple[str, str]]) -> Dict[str, Any]:
        """One ordered list of (signal, rmod), verified as a whole and applied in order (§4.4.1)."""
        line = ", ".join("%s %s" % (signal, rmod) for signal, rmod in items)
        return self._do("reconfig", line).get("data", {})

    def event(self, rmod: str, count: int = 1) -> None:
        """Wake an aperiodic task (sporadic, deferrable or background server) that is ON: COUNT cycles."""
        self._do("event", rmod, int(count))

    def set(self, rmod: str, key: str, *values: Word) -> None:
        """Change a LOCAL key of a running task (checked against the module's declaration)."""
        if not values:
            raise ValueError("set(rmod, key, value...): no value")
        self._do("set", rmod, key, *values)

    def get(self, rmod: str, key: str) -> str:
        """A LOCAL key's value as the task runs with it, as text (as the .rmod writes it)."""
        return str(self._do("set", rmod, key).get("data", {}).get("value", ""))

    def freq(self, rmod: str, hz: Optional[float] = None) -> float:
        """The task's frequency in Hz; with HZ, change it first (from the next release)."""
        reply = self._do("freq", rmod, None if hz is None else repr(float(hz)))
        return float(reply.get("data", {}).get("freq", hz or 0.0))

    def status(self, rmod: Optional[str] = None) -> List[Dict[str, Any]]:
        """The tasks' status fields as the master shows them (times in µs), counted since this peer's last status."""
        return self._do("status", rmod or "all").get("data", {}).get("tasks", [])

    def setvar(self, name: str, *values: Word, force: bool = False) -> Dict[str, Any]:
        """Write state variable NAME ('Q_REF', or 'Q_REF[2]' from element 2) as `setvar` does: checked against the
        type and the .svar MIN/MAX, refused (MasterError) while a spawned task produces it unless FORCE."""
        return self._do("setvar", name, *values, "--force" if force else None).get("data", {})

    def display(self, rmod: str = "all", *names: str) -> List[Dict[str, Any]]:
        """The values, types and units (`display`) of the variables task RMOD reads and writes, or of the whole
        table for "all"; NAMES (with * and ?) pick some of them."""
        return self._do("display", rmod, *names).get("data", {}).get("vars", [])

    def sample(self, variables: Sequence[str], rate: Optional[float] = None, rtpu: Optional[str] = None,
               capacity: Optional[int] = None) -> Dict[str, Any]:
        """Start a sampler task (`sample`): VARIABLES ('Q_REF', 'Q_REF[2]', 'Q_REF[0:2]') read at RATE Hz
        (default: the fastest producer's) into a ring; returns {rmod, ring, channels, rate, capacity, rtpu}.
        ``kill(rmod)`` stops it. chimera.record() and chimera.Sampling use this."""
        words: List[Word] = list(variables)
        if rate is not None:
            words += ["--rate", repr(float(rate))]
        if rtpu is not None:
            words += ["--rtpu", rtpu]
        if capacity is not None:
            words += ["--capacity", int(capacity)]
        return self._do("sample", *words).get("data", {})

    def peer(self, name: str, pid: int, produces: Sequence[str] = (), consumes: Sequence[str] = (),
             program: Optional[str] = None) -> Dict[str, Any]:
        """Declare process PID as the peer task NAME producing and consuming those variables (`peer`);
        chimera.Peer uses this. Refused (MasterError) when another task already produces one of them."""
        words: List[Word] = ["--pid", int(pid)]
        if produces:
            words += ["--out", *produces]
        if consumes:
            words += ["--in", *consumes]
        if program:
            words += ["--program", program]
        return self._do("peer", name, *words).get("data", {})

    def finish(self) -> None:
        """Turn every task off, kill them, and end the subsystem (the master exits)."""
        try:
            self._do("finish")
        except MasterError as e:
            if "closed the connection" not in e.message:
                raise


def _required(subsystem: Optional[str]) -> str:
    if not subsystem:
        raise ValueError("Master(subsystem) or Master(socket_path=...) or Master(tcp=(host, port), token=...)")
    return subsystem
