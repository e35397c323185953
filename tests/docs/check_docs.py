#!/usr/bin/env python3
"""What README.md and the public headers' comments name must exist and, where it
can run here, work (issue #36):
  - every repository path (abi/, bench/, docs/, examples/, ..., build/...) in
    README.md and in the comments of include/chimera/**.hpp exists (a glob
    matches something), and every file a header's example quotes ("x.sbs");
  - every program a README command starts with that the build makes (meson's
    executable targets: chimgen, sbs, ...) is built;
  - every program of the build that README's "What the main job shows" runs
    (build/...) is built by `ninja demo-only`, what scripts/demo.sh builds;
  - README's stages (`scripts/test.sh --stage X`) are in `scripts/test.sh --list`;
  - `chimcfg check` accepts every .svar/.sbs/.rmod they name;
  - the README's chimgen recipe runs as written in a scratch folder, against
    the build tree (its tools for the installed ones on PATH; the line that
    needs `meson install` is tests/install/test_system_install.sh's), and
    sbs.hpp's example program compiles and runs; each under a subsystem name
    of its own (a copy of the .sbs they name).
Each failure names the file, the line and what is missing.
  check_docs.py SOURCE_ROOT BUILD_ROOT
"""
import glob
import json
import os
import re
import shlex
import subprocess
import sys
import tempfile

src, build = (os.path.abspath(a) for a in sys.argv[1:3])
failures = []


def fail(where, what):
    failures.append(f"{where}: {what}")


# Top-level folders of the tree a path may start with; build/ is the build tree.
ROOTS = sorted(e for e in os.listdir(src)
               if os.path.isdir(os.path.join(src, e)) and e != ".git" and not e.startswith("build"))
PATH_RE = re.compile(r"(?<![\w./$<-])((?:%s|build)/[\w.*/<>…-]*)" % "|".join(re.escape(r) for r in ROOTS))
# Made by running something, not by the build: named, with what makes them.
MADE_BY_RUNNING = {"build/demo-setup.log": "scripts/demo.sh"}


def resolve(path):
    """The file a tree path names: build/... in the build tree, else in the source."""
    if path == "build" or path.startswith("build/"):
        return os.path.join(build, path[len("build/"):])
    return os.path.join(src, path)


def check_path(where, path):
    path = path.rstrip(".,;:)")
    if not path or any(c in path for c in "<>…") or path in MADE_BY_RUNNING:
        return  # a placeholder (tests/<service>/), or an output of a run
    target = resolve(path)
    if "*" in path:
        if not glob.glob(target):
            fail(where, f"'{path}' matches nothing")
    elif not os.path.exists(target):
        # A build part whose feature is off has no folder at all in the build tree.
        if path.startswith("build/") and not os.path.isdir(os.path.dirname(target)):
            print(f"note: {where}: '{path}' not built here (its folder is absent: a feature off?)")
        else:
            fail(where, f"'{path}' does not exist" + (" in the build tree" if path.startswith("build/") else ""))


def lines_of(rel):
    with open(os.path.join(src, rel), encoding="utf-8") as f:
        return f.read().splitlines()


# ---- paths in README.md and in the headers' comments, and the headers' quoted files
readme = lines_of("README.md")
for n, line in enumerate(readme, 1):
    for m in PATH_RE.finditer(line):
        check_path(f"README.md:{n}", m.group(1))

headers = sorted(os.path.relpath(p, src) for p in glob.glob(os.path.join(src, "include/chimera/**/*.hpp"), recursive=True))
config_files = []  # (where, path) of every .svar/.sbs/.rmod named
for h in headers:
    for n, line in enumerate(lines_of(h), 1):
        comment = line.split("//", 1)[1] if "//" in line else ""
        if not comment:
            continue
        for m in PATH_RE.finditer(comment):
            check_path(f"{h}:{n}", m.group(1))
        for q in re.findall(r'"([^"\s]+\.(?:sbs|svar|rmod))"', comment):
            if "/" not in q:
                fail(f"{h}:{n}", f"'{q}' is no path from the top of the tree (which {q}?)")
            elif not os.path.isfile(os.path.join(src, q)):
                fail(f"{h}:{n}", f"'{q}' does not exist")
            else:
                config_files.append((f"{h}:{n}", q))

# ---- the README's shell blocks
blocks = []  # [(first line number, [lines])]
in_block = False
for n, line in enumerate(readme, 1):
    if line.startswith("```"):
        if not in_block and line.strip() == "```sh":
            blocks.append((n + 1, []))
            in_block = "sh"
        else:
            in_block = False if in_block else "other"
        continue
    if in_block == "sh":
        blocks[-1][1].append(line)

