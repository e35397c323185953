#!/usr/bin/python3
"""Release lateness of the Fig 3.7 demo's tasks with 0 and with 5 web console
pages open, in the same run (issue 17.7). The master is `sbs --serve --http`
(tests/web/webharness.py); the pages are real ones, tabs of one headless
Chromium polling status every 0.25 s and receiving the graph stream. The
lateness is the status field latP99 (release lateness's 99th percentile in a
window, docs/prof.md), read through the master's Unix socket, whose status
window is its own (the pages' requests do not reset it). Rounds alternate
0 and 5 pages so both see the same machine load; the figure per task is the
median over rounds. With --scope each page also runs a scope of four traces
(issue 17.5): its own sampler task at 500 Hz on the master's RTPU, streamed
to the page and drawn at 25 frames/s, so the figure includes the sampler
tasks' own share of the RTPU.

    SBS_EXE=build/tools/sbs/sbs FIG3_7_DIR=examples/fig3_7_pid \\
        /usr/bin/python3 bench/web/bench_web.py --rounds 5 --seconds 10 [--scope]
"""

import argparse
import json
import os
import socket
import statistics
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "tests", "web"))
from webharness import TOKEN, Master  # noqa: E402

from selenium import webdriver  # noqa: E402
from selenium.webdriver.chrome.service import Service  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import Select, WebDriverWait  # noqa: E402

TASKS = ["puma_torque", "jtraj", "jpid", "grav_comp"]


class UnixPeer:
    """The network interface's peer on the master's Unix socket: one JSON line per request."""

    def __init__(self, path):
        self.s = socket.socket(socket.AF_UNIX)
        self.s.connect(path)
        self.f = self.s.makefile("rw")
        hello = json.loads(self.f.readline())
        if not hello["ok"]:
            raise RuntimeError(hello)

    def request(self, cmd):
        self.f.write(cmd + "\n")
        self.f.flush()
        return json.loads(self.f.readline())


def browser(n):
    opts = webdriver.ChromeOptions()
    opts.binary_location = "/usr/bin/chromium"
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
              "--window-size=1400,1100", "--user-data-dir=/tmp/chimera-web-bench-%d" % os.getpid()):
        opts.add_argument(a)
    d = webdriver.Chrome(service=Service(executable_path="/usr/bin/chromedriver"), options=opts)
    handles = [d.current_window_handle]
    for _ in range(n - 1):
        d.switch_to.new_window("tab")
        handles.append(d.current_window_handle)
    return d, handles


def open_pages(d, handles, url, scope):
    for h in handles:
        d.switch_to.window(h)
        d.get(url + "#token=" + TOKEN)
        WebDriverWait(d, 30).until(lambda d: len(d.find_elements(By.CSS_SELECTOR, "#status tr[data-rmod]")) >= 4)
        Select(d.find_element(By.ID, "status-rate")).select_by_value("250")
        if scope:
            run_scope(d)


def run_scope(d):
    WebDriverWait(d, 30).until(lambda d: len(d.find_elements(By.CSS_SELECTOR, "#sc-var option")) > 3)
    for var, element in (("Q_REF", "0"), ("Q_MEZ", "0"), ("Q_REF", "1"), ("Q_MEZ", "1")):
        Select(d.find_element(By.ID, "sc-var")).select_by_visible_text(var)
        Select(d.find_element(By.ID, "sc-elem")).select_by_visible_text(element)
        d.find_element(By.ID, "sc-add").click()
    d.find_element(By.ID, "sc-run").click()
    WebDriverWait(d, 30).until(lambda d: int(d.find_element(By.ID, "sc-received").text) > 0)


def close_pages(d, handles):
    for h in handles:
        d.switch_to.window(h)
        d.get("about:blank")


def window(peer, seconds):
    peer.request("status all")  # starts this peer's window
    time.sleep(seconds)
    rows = peer.request("status all")["data"]["tasks"]
    return {r["rmod"]: r.get("latP99") for r in rows}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=10)
    ap.add_argument("--pages", type=int, default=5)
    ap.add_argument("--scope", action="store_true", help="each page runs a scope of four traces")
    a = ap.parse_args()
    master = Master("bench")
    try:
        peer = UnixPeer(os.path.join(master.dir, "chimera", master.name + ".sock"))
        d, handles = browser(a.pages)
        samples = {0: {t: [] for t in TASKS}, a.pages: {t: [] for t in TASKS}}
        try:
            for r in range(a.rounds):
                for pages in (0, a.pages):
                    if pages:
                        open_pages(d, handles, master.url, a.scope)
                    else:
                        close_pages(d, handles)
                    time.sleep(1)
                    w = window(peer, a.seconds)
                    for t in TASKS:
                        if w.get(t) is not None:
                            samples[pages][t].append(w[t])
                    print("round %d, %d pages: %s" % (r, pages, {t: w.get(t) for t in TASKS}), file=sys.stderr)
        finally:
            d.quit()
        print("| task | latP99 0 pages [µs] | latP99 %d pages [µs] | ratio | difference [µs] | within +10 %% or +5 µs |"
              % a.pages)
        print("|---|---|---|---|---|---|")
        for t in TASKS:
            m0, m5 = statistics.median(samples[0][t]), statistics.median(samples[a.pages][t])
            ok = m5 <= m0 * 1.10 or m5 <= m0 + 5
            print("| %s | %.1f | %.1f | %.3f | %+.1f | %s |" % (t, m0, m5, m5 / m0 if m0 else float("nan"), m5 - m0,
                                                               "yes" if ok else "NO"))
        print("\nper round (µs): " + json.dumps(samples), file=sys.stderr)
        peer.request("quit")
    finally:
        master.close()


if __name__ == "__main__":
    main()
