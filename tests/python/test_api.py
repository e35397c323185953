"""The package's face (issue #35.8): chimera.__version__ is the project's, every public name says what
it is under help(), and dir(chimera) shows the API (__all__) and nothing of its insides."""

import inspect
import os
import re

import chimera

SOURCE_ROOT = os.environ.get("CHIMERA_SOURCE_ROOT", os.path.join(os.path.dirname(__file__), "..", ".."))

# pybind11 starts every function's __doc__ with its signature ("read(self: ...) -> dict"), so a
# function bound without a docstring still has a non-empty __doc__: what follows the signature counts.
_SIGNATURE = re.compile(r"^\w+\(.*\)( -> .*)?$")


def own_doc(obj):
    """OBJ's own docstring without pybind11's signature line ("" when there is none); never a base class's."""
    lines = (getattr(obj, "__doc__", None) or "").strip().splitlines()
    if lines and _SIGNATURE.match(lines[0]):
        lines = lines[1:]
    return "\n".join(lines).strip()


def public_api():
    """(label, object) for every name of __all__ and every public member of each class among them."""
    for name in chimera.__all__:
        obj = getattr(chimera, name)
        if inspect.isclass(obj) or callable(obj):
            yield name, obj
        if inspect.isclass(obj):
            for member, value in vars(obj).items():  # the class's own: a base's members are the base's
                if not member.startswith("_"):
                    yield name + "." + member, value


def test_version_is_the_one_meson_build_declares():
    with open(os.path.join(SOURCE_ROOT, "meson.build")) as f:
        declared = re.search(r"project\([^)]*?version\s*:\s*'([^']+)'", f.read()).group(1)
    assert chimera.__version__ == declared


def test_every_public_name_and_member_has_a_docstring():
    missing = [label for label, obj in public_api() if not own_doc(obj)]
    assert not missing, "%d without a docstring: %s" % (len(missing), " ".join(missing))


def test_constants_are_described_in_the_package_docstring():
    # A list or a string cannot carry a docstring of its own: help(chimera) names them.
    for name in chimera.__all__:
        obj = getattr(chimera, name)
        if not (inspect.isclass(obj) or callable(obj)):
            assert name in chimera.__doc__, name


def test_dir_shows_the_api_and_nothing_else():
    assert len(chimera.__all__) == len(set(chimera.__all__))
    public = {n for n in dir(chimera) if not n.startswith("_")}
    assert public == set(chimera.__all__), "not in __all__: %s; missing: %s" % (
        " ".join(sorted(public - set(chimera.__all__))), " ".join(sorted(set(chimera.__all__) - public)))

