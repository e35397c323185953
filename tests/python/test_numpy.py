"""The bindings refuse a numpy whose arrays they cannot read (issue #36).

Built with Debian's pybind11 2.10, the extension reads arrays through numpy
1.x's C structures; under numpy 2 (a virtual environment's, from PyPI) reads
returned wrong values silently. The import must fail instead, saying why.
"""

import os
import subprocess
import sys


def import_chimera_beside(numpy_folder):
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(numpy_folder), env.get("PYTHONPATH", "")])
    return subprocess.run([sys.executable, "-c", "import chimera"], env=env, capture_output=True, text=True, timeout=60)


def test_a_numpy_2_is_refused_at_import_naming_both_versions(tmp_path):
    fake = tmp_path / "numpy"
    fake.mkdir()
    (fake / "__init__.py").write_text('__version__ = "2.4.0"\n')
    r = import_chimera_beside(tmp_path)
    assert r.returncode != 0
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("ImportError: chimera: numpy 2.4.0 (%s) is imported, but chimera's bindings were built "
                           "with pybind11 2." % (fake / "__init__.py")), r.stderr
    assert "use numpy < 2" in last, r.stderr


def test_the_numpy_it_was_built_for_imports():
    r = import_chimera_beside("")
    assert r.returncode == 0, r.stderr
