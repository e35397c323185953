"""Start a subsystem's master (`sbs FILE.sbs --serve`) from Python and talk to it.

For scripts, examples and tests that bring their own subsystem up:

    with chimera.serve("examples/fig3_7_pid/fig3_7.sbs", script="spawn jpid") as sub:
        table = chimera.attach(sub.name)
        with sub.master() as m:
            m.on("jpid")

The master is the real `sbs` program (SBS_EXE, else `sbs` on PATH) in a process
of its own: its tasks run on their RTPUs' threads there, never in Python.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import time
from typing import List, Optional, Sequence

from ._master import Master


class ServedSubsystem:
    """A master process serving its socket; stop() (or the with block's end) finishes it."""

    def __init__(self, sbs_file: str, script: str = "", *, sbs_exe: Optional[str] = None,
                 module_path: Sequence[str] = (), options: Sequence[str] = (), token: Optional[str] = None,
                 timeout: float = 20.0):
        self._token = token  # the master's token (--token-file in OPTIONS): it asks every peer for it
        exe = sbs_exe or os.environ.get("SBS_EXE") or shutil.which("sbs")
        if not exe:
            raise FileNotFoundError("no sbs program: set SBS_EXE or put sbs on PATH (meson install, or build/tools/sbs)")
        if os.sep in exe:
            exe = os.path.abspath(exe)
        self._folder = tempfile.mkdtemp(prefix="chimera-serve-")
        self.socket = os.path.join(self._folder, "sbs.sock")
        self._log = open(os.path.join(self._folder, "sbs.log"), "w+")
        args: List[str] = [exe, sbs_file, "--serve", "--no-attach", "--socket", self.socket]
        for folder in module_path:
            args += ["--module-path", os.path.abspath(folder)]
        args += list(options)  # more of sbs's options, e.g. ["--tcp", "127.0.0.1:0", "--token-file", F]
        if script:
            args += ["-c", script]
        # The master runs in the .sbs's folder: relative module folders are made absolute first.
        env = dict(os.environ)
        if env.get("CHIMERA_MODULE_PATH"):
            env["CHIMERA_MODULE_PATH"] = ":".join(os.path.abspath(p) for p in env["CHIMERA_MODULE_PATH"].split(":") if p)
        self.process = subprocess.Popen(args, stdout=self._log, stderr=subprocess.STDOUT, env=env,
                                        cwd=os.path.dirname(os.path.abspath(sbs_file)))
        try:
            self._wait_until_listening(sbs_file, timeout)
            with self.master() as m:
                self.name: str = m.subsystem
        except BaseException:
            self.stop()  # never leave a master running (holding its segments) behind a failed start
            raise

    def _wait_until_listening(self, sbs_file: str, timeout: float) -> None:
        """Until sbs says it listens: printed once every socket it opens accepts (TCP included)."""
        deadline = time.monotonic() + timeout
        while " listening on " not in self.output():
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("sbs %s did not start:\n%s" % (sbs_file, self.output()))
            time.sleep(0.02)

    def master(self) -> Master:
        """A client of this master (one at a time has control)."""
        return Master(socket_path=self.socket, token=self._token)

    def output(self) -> str:
        """What the master printed so far."""
        self._log.flush()
        with open(self._log.name) as f:
            return f.read()

    def stop(self) -> None:
        """`finish` (every task off and killed, segments removed); terminate if it does not answer."""
        if self.process.poll() is None:
            try:
                with self.master() as m:
                    m.finish()
            except Exception:
                self.process.terminate()
            try:
                self.process.wait(10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        if not self._log.closed:
            self._log.close()
            shutil.rmtree(self._folder, ignore_errors=True)

    def __enter__(self) -> "ServedSubsystem":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def serve(sbs_file: str, script: str = "", **options) -> ServedSubsystem:
    """Start `sbs SBS_FILE --serve -c SCRIPT` and wait until its socket answers."""
    return ServedSubsystem(sbs_file, script, **options)
