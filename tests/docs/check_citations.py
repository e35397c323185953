#!/usr/bin/env python3
"""Every repository path and every document section that a comment cites exists
(issue #31 item 4).

  check_citations.py SOURCE_ROOT

What is scanned: the files git tracks (every file under SOURCE_ROOT but .git/
and build*/ when it is no git work tree), and in them only the comment text:
  - C and C++ (.c .cc .cpp .h .hpp .ipp .pyi .idl): `//` comments and `/* */`
    blocks;
  - Python (.py): `#` comments and the text of the triple-quoted strings
    that begin a line (the docstrings);
  - shell (.sh), meson (meson.build, meson_options.txt), the configuration
    files (.sbs .svar .rmod .iod .spp .tasks .cfg), YAML and CI files: `#`
    comments;
  - Markdown (.md): all of it, code blocks included.

What counts as a cited path: a word that starts with one of the tree's
top-level folders (abi/, bench/, docs/, examples/, ...: the folders of
SOURCE_ROOT but .git and build*) or is one of its top-level files
(README.md, meson.build, meson_options.txt), not preceded by a letter, digit,
`.`, `/`, `$`, `<`, `-` or `~` (so /dev/shm/..., /work/src/..., ../src,
build/src/..., $HOME/docs/... and a build-tree path are not taken), and made of
letters, digits and `_ . - / + @`. Trailing punctuation (`.,;:)'`) is not part
of it. It must name a file or a folder of the source tree.
Not checked, because they name no one file: a path with a placeholder or a
glob in it (`<`, `>`, `*`, `?`, `{`, `…`, `%`, `$`, `[`, a `...`, or a part
in capitals only or ending in one, as fuzz/corpus/NAME/, modules/NAME or
fuzz/fuzz_NAME.cpp). A path with no
extension may name a program: it is taken when a file of that stem is in its
folder (fuzz/fuzz_sbs: fuzz/fuzz_sbs.cpp) or its folder's meson.build quotes
the name (bench/svar/svar_hot_path_check, a target). An example path is
checked like any other: an example must exist too.

What counts as a cited section: `docs/<name>.md §N` (also `§N.M`, and further
`, §M` / ` and §M` / `-§M` right after it) cites the heading numbered N in that
document, a Markdown heading line `#... N. Title` or `#... N.M Title`.
A `§` that does not follow a docs/ path is the thesis's section, not checked,
except after the word ARCHITECTURE: the design brief that name meant is no
file of the tree, and such a citation is reported (cite docs/architecture.md).

Each failure is printed as FILE:LINE: what is missing; the exit status is 1
when there is any.
"""
import os
import re
import subprocess
import sys

src = os.path.abspath(sys.argv[1] if len(sys.argv) > 1 else os.path.join(os.path.dirname(__file__), "..", ".."))

C_LIKE = {".c", ".cc", ".cpp", ".h", ".hpp", ".ipp", ".pyi", ".idl"}
HASH = {".sh", ".sbs", ".svar", ".rmod", ".iod", ".spp", ".tasks", ".cfg", ".yml", ".yaml", ".toml", ".txt"}
HASH_NAMES = {"meson.build", "meson_options.txt", ".gitignore"}


def tracked_files():
    try:
        out = subprocess.run(["git", "-C", src, "ls-files", "-z"], check=True, capture_output=True).stdout
        files = [f for f in out.decode().split("\0") if f]
        if files:
            return sorted(f for f in files if os.path.isfile(os.path.join(src, f)))
    except (OSError, subprocess.CalledProcessError):
        pass
    files = []
    for root, dirs, names in os.walk(src):
        dirs[:] = [d for d in dirs if d != ".git" and not (root == src and d.startswith("build"))]
        files += [os.path.relpath(os.path.join(root, n), src) for n in names]
    return sorted(files)


def c_comments(lines):
    """(line number, comment text) of // and /* */ comments, string literals skipped."""
    in_block = False
    for n, line in enumerate(lines, 1):
        i, text, in_str = 0, [], None
        while i < len(line):
            if in_block:
                end = line.find("*/", i)
                if end < 0:
                    text.append(line[i:])
                    break
                text.append(line[i:end])
                i, in_block = end + 2, False
                continue
            c = line[i]
            if in_str:
                if c == "\\":
                    i += 2
                    continue
                if c == in_str:
                    in_str = None
            elif c in "\"'":
                # A digit separator (1'000'000) or a char literal; R"(...)" is rare enough.
                if c == "'" and i > 0 and line[i - 1].isalnum():
                    pass
                else:
                    in_str = c
            elif line.startswith("//", i):
                text.append(line[i + 2:])
                break
            elif line.startswith("/*", i):
                in_block = True
                i += 2
                continue
            i += 1
        if text:
            yield n, " ".join(text)


