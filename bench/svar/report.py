#!/usr/bin/env python3
"""Turns bench_svar's JSON output into the Markdown tables of bench/results/svar.md.

    bench_svar --benchmark_repetitions=5 --benchmark_report_aggregates_only=true \
               --benchmark_out=svar.json --benchmark_out_format=json
    bench/svar/report.py svar.json

Every figure is the median of the repetitions, CPU time in ns (the machine is
shared: CPU time leaves out the time the benchmark thread was preempted; the
wall-clock medians of the target rows are printed beside them).
"""
import json
import sys


def load(path):
    with open(path) as f:
        data = json.load(f)
    cpu, real = {}, {}
    for b in data["benchmarks"]:
        if b.get("aggregate_name") != "median":
            continue
        name = b["run_name"]
        scale = {"ns": 1.0, "us": 1e3, "ms": 1e6}[b.get("time_unit", "ns")]
        cpu[name] = b["cpu_time"] * scale
        real[name] = b["real_time"] * scale
    return data["context"], cpu, real


def t(name, nelem, count):
    return f"{name}/nelem:{nelem}/count:{count}"


def fmt(x):
    return f"{x:.1f}" if x < 100 else f"{x:.0f}"


def met(ok):
    return "**met**" if ok else "**not met**"


def main():
    context, cpu, real = load(sys.argv[1])
    out = []
    p = out.append

    p("### Locking and raw transfer (the shape of Table 2)\n")
    p("| operation | ns (median CPU time) |")
    p("|---|---|")
    p(f"| atomic test-and-set lock + unlock (CAS, store), plain word | {fmt(cpu['BM_AtomicLockUnlock'])} |")
    p(f"| SVAR table lock acquire + release (`ipc::lock` / `ipc::unlock`) | {fmt(cpu['BM_TableLockUnlock'])} |")
    for nelem in (6, 32, 256):
        p(f"| raw data transfer (memcpy), float[{nelem}] | {fmt(cpu[t('BM_Memcpy', nelem, 1)])} |")
    p("")

    p("### Single-variable vs multi-variable transfers (the shape of Table 3)\n")
    p("n × float[m]; every column moves the same bytes. *floor*: bare memcpy of each variable; "
      "*atomic*: one atomic lock/unlock around the memcpys; *atomic, copy_var*: the same with the "
      "table's own copy routine instead of memcpy (inline moves for 8 to 64 bytes, memcpy beyond); "
      "*mutex*: one pthread mutex around the memcpys; "
      "*svarRead ×n*: n single-variable reads (`LocalTable::read`, one lock each); "
      "*copy_from*: one `copy_from_global` of the n-variable set (one lock); same for writes "
      "(`LocalTable::write` ×n vs `copy_to_global`, which also saves the undo record). "
      "*saving*: how much the multi-variable transfer saves over n single ones.\n")
    p("| transfer | floor | atomic | atomic, copy_var | mutex | svarRead ×n | copy_from | saving | svarWrite ×n | copy_to | saving |")
    p("|---|---|---|---|---|---|---|---|---|---|---|")
    for count in (1, 2, 6):
        for nelem in (6, 32, 256):
            r, cf = cpu[t("BM_SvarRead", nelem, count)], cpu[t("BM_SvarCopyFrom", nelem, count)]
            w, ct = cpu[t("BM_SvarWrite", nelem, count)], cpu[t("BM_SvarCopyTo", nelem, count)]
            p(f"| {count} × float[{nelem}] | {fmt(cpu[t('BM_Memcpy', nelem, count)])} "
              f"| {fmt(cpu[t('BM_AtomicLockMemcpy', nelem, count)])} "
              f"| {fmt(cpu[t('BM_AtomicLockCopyVar', nelem, count)])} "
              f"| {fmt(cpu[t('BM_PthreadMutexMemcpy', nelem, count)])} "
              f"| {fmt(r)} | {fmt(cf)} | {100 * (1 - cf / r):.0f} % "
              f"| {fmt(w)} | {fmt(ct)} | {100 * (1 - ct / w):.0f} % |")
    p("")

    p("### TBUF write + read\n")
    p("One item written and read back (both roles in one thread). *tbuf*: `write(item)` (stamps "
      "it with `now_ns()`) + `read`; *tbuf, stamp given*: `write(item, time_ns)` + `read`, no clock "
      "read; *mutex*: the same item through a buffer guarded by a pthread mutex (lock, memcpy in, "
      "unlock; lock, memcpy out, unlock); *mutex + stamp*: the same, the writer also reading the clock "
      "and passing the stamp with the item, as TBUF's default write() does.\n")
    p("| item | tbuf | tbuf, stamp given | mutex write + read | mutex + stamp | tbuf / (mutex + stamp) | stamp given / mutex |")
    p("|---|---|---|---|---|---|---|")
    for size in (24, 128, 144, 1024):
        a = cpu[f"BM_TbufWriteRead/bytes:{size}/stamped:0"]
        b = cpu[f"BM_TbufWriteRead/bytes:{size}/stamped:1"]
        m = cpu[f"BM_PthreadMutexWriteRead/bytes:{size}"]
        ms = cpu[f"BM_PthreadMutexWriteReadStamped/bytes:{size}"]
        p(f"| {size} B | {fmt(a)} | {fmt(b)} | {fmt(m)} | {fmt(ms)} | {a / ms:.2f} | {b / m:.2f} |")
    p(f"\nOne `clock_gettime(CLOCK_MONOTONIC)` (vDSO) on this machine: {fmt(cpu['BM_MonotonicClock'])} ns.\n")

    p("### Targets (medians of this run)\n")
    read1 = t("BM_SvarRead", 6, 1)
    floor1 = t("BM_AtomicLockMemcpy", 6, 1)
    r1 = cpu[read1] / cpu[floor1]
    floor_sum = cpu[t("BM_Memcpy", 6, 1)] + cpu["BM_AtomicLockUnlock"]
    strict1 = t("BM_AtomicLockCopyVar", 6, 1)
    p(f"1. Single float[6] read ≤ 2 × (bare memcpy + one uncontended atomic lock/unlock): "
      f"svarRead {fmt(cpu[read1])} ns / floor {fmt(cpu[floor1])} ns = **{r1:.2f}** → {met(r1 <= 2)} "
      f"(wall clock: {fmt(real[read1])} / {fmt(real[floor1])} = {real[read1] / real[floor1]:.2f}; "
      f"against the floor taken as the sum of its two parts measured apart, "
      f"{fmt(cpu['BM_Memcpy/nelem:6/count:1'])} + {fmt(cpu['BM_AtomicLockUnlock'])} = {fmt(floor_sum)} ns: "
      f"{cpu[read1] / floor_sum:.2f}; against the floor with the table's own copy routine, "
      f"{fmt(cpu[strict1])} ns: {cpu[read1] / cpu[strict1]:.2f}).")
    rr = cpu[t("BM_SvarCopyFrom", 6, 6)] / cpu[t("BM_SvarRead", 6, 6)]
    rw = cpu[t("BM_SvarCopyTo", 6, 6)] / cpu[t("BM_SvarWrite", 6, 6)]
    p(f"2. Six float[6] in one multi-variable transfer ≤ ½ of six single transfers: "
      f"copy_from_global / 6 × read = {fmt(cpu[t('BM_SvarCopyFrom', 6, 6)])} / "
      f"{fmt(cpu[t('BM_SvarRead', 6, 6)])} = **{rr:.2f}** → {met(rr <= 0.5)}; "
      f"copy_to_global / 6 × write = {fmt(cpu[t('BM_SvarCopyTo', 6, 6)])} / "
      f"{fmt(cpu[t('BM_SvarWrite', 6, 6)])} = **{rw:.2f}** → {met(rw <= 0.5)}.")
    others = []
    for nelem in (32, 256):
        a = cpu[t("BM_SvarCopyFrom", nelem, 6)] / cpu[t("BM_SvarRead", nelem, 6)]
        b = cpu[t("BM_SvarCopyTo", nelem, 6)] / cpu[t("BM_SvarWrite", nelem, 6)]
        others.append(f"float[{nelem}]: {a:.2f} (read), {b:.2f} (write)")
    p(f"   For larger variables the copy itself dominates, as in the thesis (its savings: 53 %, 36 %, 9 %): "
      + "; ".join(others) + ".")
    tb = cpu["BM_TbufWriteRead/bytes:24/stamped:0"]
    tbs = cpu["BM_TbufWriteRead/bytes:24/stamped:1"]
    mx = cpu["BM_PthreadMutexWriteRead/bytes:24"]
    mx1 = cpu[t("BM_PthreadMutexMemcpy", 6, 1)]
    mxs = cpu["BM_PthreadMutexWriteReadStamped/bytes:24"]
    p(f"3. TBUF write+read ≤ pthread-mutex write+read of the same 24 B item: "
      f"like for like (both time-stamp the item) {fmt(tb)} / {fmt(mxs)} = **{tb / mxs:.2f}** → {met(tb <= mxs)}; "
      f"both without a clock read (stamp given) {fmt(tbs)} / {fmt(mx)} = **{tbs / mx:.2f}** → {met(tbs <= mx)}; "
      f"TBUF with its own stamp against the mutex without one {fmt(tb)} / {fmt(mx)} = {tb / mx:.2f} "
      f"(the clock read, {fmt(cpu['BM_MonotonicClock'])} ns here, is the difference). "
      f"(One mutex lock + memcpy + unlock alone: {fmt(mx1)} ns.)")
    print("\n".join(out))


if __name__ == "__main__":
    main()
