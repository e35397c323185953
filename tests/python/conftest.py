"""Fixtures of the Python tests: a running subsystem whose master serves its socket.

The master is the real `sbs` program (SBS_EXE) started with --serve on a copy of
data/py.svar and the ramp test module (tests/tools/modules/ramp.cpp, found through
CHIMERA_MODULE_PATH), under a subsystem name of its own per test file.
"""

import os
import shutil
import subprocess
import sys
import time

import pytest

DATA = os.environ.get("PY_TEST_DATA", os.path.join(os.path.dirname(__file__), "data"))
TOOLS_DATA = os.path.join(os.environ.get("CHIMERA_SOURCE_ROOT", ""), "tests", "tools", "data")


class RunningSubsystem:
    def __init__(self, name, folder, script=""):
        import chimera

        self.name = name
        with open(os.path.join(folder, name + ".sbs"), "w") as f:
            f.write("SUBSYSTEM %s\nSVARFILE py.svar\nRTPU cpu0\nBACKEND other\nEOF\n" % name)
        shutil.copy(os.path.join(DATA, "py.svar"), folder)
        for rmod in ("ramp.rmod", "follow.rmod"):
            shutil.copy(os.path.join(TOOLS_DATA, rmod), folder)
        self.log = open(os.path.join(folder, "sbs.log"), "w+")
        args = [os.environ["SBS_EXE"], os.path.join(folder, name + ".sbs"), "--serve", "--no-attach",
                "--socket", os.path.join(folder, "sbs.sock")]
        if script:
            args += ["-c", script]
        self.socket = os.path.join(folder, "sbs.sock")
        self.process = subprocess.Popen(args, cwd=folder, stdout=self.log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 20
        while not os.path.exists(self.socket):
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("sbs did not start:\n" + self.output())
            time.sleep(0.02)
        self.chimera = chimera

    def master(self):
        return self.chimera.Master(socket_path=self.socket)

    def output(self):
        self.log.flush()
        self.log.seek(0)
        return self.log.read()

    def stop(self):
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
        self.log.close()


@pytest.fixture(scope="module")
def subsystem(tmp_path_factory, request):
    name = "py%s%d" % (request.module.__name__.replace("test_", "")[:6], os.getpid())
    s = RunningSubsystem(name, str(tmp_path_factory.mktemp(name)), getattr(request.module, "SBS_SCRIPT", ""))
    yield s
    s.stop()


def run_python(code, *args):
    """A child interpreter (this one) running CODE with the test's PYTHONPATH."""
    return subprocess.Popen([sys.executable, "-c", code] + [str(a) for a in args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