intro = json.loads(subprocess.run(["meson", "introspect", build, "--targets"], check=True,
                                  capture_output=True, text=True).stdout)
programs = {}  # the build's programs: name -> its file
for t in intro:
    if t["type"] == "executable":
        for f in t["filename"]:
            programs.setdefault(os.path.basename(f), f)


def commands(line):
    """The commands of one shell line: its words, split at ;, &&, ||, |."""
    code = re.split(r"\s#", " " + line, maxsplit=1)[0]
    try:
        words = shlex.split(code, comments=True)
    except ValueError:
        return []
    cmds, cur = [], []
    for w in words:
        if w in (";", "&&", "||", "|"):
            cmds.append(cur)
            cur = []
        else:
            cur.append(w)
    cmds.append(cur)
    return [c for c in cmds if c]


USER_FILES = {"my_controller.cpp": "the user's own program"}
for first, block in blocks:
    made = set()  # what earlier lines of the block write (-o NAME)
    for i, line in enumerate(block):
        where = f"README.md:{first + i}"
        for cmd in commands(line):
            while cmd and re.match(r"^\w+=", cmd[0]):
                cmd = cmd[1:]
            if not cmd:
                continue
            prog = cmd[0]
            if "/" in prog:
                check_path(where, prog)
            elif prog in programs and not os.path.exists(programs[prog]):
                fail(where, f"the program '{prog}' is not built ({programs[prog]})")
            for j, w in enumerate(cmd[1:], 1):
                if cmd[j - 1] in ("-o", "--output", "-C"):
                    made.add(w)
                    continue
                w = w.replace("$PWD/", "")
                if w.startswith(("-", "/", "$", "'")) or w in made or w in USER_FILES:
                    continue
                if re.search(r"\.(sbs|svar|rmod|cpp|py|sh|tasks)$", w):
                    if not os.path.isfile(os.path.join(src, w)):
                        fail(where, f"'{w}' does not exist (from the top of the tree)")
                    elif w.endswith((".sbs", ".svar", ".rmod")):
                        config_files.append((where, w))

# ---- the programs the demo's section runs are built by the demo (scripts/demo.sh: ninja demo-only)
def demo_only_inputs():
    q = subprocess.run(["ninja", "-C", build, "-t", "query", "demo-only"], capture_output=True, text=True)
    if q.returncode != 0:
        return None
    return {l.strip(" |") for l in q.stdout.splitlines() if l.startswith("    ")}


demo_inputs = demo_only_inputs()
built_programs = {os.path.relpath(f, build) for f in programs.values()}
in_demo_section = False
for n, line in enumerate(readme, 1):
    if line.startswith("## "):
        in_demo_section = line.strip() == "## What the main job shows"
    if not in_demo_section or demo_inputs is None:
        continue
    for prog in re.findall(r"`build/([^`\s]+)", line):
        if prog in built_programs and prog not in demo_inputs:
            fail(f"README.md:{n}", f"runs build/{prog}, which scripts/demo.sh (ninja demo-only) does not build")
if demo_inputs is None:
    print("note: no target demo-only here (the demo is not built): its programs are not checked")

# ---- scripts/test.sh's stages the README names
listed = subprocess.run([os.path.join(src, "scripts/test.sh"), "--list"], capture_output=True, text=True)
if listed.returncode != 0:
    fail("scripts/test.sh", f"--list exits {listed.returncode}: {listed.stderr.strip()}")
stages = set(listed.stdout.split())
for n, line in enumerate(readme, 1):
    for stage in re.findall(r"scripts/test\.sh --stage ([\w-]+)", line):
        if stage not in stages:
            fail(f"README.md:{n}", f"no stage '{stage}' in scripts/test.sh --list ({' '.join(sorted(stages))})")

# ---- chimcfg check on every configuration file named
chimcfg = programs.get("chimcfg")
for where, f in config_files:
    r = subprocess.run([chimcfg, "check", os.path.join(src, f)], capture_output=True, text=True)
    if r.returncode != 0:
        fail(where, f"chimcfg check {f}: {(r.stdout + r.stderr).strip()}")


# ---- the chimgen recipe and sbs.hpp's example, run
UNIQUE = f"docs{os.getpid()}"


def scratch(tmp):
    """tmp as the tree's top (build/ the build tree), the build's programs on PATH."""
    for e in os.listdir(src):
        if e not in ("build", ".git"):
            os.symlink(os.path.join(src, e), os.path.join(tmp, e))
    os.symlink(build, os.path.join(tmp, "build"))
    bindir = os.path.join(tmp, ".bin")
    os.mkdir(bindir)
    for name, f in programs.items():
        os.symlink(f, os.path.join(bindir, name))
    return dict(os.environ, PATH=bindir + os.pathsep + os.environ["PATH"])


