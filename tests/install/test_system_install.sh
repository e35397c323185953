#!/usr/bin/env bash
# The README's controller recipe exactly as a user on Debian runs it (issue #16):
#   meson install -C build            (the real prefix, /usr/local; no DESTDIR)
#   c++ -std=c++20 controller.cpp $(pkg-config --cflags --libs chimera)
#   ./controller                      (no PKG_CONFIG_PATH, no LD_LIBRARY_PATH)
# so the library must land where Debian's pkg-config and loader look
# (/usr/local/lib/<multiarch>, not /usr/local/lib64) and the loader cache must
# be refreshed by the install. The machine is not touched: in a private mount
# namespace, /usr/local is an empty tmpfs and /etc a copy (ldconfig writes
# /etc/ld.so.cache), both gone when the test ends.
#   test_system_install.sh BUILD_ROOT SOURCE_ROOT
set -euo pipefail
build=$(cd "${1:?usage: test_system_install.sh BUILD_ROOT SOURCE_ROOT}" && pwd)
source=$(cd "${2:?usage: test_system_install.sh BUILD_ROOT SOURCE_ROOT}" && pwd)
if [ "$(id -u)" -ne 0 ] || ! command -v unshare >/dev/null; then
    echo "test_system_install: needs root and unshare (a private mount namespace) to install into /usr/local"
    [ -n "${CI:-}" ] && exit 1
    exit 77
fi
# What the namespace below needs first; its error says why not (a container
# forbidding unshare, or a chroot: its / is no mount point, so cannot be made private).
if ! why=$(unshare -m -- mount --make-rprivate / 2>&1); then
    if ! awk '$5 == "/" { found = 1 } END { exit !found }' /proc/self/mountinfo; then
        echo "test_system_install: / is not a mount point (a chroot?), so no private mount namespace of it: $why"
    else
        echo "test_system_install: no private mount namespace here (unshare -m, mount --make-rprivate /): $why"
    fi
    [ -n "${CI:-}" ] && exit 1
    exit 77
fi
prefix=$(meson introspect "$build" --buildoptions |
         python3 -c 'import json,sys; print(next(o["value"] for o in json.load(sys.stdin) if o["name"] == "prefix"))')
[ "$prefix" = /usr/local ] || { echo "test_system_install: the build's prefix is $prefix, not the default /usr/local"; exit 77; }
work=$(mktemp -d /tmp/chimera-sysinstall.XXXXXX)
trap 'rm -rf "$work"' EXIT
cp -a /etc "$work/etc"
# not exec: the EXIT trap removes $work afterwards
unshare -m -- bash -euo pipefail -c '
    build=$1 source=$2 work=$3
    mount --make-rprivate /
    mount -t tmpfs tmpfs /usr/local
    mount --bind "$work/etc" /etc
    echo "== meson install -C build (prefix /usr/local)"
    meson install -C "$build" --no-rebuild --quiet
    cd "$work"
    echo "== c++ -std=c++20 controller.cpp \$(pkg-config --cflags --libs chimera), nothing set"
    flags=$(env -i PATH=/usr/bin:/bin pkg-config --cflags --libs chimera) ||
        { echo "pkg-config does not find chimera where it was installed:"; find /usr/local -name chimera.pc; exit 1; }
    echo "pkg-config: $flags"
    env -i PATH=/usr/bin:/bin c++ -std=c++20 -o controller "$source/tests/install/controller.cpp" $flags
    echo "== ./controller, no environment"
    env -i PATH=/usr/bin:/bin ./controller "$source/tests/install/data/controller.svar" "sysinstall$$" > out.txt ||
        { echo "the controller does not run: $(env -i ldd ./controller | grep chimera)"; exit 1; }
    diff -u "$source/tests/install/controller.expected" out.txt
    echo "== the installed tools run from PATH"
    env -i PATH=/usr/local/bin:/usr/bin:/bin chimcfg check "$source/tests/install/data/controller.svar"
    echo "== a chimgen skeleton: built unedited by its Makefile against the installed library, spawned by name"
    skel="$work/skel"
    env -i PATH=/usr/local/bin:/usr/bin:/bin chimgen skel --in-var Q_REF --out-var TAU --freq 100 \
        --svar "$source/tests/install/data/controller.svar" -o "$skel" > /dev/null
    env -i PATH=/usr/local/bin:/usr/bin:/bin make -s -C "$skel"
    cp "$source/tests/install/data/controller.svar" "$skel/"
    sed "s/^SUBSYSTEM .*/SUBSYSTEM skel$$/" "$source/tests/install/data/ctl.sbs" > "$skel/skel.sbs"
    env -i PATH=/usr/local/bin:/usr/bin:/bin CHIMERA_MODULE_PATH="$skel" \
        sbs "$skel/skel.sbs" --no-attach -c "spawn skel; on; sleep 0.2; status skel" > "$skel/out.txt" ||
        { cat "$skel/out.txt"; exit 1; }
    grep -E "^skel +main .* ON " "$skel/out.txt" || { echo "the skeleton does not run:"; cat "$skel/out.txt"; exit 1; }
    echo "== the build tree'"'"'s sbs loads the modules built with it, the installed sbs the installed ones"
    sed "s/^SUBSYSTEM .*/SUBSYSTEM modpath$$/" "$source/tests/install/data/ctl.sbs" > "$work/modpath.sbs"
    cp "$source/tests/install/data/controller.svar" "$work/"
    pid_module() {  # the pid.so that sbs ($1) finds for `module`
        env -i PATH=/usr/local/bin:/usr/bin:/bin "$1" "$work/modpath.sbs" --no-attach --json -c module |
            python3 -c "import json,sys; print(next(m[\"path\"] for m in json.loads(sys.stdin.readline())[\"data\"][\"modules\"] if m[\"name\"] == \"pid\"))"
    }
    found=$(pid_module "$build/tools/sbs/sbs")
    [ "$found" = "$build/modules/pid/pid.so" ] || { echo "build-tree sbs found $found, not $build/modules/pid/pid.so"; exit 1; }
    found=$(pid_module sbs)
    case $found in /usr/local/lib/*/chimera/modules/pid.so) ;; *) echo "installed sbs found $found"; exit 1 ;; esac
    if meson introspect "$build" --install-plan | grep -q "_core.*\\.so"; then
        echo "== /usr/bin/python3 -c \"import chimera\", no environment: the package is on Debian'"'"'s sys.path"
        env -i PATH=/usr/bin:/bin /usr/bin/python3 "$source/tests/install/python_check.py" \
            "$source/tests/install/data/controller.svar" "sysinstallpy$$" /usr/local/lib/python3
    fi
    echo "== system install test passed"
' bash "$build" "$source" "$work"
