#!/usr/bin/env bash
# Runs test programs inside a Debian PREEMPT_RT kernel booted under qemu.
#
#   rtguest.sh [--keep] [--require] [--file PATH]... TEST_PROGRAM[@GTEST_FILTER]...
#
# --keep keeps the work directory (initramfs, console log); --require turns
# "cannot be prepared here" into a failure instead of a skip (meson passes it
# when -Drt_guest_tests=enabled). A program given as path@filter runs with
# GTEST_FILTER=filter in the guest. --file copies a file or folder the tests
# need (module shared objects, .rmod files, a helper program) into the guest
# at the same absolute path; executables and shared objects bring their
# shared libraries.
#
# What it does (everything downloaded or built is cached under
# $CHIMERA_RTGUEST_CACHE, default /var/cache/chimera-rtguest, so a second run
# starts the guest straight away):
#   1. installs qemu-system-x86, busybox-static, xz-utils and the linux-headers package
#      matching Debian's linux-image-rt-amd64 (apt-get), downloads the kernel
#      image and linux-source packages (apt-get download) and unpacks the
#      kernel and the few modules the guest loads into the cache (the host's
#      own kernel is not touched); older kernel versions are dropped from it;
#   2. builds gpio-sim out of tree (Debian's RT config has it switched off):
#      drivers/gpio/gpio-sim.c plus kernel/irq/irq_sim.c, whose use of the
#      unexported irq_to_desc() is replaced by generic_handle_irq();
#   3. builds an initramfs: busybox, the test programs with their shared
#      libraries (ldd), the kernel modules configfs, can, can-raw, can-dev,
#      vcan and gpio-sim, and guest-init.sh as /init;
#   4. boots it with -accel tcg (kvm only when the CPU shows vmx/svm and
#      /dev/kvm can be opened), the init script loads the modules, creates
#      vcan0 and a gpio-sim chip, runs every test program, and powers off;
#   5. returns the tests' status, read from the marker line the guest prints
#      on its serial console. Exit 77 (meson's "skipped") when the guest
#      cannot be prepared here (not x86_64, no root and nothing installed, no
#      apt, no network), unless --require or the CI variable is set.
# The guest's emulated CPUs run at host nice -10 (CHIMERA_RTGUEST_NICE).
#
# Timing numbers measured inside a TCG guest mean nothing; the guest tests
# assert behaviour only.
set -euo pipefail

