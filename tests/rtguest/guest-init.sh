#!/bin/sh
# /init of the rtguest initramfs (busybox sh): set up the kernel interfaces the
# guest tests need, run every program under /tests, print one result line,
# power off. The host (rtguest.sh) reads the result line from the console.
export PATH=/bin:/sbin
mount -t proc proc /proc
mount -t sysfs sysfs /sys
mount -t devtmpfs devtmpfs /dev
mkdir -p /dev/shm /dev/pts
mount -t tmpfs tmpfs /dev/shm
# /tmp stays the initramfs's own (writable, like all of it): the files
# rtguest.sh --file copied in may live under /tmp (a build tree there).
echo "=== chimera-rtguest begin: $(uname -r) $(uname -v), $(nproc) cpu(s)"

fail=0
setup_fail() { echo "rtguest setup: $*"; fail=$((fail + 1)); }

for m in configfs can can-raw can-dev vcan gpio-sim; do
    insmod /lib/modules/$m.ko || setup_fail "insmod $m"
done
mount -t configfs none /sys/kernel/config || setup_fail "mount configfs"
# The per-thread system-call counters of the real-time tests (raw_syscalls).
mount -t tracefs nodev /sys/kernel/tracing || setup_fail "mount tracefs"
# cgroup v2 with the cpuset controller: the deadline backend's tests make an
# exclusive partition of one CPU there (docs/muf.md, "Deadline backend").
mount -t cgroup2 none /sys/fs/cgroup || setup_fail "mount cgroup2"

ip link add dev vcan0 type vcan && ip link set vcan0 up || setup_fail "vcan0"
ip link add dev vcan1 type vcan && ip link set vcan1 up || setup_fail "vcan1"

# One simulated chip with two banks: bank0 has 8 lines, bank1 has 4 (a second
# device for the database tests). The tests find them through these variables.
g=/sys/kernel/config/gpio-sim/chimera
if mkdir $g && mkdir $g/bank0 $g/bank1; then
    echo 8 >$g/bank0/num_lines
    echo 4 >$g/bank1/num_lines
    echo 1 >$g/live
    export CHIMERA_GPIOSIM_CHIP0="$(cat $g/bank0/chip_name)"
    export CHIMERA_GPIOSIM_CHIP1="$(cat $g/bank1/chip_name)"
    export CHIMERA_GPIOSIM_DEV="$(cat $g/dev_name)"
    echo "gpio-sim: $CHIMERA_GPIOSIM_DEV banks $CHIMERA_GPIOSIM_CHIP0 $CHIMERA_GPIOSIM_CHIP1"
else
    setup_fail "gpio-sim configfs"
fi
# Library folders of the test programs and the files they brought (rtguest.sh).
[ -f /etc/ld-library-path ] && export LD_LIBRARY_PATH="$(tr '\n' ':' </etc/ld-library-path)"
export CHIMERA_VCAN=vcan0 CHIMERA_VCAN1=vcan1 CHIMERA_RTGUEST=1 GTEST_COLOR=no

# Each program may have a Google Test filter (rtguest.sh PROGRAM@FILTER) and
# gets at most 300 s, so one hung test fails alone instead of the whole boot.
n=0
for t in /tests/*; do
    n=$((n + 1))
    filter=""
    [ -f "/filters/${t##*/}" ] && filter="$(cat "/filters/${t##*/}")"
    echo "=== run $t${filter:+ (GTEST_FILTER=$filter)}"
    if [ -n "$filter" ]; then
        GTEST_FILTER="$filter" timeout 300 "$t"
    else
        timeout 300 "$t"
    fi
    status=$?
    if [ $status -eq 0 ]; then
        echo "=== ok $t"
    else
        echo "=== FAILED $t (status $status)"
        fail=$((fail + 1))
    fi
    # A CPU partition a test made and left would take its CPU from every later program.
    for p in /sys/fs/cgroup/chimera-partition-*; do
        [ -d "$p" ] || continue
        echo "=== FAILED $t left the CPU partition $p ($(cat $p/cpuset.cpus.partition))"
        fail=$((fail + 1))
    done
done
if [ $fail -eq 0 ]; then
    echo "CHIMERA-RTGUEST-RESULT: PASS ($n programs)"
else
    echo "CHIMERA-RTGUEST-RESULT: FAIL ($fail failures, $n programs)"
fi
sync
poweroff -f
