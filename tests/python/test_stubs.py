"""The shipped type stubs (python/chimera/_core.pyi) name exactly what the extension has, and mypy uses them."""

import ast
import inspect
import os
import subprocess
import sys

import pytest

import chimera
from chimera import _core

HERE = os.path.dirname(os.path.abspath(__file__))
STUB = os.path.join(os.path.dirname(_core.__file__), "_core.pyi")


def stub_tree():
    with open(STUB) as f:
        return ast.parse(f.read())


def members(node):
    names = set()
    for item in node.body:
        if isinstance(item, (ast.FunctionDef, ast.ClassDef)):
            names.add(item.name)
        elif isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
            names.add(item.target.id)
    return {n for n in names if not n.startswith("_") or n in ("__contains__", "__len__")}


def test_the_stub_names_every_public_name_of_the_module_and_nothing_else():
    tree = stub_tree()
    runtime = {n for n in dir(_core) if not n.startswith("_")}
    assert members(tree) == runtime


def test_each_class_has_the_same_members_in_the_stub():
    classes = {c.name: c for c in stub_tree().body if isinstance(c, ast.ClassDef)}
    for name, node in classes.items():
        cls = getattr(_core, name)
        if issubclass(cls, BaseException):
            continue
        stub = members(node)
        for base in node.bases:  # members a stub class inherits from another stub class
            if isinstance(base, ast.Name) and base.id in classes:
                stub |= members(classes[base.id])
        runtime = {n for n, _ in inspect.getmembers(cls) if not n.startswith("_") or n in ("__contains__", "__len__")}
        assert stub == runtime, name


def mypy(path):
    env = dict(os.environ, MYPYPATH=os.path.dirname(os.path.dirname(chimera.__file__)))
    return subprocess.run([sys.executable, "-m", "mypy", "--no-incremental", "--cache-dir", os.devnull,
                           "--strict-optional", "--no-error-summary", path],
                          env=env, capture_output=True, text=True)


def test_mypy_accepts_a_typed_use_and_catches_a_wrong_one(tmp_path):
    pytest.importorskip("mypy")
    good = mypy(os.path.join(HERE, "typed_use.py"))
    assert good.returncode == 0, good.stdout + good.stderr
    bad = tmp_path / "wrong.py"
    bad.write_text("import chimera\ncount: int = chimera.attach('x').names()\nchimera.attach('x').read(5)\n")
    out = mypy(str(bad))
    assert out.returncode == 1
    assert 'Incompatible types in assignment (expression has type "list[str]", variable has type "int")' in out.stdout or \
        'Incompatible types in assignment (expression has type "List[str]", variable has type "int")' in out.stdout, out.stdout
    assert 'Argument 1 to "read" of "Table" has incompatible type "int"' in out.stdout, out.stdout