def hash_comments(lines, docstrings=False):
    """(line number, text) of # comments (and, for Python, triple-quoted strings)."""
    in_doc = None
    for n, line in enumerate(lines, 1):
        if in_doc:
            end = line.find(in_doc)
            if end < 0:
                yield n, line
                continue
            yield n, line[:end]
            line, in_doc = line[end + 3:], None
        if docstrings:
            m = re.match(r'\s*[rRbBuUfF]?("""|\'\'\')', line)
            if m:
                q = m.group(1)
                rest = line[m.end():]
                end = rest.find(q)
                if end < 0:
                    in_doc = q
                    yield n, rest
                    continue
                yield n, rest[:end]
                line = line[:m.start()] + rest[end + 3:]
        # A # that starts a comment: at the line's start or after whitespace, outside quotes.
        in_str = None
        for i, c in enumerate(line):
            if in_str:
                if c == in_str:
                    in_str = None
            elif c in "\"'":
                in_str = c
            elif c == "#" and (i == 0 or line[i - 1].isspace()):
                yield n, line[i + 1:]
                break


def comment_text(rel, lines):
    base = os.path.basename(rel)
    ext = os.path.splitext(rel)[1]
    if ext in C_LIKE:
        return c_comments(lines)
    if ext == ".py" or (lines and lines[0].startswith("#!") and "python" in lines[0]):
        return hash_comments(lines, docstrings=True)
    if ext in HASH or base in HASH_NAMES or (lines and lines[0].startswith("#!")):
        return hash_comments(lines)
    if ext == ".md":
        return enumerate(lines, 1)
    return iter(())


TOP = sorted(e for e in os.listdir(src) if e != ".git" and not e.startswith("build") and not e.startswith("."))
TOP_DIRS = [e for e in TOP if os.path.isdir(os.path.join(src, e))]
TOP_FILES = [e for e in TOP if os.path.isfile(os.path.join(src, e))]
PATH_RE = re.compile(r"(?<![\w./$<~-])((?:%s)/[\w.+@/<>*?{}…%%$\[\]-]*|(?:%s)(?![\w/]))" % (
    "|".join(re.escape(d) for d in TOP_DIRS), "|".join(re.escape(f) for f in TOP_FILES)))
SECTION_RE = re.compile(r"\s*§\s*(\d+(?:\.\d+)*)")
MORE_SECTIONS_RE = re.compile(r"(?:\s*,\s*|\s+and\s+|\s*[-–]\s*)§\s*(\d+(?:\.\d+)*)")
HEADING_RE = re.compile(r"^#{1,6}\s+(\d+(?:\.\d+)*)\.?\s")

_sections = {}


def sections_of(doc):
    if doc not in _sections:
        found = set()
        with open(os.path.join(src, doc), encoding="utf-8", errors="replace") as f:
            in_code = False
            for line in f:
                if line.startswith("```"):
                    in_code = not in_code
                elif not in_code and (m := HEADING_RE.match(line)):
                    found.add(m.group(1))
        _sections[doc] = found
    return _sections[doc]


def is_program(path):
    """An extensionless path naming a source file's stem or a target of its folder's meson.build."""
    folder, name = os.path.split(path.rstrip("/"))
    if "." in name or not os.path.isdir(os.path.join(src, folder)):
        return False
    if any(os.path.splitext(e)[0] == name for e in os.listdir(os.path.join(src, folder))):
        return True
    build_file = os.path.join(src, folder, "meson.build")
    if os.path.isfile(build_file):
        with open(build_file, encoding="utf-8") as f:
            return f"'{name}'" in f.read()
    return False


ARCHITECTURE_RE = re.compile(r"\bARCHITECTURE(?:\.md)?\s*§")

failures = []
checked = {"paths": 0, "sections": 0}

for rel in tracked_files():
    try:
        with open(os.path.join(src, rel), encoding="utf-8") as f:
            lines = f.read().splitlines()
    except (UnicodeDecodeError, OSError):
        continue  # binary
    for n, text in comment_text(rel, lines):
        if ARCHITECTURE_RE.search(text):
            failures.append(f"{rel}:{n}: 'ARCHITECTURE §' cites no file of the tree (docs/architecture.md?)")
        for m in PATH_RE.finditer(text):
            path = m.group(1).rstrip(".,;:)'\"`")
            if any(c in path for c in "<>*?{}…%$[]") or "..." in path or "XXX" in path:
                continue
            if any(re.fullmatch(r"[A-Z][A-Z_]+", part) or re.search(r"_[A-Z]{2,}\b", part) for part in path.split("/")):
                continue  # fuzz/corpus/NAME/: a placeholder
            checked["paths"] += 1
            if not os.path.exists(os.path.join(src, path)) and not is_program(path):
                failures.append(f"{rel}:{n}: '{path}' does not exist")
                continue
            if path.startswith("docs/") and path.endswith(".md"):
                after = text[m.start(1) + len(path):]
                sm = SECTION_RE.match(after)
                if not sm:
                    continue
                wanted = [sm.group(1)]
                rest = after[sm.end():]
                while mm := MORE_SECTIONS_RE.match(rest):
                    wanted.append(mm.group(1))
                    rest = rest[mm.end():]
                for s in wanted:
                    checked["sections"] += 1
                    if s not in sections_of(path):
                        failures.append(f"{rel}:{n}: '{path} §{s}': {path} has no heading numbered {s}")

for f in failures:
    print(f)
print(f"check_citations: {checked['paths']} path citations, {checked['sections']} section citations, "
      f"{len(failures)} dead", file=sys.stderr)
sys.exit(1 if failures else 0)