def own_subsystem(tmp, text):
    """text with every .sbs it names replaced by a copy under the name UNIQUE."""
    for sbs in set(re.findall(r"([\w./-]+\.sbs)\b", text)):
        path = os.path.join(tmp, sbs)
        if not os.path.isfile(path):
            continue  # reported above
        with open(path) as f:
            conf = f.read()
        conf = re.sub(r"(?m)^SUBSYSTEM\s+\S+", f"SUBSYSTEM {UNIQUE}", conf)
        conf = re.sub(r"(?m)^(SVARFILE\s+)(\S+)",
                      lambda m: m.group(1) + os.path.join(os.path.dirname(os.path.realpath(path)), m.group(2)), conf)
        copy = os.path.join(tmp, f"{UNIQUE}.sbs")
        with open(copy, "w") as f:
            f.write(conf)
        text = text.replace(sbs, copy)
    return text


def run(where, cmd, tmp, env, shown):
    r = subprocess.run(["bash", "-c", "set -eo pipefail; " + cmd], cwd=tmp, env=env,
                       capture_output=True, text=True, timeout=120)
    print(f"$ {shown}\n{r.stdout}{r.stderr}", end="")
    if r.returncode != 0:
        out = (r.stdout + r.stderr).strip()
        fail(where, f"exits {r.returncode}: " + (out if len(out) < 800 else out[:500] + " … " + out[-300:]))
    return r.returncode == 0


def run_recipe():
    found = [(first, b) for first, b in blocks if any(l.startswith("chimgen ") for l in b)]
    if len(found) != 1:
        fail("README.md", f"one sh block with the chimgen recipe expected, found {len(found)}")
        return
    first, block = found[0]
    # Needs the library installed on the machine: tests/install/test_system_install.sh runs it.
    skip = re.compile(r"^make -C \S+\s+# against the installed library$")
    with tempfile.TemporaryDirectory(prefix="chimera-docs-") as tmp:
        env = scratch(tmp)
        for i, line in enumerate(block):
            if line.strip() and not skip.match(line):
                if not run(f"README.md:{first + i}", own_subsystem(tmp, line), tmp, env, line):
                    return


def run_header_example():
    """sbs.hpp's example, in main(), built against the build tree and run."""
    lines = lines_of("include/chimera/sbs.hpp")
    start = next((n for n, l in enumerate(lines) if "Subsystem::init(" in l and l.startswith("//     ")), None)
    if start is None:
        fail("include/chimera/sbs.hpp", "no example calling Subsystem::init( found")
        return
    while lines[start - 1].startswith("//     "):
        start -= 1
    end = start
    while end < len(lines) and lines[end].startswith("//     "):
        end += 1
    where = f"include/chimera/sbs.hpp:{start + 1}"
    modules = sorted({os.path.join(build, "modules", m) for m in re.findall(r'"modules/(\w+)/', "".join(lines[start:end]))})
    if not all(os.path.isdir(m) for m in modules):
        print(f"note: {where}: its modules are not built here ({' '.join(modules)}): the example is not run")
        return
    body = "\n".join("    " + l[len("//     "):] for l in lines[start:end])
    with tempfile.TemporaryDirectory(prefix="chimera-docs-") as tmp:
        env = scratch(tmp)
        env.update(PKG_CONFIG_PATH=os.path.join(build, "meson-uninstalled"), LD_LIBRARY_PATH=build,
                   CHIMERA_MODULE_PATH=":".join(modules))
        with open(os.path.join(tmp, "example.cpp"), "w") as f:
            f.write("#include <chimera/sbs.hpp>\n#include <chrono>\n#include <iostream>\n#include <thread>\n"
                    "using namespace std::chrono_literals;\nusing chimera::sbs::Control;\n"
                    "using chimera::sbs::format_status;\n"
                    "int main() {\n" + own_subsystem(tmp, body) + "\n}\n")
        if run(where, "c++ -std=c++20 -Wall -Wextra -Werror -o example example.cpp $(pkg-config --cflags --libs chimera)", tmp, env,
               "c++ example.cpp (sbs.hpp's example in main())"):
            run(where, "./example", tmp, env, "./example")


if not failures:  # what names a missing file fails above, and would only fail again here
    run_recipe()
    run_header_example()

failures = list(dict.fromkeys(failures))  # a path both named and quoted: once
for f in failures:
    print("FAIL", f)
print(f"check_docs: {len(failures)} failure(s)")
sys.exit(1 if failures else 0)