here="$(cd "$(dirname "$0")" && pwd)"
cache="${CHIMERA_RTGUEST_CACHE:-/var/cache/chimera-rtguest}"
timeout_s="${CHIMERA_RTGUEST_TIMEOUT:-600}"
keep=0
require=0
files=()
while [[ "${1:-}" == --* ]]; do
    case "$1" in
        --keep) keep=1 ;;
        --require) require=1 ;;
        --file) [[ $# -ge 2 ]] || { echo "$0: --file needs a path" >&2; exit 2; }
                files+=("$2"); shift ;;
        *) echo "$0: unknown option $1" >&2; exit 2 ;;
    esac
    shift
done
tests=("$@")
# Under CI (the CI variable set, as CI systems do) a missing prerequisite is a
# failure with its reason, never a silent skip: a green CI must mean the guest ran.
if [[ -n "${CI:-}" && "${CI}" != false && "${CI}" != 0 ]]; then require=1; fi
if ((${#tests[@]} == 0)); then
    echo "usage: $0 [--keep] [--require] TEST_PROGRAM[@GTEST_FILTER]..." >&2; exit 2
fi

say() { echo "rtguest: $*"; }
skip() {
    if ((require)); then say "FAIL (rt_guest_tests=enabled): $*"; exit 1; fi
    say "SKIP: $*"; exit 77
}

if [[ "$(uname -m)" != x86_64 ]]; then skip "x86_64 host needed"; fi
mkdir -p "$cache" 2>/dev/null || skip "cannot create cache $cache (set CHIMERA_RTGUEST_CACHE)"
[[ -w "$cache" ]] || skip "cache $cache is not writable (set CHIMERA_RTGUEST_CACHE)"

# Serialise concurrent runs (two build trees testing at once share the cache).
exec 9>"$cache/.lock"
flock 9

as_root() {
    if [[ $EUID -ne 0 ]]; then return 1; fi
    DEBIAN_FRONTEND=noninteractive "$@"
}

# --- 1. packages ----------------------------------------------------------
# linux-image-rt-amd64 is a meta package: its dependency names the kernel.
rt_kernel_version() {
    apt-cache depends linux-image-rt-amd64 2>/dev/null |
        sed -n 's/^ *Depends: linux-image-\(.*-rt-amd64\)$/\1/p' | head -n1
}
apt_updated=0
apt_update() {  # once per run; stale package lists name versions the mirror dropped
    ((apt_updated)) && return 0
    apt_updated=1
    as_root apt-get update -qq >>"$cache/apt-update.log" 2>&1
}
kver=""
if command -v apt-cache >/dev/null; then
    kver="$(rt_kernel_version)"
    if [[ -z "$kver" ]] && apt_update; then kver="$(rt_kernel_version)"; fi
fi
if [[ -z "$kver" && -f "$cache/kver" ]]; then kver="$(cat "$cache/kver")"; fi
[[ -n "$kver" ]] || skip "cannot find the linux-image-rt-amd64 kernel version (apt-cache)"
# A newer kernel version replaces the older one in the cache.
if [[ -f "$cache/kver" && "$(cat "$cache/kver")" != "$kver" ]]; then
    old="$(cat "$cache/kver")"
    say "dropping the cached kernel $old"
    rm -rf "$cache/kernel-$old" "$cache/gpio-sim-$old" "$cache/debs/linux-image-${old}"_*.deb
fi
echo "$kver" >"$cache/kver"
say "kernel $kver, cache $cache"

need_pkgs=()
command -v qemu-system-x86_64 >/dev/null || need_pkgs+=(qemu-system-x86)
[[ -x /bin/busybox ]] || need_pkgs+=(busybox-static)
command -v xz >/dev/null || need_pkgs+=(xz-utils)  # the kernel source is a .tar.xz (minbase Debian lacks it)
[[ -e "/lib/modules/$kver/build/Makefile" ]] || need_pkgs+=("linux-headers-$kver")
command -v make >/dev/null || need_pkgs+=(make)
command -v gcc >/dev/null || need_pkgs+=(gcc)
if ((${#need_pkgs[@]})); then
    say "installing ${need_pkgs[*]}"
    [[ $EUID -eq 0 ]] || skip "not root: cannot apt-get install ${need_pkgs[*]}"
    as_root apt-get install -y -qq --no-install-recommends "${need_pkgs[@]}" >"$cache/apt-install.log" 2>&1 ||
    { apt_update &&
      as_root apt-get install -y -qq --no-install-recommends "${need_pkgs[@]}" >"$cache/apt-install.log" 2>&1; } ||
        skip "could not install ${need_pkgs[*]} (see $cache/apt-install.log)"
fi
busybox_bin=/bin/busybox

download() {  # download PACKAGE[=VERSION] into the cache, updating the lists once if needed
    mkdir -p "$cache/debs"
    (cd "$cache/debs" && apt-get download "$1" >>"$cache/apt-download.log" 2>&1) ||
    { apt_update && (cd "$cache/debs" && apt-get download "$1" >>"$cache/apt-download.log" 2>&1); }
}

# Only the kernel and the modules the guest loads are unpacked (the package's
# whole module tree is 400 MB). Debian 12's modules are plain .ko files.
guest_modules=(fs/configfs/configfs.ko net/can/can.ko net/can/can-raw.ko
               drivers/net/can/dev/can-dev.ko drivers/net/can/vcan.ko)
kdir="$cache/kernel-$kver"
if [[ ! -f "$kdir/.done" || "$(cat "$kdir/.done")" != "${guest_modules[*]}" ]]; then
    imgdeb="$(ls "$cache/debs/linux-image-${kver}"_*.deb 2>/dev/null | head -n1 || true)"
    if [[ -z "$imgdeb" ]]; then
        download "linux-image-$kver" ||
            skip "apt-get download linux-image-$kver failed (see $cache/apt-download.log)"
        imgdeb="$(ls "$cache/debs/linux-image-${kver}"_*.deb | head -n1)"
    fi
    rm -rf "$kdir" && mkdir -p "$kdir"
    members=("./boot/vmlinuz-$kver")
    for m in "${guest_modules[@]}"; do members+=("./lib/modules/$kver/kernel/$m"); done
    dpkg-deb --fsys-tarfile "$imgdeb" | tar -x -C "$kdir" "${members[@]}" ||
        skip "the kernel package lacks one of ${members[*]}"
    echo "${guest_modules[*]}" >"$kdir/.done"
fi
vmlinuz="$kdir/boot/vmlinuz-$kver"
kmods="$kdir/lib/modules/$kver/kernel"
[[ -f "$vmlinuz" ]] || skip "no $vmlinuz in the kernel package"

# --- 2. gpio-sim, out of tree ----------------------------------------------
gdir="$cache/gpio-sim-$kver"
if [[ ! -f "$gdir/gpio-sim.ko" ]]; then
    # The linux-source package built from the same source version as the image.
    # (Built-Using names the linux source version; the image's own Version is the fallback.)
    srcver="$(dpkg-deb -f "$cache/debs/linux-image-${kver}"_*.deb Built-Using 2>/dev/null |
        sed -n 's/.*linux (= \([^)]*\)).*/\1/p')"
    [[ -n "$srcver" ]] || srcver="$(dpkg-deb -f "$cache/debs/linux-image-${kver}"_*.deb Version)"
    series="$(echo "$kver" | sed -n 's/^\([0-9]*\.[0-9]*\)\..*/\1/p')"
    srcdeb="$(ls "$cache/debs/linux-source-${series}_${srcver}"_all.deb 2>/dev/null | head -n1 || true)"
    if [[ -z "$srcdeb" ]]; then
        download "linux-source-${series}=${srcver}" ||
            skip "apt-get download linux-source-${series}=${srcver} failed (see $cache/apt-download.log)"
        srcdeb="$(ls "$cache/debs/linux-source-${series}_${srcver}"_all.deb | head -n1)"
    fi
    rm -rf "$gdir" && mkdir -p "$gdir/tmp"
    dpkg-deb --fsys-tarfile "$srcdeb" | tar -x -C "$gdir/tmp" "./usr/src/linux-source-${series}.tar.xz"
    tar -xJf "$gdir/tmp/usr/src/linux-source-${series}.tar.xz" -C "$gdir/tmp" \
        "linux-source-${series}/drivers/gpio/gpio-sim.c" \
        "linux-source-${series}/drivers/gpio/gpiolib.h" \
        "linux-source-${series}/kernel/irq/irq_sim.c"
    s="$gdir/tmp/linux-source-${series}"
    cp "$s/drivers/gpio/gpio-sim.c" "$gdir/gpio-sim-main.c"
    cp "$s/drivers/gpio/gpiolib.h" "$gdir/gpiolib.h"
    # irq_to_desc() is not exported to modules; generic_handle_irq() is, and
    # does the same for this simple-irq domain.
    sed 's/handle_simple_irq(irq_to_desc(irqnum));/generic_handle_irq(irqnum);/' \
        "$s/kernel/irq/irq_sim.c" >"$gdir/irq_sim.c"
    grep -q 'generic_handle_irq(irqnum);' "$gdir/irq_sim.c" || skip "irq_sim.c did not patch"
    rm -rf "$gdir/tmp"
    printf 'obj-m := gpio-sim.o\ngpio-sim-y := gpio-sim-main.o irq_sim.o\n' >"$gdir/Kbuild"
    say "building gpio-sim.ko against linux-headers-$kver"
    make -C "/lib/modules/$kver/build" M="$gdir" -j1 modules >"$gdir/build.log" 2>&1 ||
        { tail -n 30 "$gdir/build.log"; say "FAIL: gpio-sim build"; exit 1; }
    # The module is all that is needed from the source package (140 MB).
    rm -f "$srcdeb"
fi

# --- 3. initramfs ------------------------------------------------------------
work="$(mktemp -d "${TMPDIR:-/tmp}/chimera-rtguest.XXXXXX")"
cleanup() { if ((keep)); then say "kept $work"; else rm -rf "$work"; fi; }
trap cleanup EXIT
root="$work/root"
mkdir -p "$root"/{bin,sbin,dev,proc,sys,tmp,run,lib/modules,tests,filters,etc}
for applet in sh mount umount mkdir cat echo insmod ip ls sleep poweroff grep sed tr \
              head tail dmesg mknod ln env printf uname nproc timeout cut seq basename \
              date rm find wc test [ true false; do
    ln -sf busybox "$root/bin/$applet"
done
copy_with_libs() {  # copy a program and the shared libraries it needs
    local prog="$1" dest="$2"
    cp "$prog" "$dest"
    # A static program has no libraries: ldd fails and nothing is copied.
    { ldd "$prog" 2>/dev/null || true; } | { grep -o '/[^ ]*' || true; } | while read -r lib; do
        mkdir -p "$root$(dirname "$lib")"
        [[ -e "$root$lib" ]] || cp -L "$lib" "$root$lib"
        # The test programs run from /tests, where a RUNPATH relative to
        # $ORIGIN (meson's, for libchimera.so in the build tree) finds nothing:
        # the guest's init puts every library folder on LD_LIBRARY_PATH.
        grep -qxF "$(dirname "$lib")" "$root/etc/ld-library-path" 2>/dev/null ||
            dirname "$lib" >>"$root/etc/ld-library-path"
    done
}
copy_with_libs "$busybox_bin" "$root/bin/busybox"
i=0
for arg in "${tests[@]}"; do
    t="${arg%%@*}"
    [[ -x "$t" ]] || { say "FAIL: $t is not an executable"; exit 1; }
    i=$((i + 1))
    name="$(printf '%02d' $i)-$(basename "$t")"
    copy_with_libs "$t" "$root/tests/$name"
    if [[ "$arg" == *@* ]]; then printf '%s\n' "${arg#*@}" >"$root/filters/$name"; fi
done
for f in "${files[@]}"; do
    [[ -e "$f" ]] || { say "FAIL: --file $f does not exist"; exit 1; }
    f="$(realpath "$f")"
    mkdir -p "$root$(dirname "$f")"
    if [[ -d "$f" ]]; then
        cp -a "$f" "$root$(dirname "$f")/"
    else
        copy_with_libs "$f" "$root$f"
    fi
done
for m in "${guest_modules[@]}"; do
    cp "$kmods/$m" "$root/lib/modules/"
done
cp "$gdir/gpio-sim.ko" "$root/lib/modules/"
cp "$here/guest-init.sh" "$root/init"
chmod +x "$root/init"
(cd "$root" && find . | "$busybox_bin" cpio -o -H newc 2>/dev/null | gzip -1 >"$work/initramfs.gz")

# --- 4. boot ------------------------------------------------------------------
accel=tcg
if grep -qE '\b(vmx|svm)\b' /proc/cpuinfo && [[ -r /dev/kvm && -w /dev/kvm ]] &&
   (exec 8<>/dev/kvm) 2>/dev/null; then
    accel=kvm
fi
say "booting ($accel, ${#tests[@]} test program(s)), console log: $work/console.log"
start=$(date +%s)
set +e
# The guest's CPUs are emulated threads of this host: a loaded host (CI, or
# stress-ng) would starve them and the guest's real-time tests would measure
# the host's load, not the kernel under test. Like a real-time VM's vCPU
# threads, they get a higher host priority: nice -10 (CFS weight ~9x a nice-0
# thread), not SCHED_FIFO, which would take the host's CPUs from everything
# else while the emulation is busy. CHIMERA_RTGUEST_NICE overrides it.
nice_level="${CHIMERA_RTGUEST_NICE:--10}"
timeout --kill-after=10 "$timeout_s" nice -n "$nice_level" qemu-system-x86_64 \
    -accel "$accel" -m 768 -smp 2 -nographic -no-reboot \
    -kernel "$vmlinuz" -initrd "$work/initramfs.gz" \
    -append "console=ttyS0 panic=-1 loglevel=4 rdinit=/init" \
    -nic none -serial "file:$work/console.log" -monitor none -display none </dev/null
qrc=$?
set -e
say "guest ran $(( $(date +%s) - start )) s (qemu status $qrc)"
tr -d '\r' <"$work/console.log" | sed -n '/=== chimera-rtguest begin/,$p'
result="$(tr -d '\r' <"$work/console.log" | sed -n 's/^CHIMERA-RTGUEST-RESULT: \([A-Z]*\).*/\1/p' | tail -n1)"
case "$result" in
    PASS) exit 0 ;;
    FAIL) exit 1 ;;
    *) keep=1; tail -n 40 "$work/console.log"; say "FAIL: no result line from the guest"; exit 1 ;;
esac
