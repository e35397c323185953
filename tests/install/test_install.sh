#!/usr/bin/env bash
# The link-in library as a user gets it (issue 2): `meson install` into a
# staging directory, then, using only what was installed,
#   1. every installed header compiles on its own (self-sufficient headers),
#   2. a controller written out of tree (controller.cpp, which includes only
#      <chimera/...>) builds with `c++ ... $(pkg-config --cflags --libs chimera)`
#      and runs against the staged libchimera.so, printing what it expects,
#   3. the installed chimcfg runs.
#   test_install.sh BUILD_ROOT SOURCE_ROOT
set -euo pipefail
build=$(cd "${1:?usage: test_install.sh BUILD_ROOT SOURCE_ROOT}" && pwd)
source=$(cd "${2:?usage: test_install.sh BUILD_ROOT SOURCE_ROOT}" && pwd)
here="$source/tests/install"
cxx=${CXX:-c++}

fail() { echo "test_install: $*" >&2; exit 1; }

# meson test builds only what a test depends on; `meson install --no-rebuild`
# needs every installed target. Say so instead of failing obscurely.
missing=$(meson introspect "$build" --install-plan | python3 -c '
import json, os, sys
plan = json.load(sys.stdin)
for src in plan.get("targets", {}):
    if not os.path.exists(src): print(src)')
if [ -n "$missing" ]; then
    echo "test_install: not everything that is installed has been built; run ninja -C $build first:" >&2
    echo "$missing" | head -5 >&2
    exit 77  # skipped
fi

stage=$(mktemp -d /tmp/chimera-install.XXXXXX)
trap 'rm -rf "$stage"' EXIT
destdir="$stage/root"

echo "== DESTDIR=$destdir meson install -C $build --no-rebuild"
DESTDIR="$destdir" meson install -C "$build" --no-rebuild --quiet

pcs=$(find "$destdir" -name chimera.pc)
[ "$(echo "$pcs" | wc -l)" = 1 ] && [ -n "$pcs" ] || fail "expected one chimera.pc in the staging tree, found: ${pcs:-none}"
export PKG_CONFIG_PATH=$(dirname "$pcs")
export PKG_CONFIG_SYSROOT_DIR="$destdir"
export PKG_CONFIG_LIBDIR="$PKG_CONFIG_PATH"  # the staged chimera.pc and nothing else
cflags=$(pkg-config --cflags chimera)
libs=$(pkg-config --libs chimera)
echo "pkg-config --cflags chimera: $cflags"
echo "pkg-config --libs chimera:   $libs"
case "$cflags" in *"$destdir"*) ;; *) fail "cflags do not point into the staging tree: $cflags" ;; esac
# pkgconf prefixes variables with the sysroot too; pkg-config 0.29 does not.
staged() { case "$1" in "$destdir"/*) echo "$1" ;; *) echo "$destdir$1" ;; esac; }
libdir=$(staged "$(pkg-config --variable=libdir chimera)")
includedir=$(staged "$(pkg-config --variable=includedir chimera)")
[ -e "$libdir/libchimera.so" ] || fail "no libchimera.so in $libdir"

# Every public header is installed, and nothing else.
(cd "$source/include" && find chimera -name '*.hpp' | sort) > "$stage/headers.source"
(cd "$includedir" && find chimera -type f | sort) > "$stage/headers.installed"
diff -u "$stage/headers.source" "$stage/headers.installed" ||
    fail "installed headers differ from include/chimera (- source, + installed)"
echo "== $(wc -l < "$stage/headers.installed") headers installed"

# 1. Each header on its own, with nothing but the installed include path.
echo "== each installed header compiles alone"
bad=0
while read -r h; do
    if ! echo "#include <$h>" | $cxx -x c++ $cflags -fsyntax-only -Wall -Wextra -Werror - \
            2> "$stage/header.err"; then
        echo "header $h does not compile on its own:" >&2
        head -20 "$stage/header.err" >&2
        bad=1
    fi
done < "$stage/headers.installed"
[ $bad = 0 ] || fail "some installed headers are not self-sufficient"

# 2. The out-of-tree controller: only <chimera/...> and the standard library.
if grep -E '^\s*#\s*include\s*"' "$here/controller.cpp"; then
    fail "controller.cpp must include only <chimera/...> and standard headers"
fi
echo "== $cxx -o controller controller.cpp \$(pkg-config --cflags --libs chimera)"
$cxx -o "$stage/controller" "$here/controller.cpp" $cflags $libs
export LD_LIBRARY_PATH="$libdir"
resolved=$(ldd "$stage/controller" | awk '/libchimera/ {print $3}')
[ -n "$resolved" ] && [ "$(readlink -f "$resolved")" = "$(readlink -f "$libdir/libchimera.so")" ] ||
    fail "controller resolves libchimera to '$resolved', not the staged one in $libdir"
echo "controller uses $resolved"
"$stage/controller" "$here/data/controller.svar" "installtest$$" > "$stage/controller.out"
diff -u "$here/controller.expected" "$stage/controller.out" || fail "controller output differs (- expected, + got)"
cat "$stage/controller.out"

# 3. The installed chimcfg.
chimcfg=$(find "$destdir" -type f -name chimcfg | head -1)
[ -x "$chimcfg" ] || fail "chimcfg is not installed"
out=$("$chimcfg" check "$here/data/controller.svar")
[ "$out" = "$here/data/controller.svar: ok, svar, 3 variables, 76 bytes of data" ] || fail "installed chimcfg check printed: $out"
echo "installed chimcfg: $out"
# 4. The Python package, when the bindings are built (-Dpython): the staged
# package and extension import with the staged libchimera.
core=$(find "$destdir" -name '_core*.so' -path '*/chimera/*' | head -1)
if [ -n "$core" ]; then
    pydir=$(dirname "$(dirname "$core")")
    echo "== PYTHONPATH=$pydir /usr/bin/python3 -c 'import chimera'"
    PYTHONPATH="$pydir" /usr/bin/python3 "$here/python_check.py" "$here/data/controller.svar" "pyinstall$$" "$pydir/chimera/" ||
        fail "the installed Python package does not import and run"
fi
echo "== install test passed"
