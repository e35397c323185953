"""Fixtures of the Python tests: a running subsystem whose master serves its socket.

The master is the real `sbs` program (SBS_EXE) started by chimera.serve() on a copy
of data/py.svar and the ramp test module (tests/tools/modules/ramp.cpp, found through
CHIMERA_MODULE_PATH), under a subsystem name of its own per test file.
"""

import os
import shutil
import subprocess
import sys

import pytest

import chimera

DATA = os.environ.get("PY_TEST_DATA", os.path.join(os.path.dirname(__file__), "data"))
TOOLS_DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tools", "data")


def start_subsystem(name, folder, script=""):
    """A copy of data/py.svar and the ramp .rmod files in FOLDER, served by sbs as subsystem NAME."""
    with open(os.path.join(folder, name + ".sbs"), "w") as f:
        f.write("SUBSYSTEM %s\nSVARFILE py.svar\nRTPU cpu0\nBACKEND other\nEOF\n" % name)
    shutil.copy(os.path.join(DATA, "py.svar"), folder)
    for rmod in ("ramp.rmod", "follow.rmod"):
        shutil.copy(os.path.join(TOOLS_DATA, rmod), folder)
    shutil.copy(os.path.join(DATA, "tick.rmod"), folder)
    return chimera.serve(os.path.join(folder, name + ".sbs"), script)


@pytest.fixture(scope="module")
def subsystem(tmp_path_factory, request):
    name = "py%s%d" % (request.module.__name__.replace("test_", "")[:6], os.getpid())
    s = start_subsystem(name, str(tmp_path_factory.mktemp(name)), getattr(request.module, "SBS_SCRIPT", ""))
    yield s
    s.stop()


def run_python(code, *args):
    """A child interpreter (this one) running CODE with the test's PYTHONPATH."""
    return subprocess.Popen([sys.executable, "-c", code] + [str(a) for a in args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
