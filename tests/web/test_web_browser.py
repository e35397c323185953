"""The web console in a real browser (issue 17, item 8): headless Chromium
driven through Selenium against the running Fig 3.7 demo. The graph shows
Fig 3.7's tasks and edges, an on/off from the command line recolours the box,
a reconfiguration built on the page swaps PID for PID with gravity
compensation (and one verification refuses is shown refused first, with
nothing changed), a module spawned from the library appears as a box, the
scope plots four traces, triggers on a crossing and exports the captured
window as the stream delivered it, and a bad token is refused. Screenshots
go to WEB_SCREENSHOT_DIR."""

import csv
import io
import os
import shutil
import time

import pytest

from webharness import TOKEN, Master

webdriver = pytest.importorskip("selenium.webdriver")
from selenium.webdriver.chrome.service import Service  # noqa: E402
from selenium.webdriver.common.action_chains import ActionChains  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.common.exceptions import StaleElementReferenceException  # noqa: E402
from selenium.webdriver.support.ui import Select, WebDriverWait  # noqa: E402

CHROMEDRIVER = "/usr/bin/chromedriver"
SHOTS = os.environ.get("WEB_SCREENSHOT_DIR", ".")
DOWNLOADS = os.path.join(SHOTS, "downloads-%d" % os.getpid())
PROFILE = "/tmp/chimera-web-chrome-%d" % os.getpid()

if not os.path.exists(CHROMEDRIVER) or not (shutil.which("chromium") or os.path.exists("/usr/bin/chromium")):
    pytest.skip("chromium and chromium-driver are not installed", allow_module_level=True)


@pytest.fixture(scope="module")
def master():
    m = Master("b")
    yield m
    assert m.close() == 0


@pytest.fixture(scope="module")
def browser():
    opts = webdriver.ChromeOptions()
    opts.binary_location = "/usr/bin/chromium"
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1500,1300",
              "--user-data-dir=" + PROFILE):
        opts.add_argument(a)
    os.makedirs(DOWNLOADS, exist_ok=True)
    opts.add_experimental_option("prefs", {"download.default_directory": DOWNLOADS,
                                           "download.prompt_for_download": False})
    driver = webdriver.Chrome(service=Service(executable_path=CHROMEDRIVER), options=opts)
    driver.execute_cdp_cmd("Browser.setDownloadBehavior", {"behavior": "allow", "downloadPath": DOWNLOADS})
    yield driver
    driver.quit()
    shutil.rmtree(DOWNLOADS, ignore_errors=True)
    shutil.rmtree(PROFILE, ignore_errors=True)


def wait(driver, what, timeout=20):
    return WebDriverWait(driver, timeout, poll_frequency=0.1).until(lambda d: what(d))


# Read in one script call: the graph is redrawn whenever it changes, so an
# element found in one call may be gone by the next.
def box_state(driver, rmod):
    return driver.execute_script(
        "const b = document.querySelector('#graph g.task[data-rmod=\"' + arguments[0] + '\"]');"
        "return b ? b.dataset.state : null;", rmod)


def box_fill(driver, rmod):
    return driver.execute_script(
        "const r = document.querySelector('#graph g.task[data-rmod=\"' + arguments[0] + '\"] rect');"
        "return r ? getComputedStyle(r).fill : null;", rmod)


def edges(driver):
    return {tuple(e) for e in driver.execute_script(
        "return [...document.querySelectorAll('#graph path.edge')].map("
        "(e) => [e.dataset.var, e.dataset.from, e.dataset.to]);")}


def open_console(driver, master, token=TOKEN):
    driver.get("about:blank")  # a new document, not a fragment change
    driver.get(master.url + "#token=" + token)


def test_graph_shows_fig3_7(master, browser):
    open_console(browser, master)
    wait(browser, lambda d: len(d.find_elements(By.CSS_SELECTOR, "#graph g.task")) == 5)
    assert "token" not in browser.current_url  # dropped from the address bar
    states = {r: box_state(browser, r) for r in ("puma_torque", "jtraj", "jpid", "grav_comp", "jpidg")}
    assert states == {"puma_torque": "ON", "jtraj": "ON", "jpid": "ON", "grav_comp": "ON", "jpidg": "OFF"}
    e = edges(browser)
    # Fig 3.7: trajectory -> PID -> robot, the measured joints back to the PID.
    for edge in [("Q_REF", "jtraj", "jpid"), ("Q^_REF", "jtraj", "jpid"), ("T_REF", "jpid", "puma_torque"),
                 ("Q_MEZ", "puma_torque", "jpid"), ("Q^_MEZ", "puma_torque", "jpid"),
                 ("T_GRAV", "grav_comp", "jpidg"), ("Q_MEZ", "puma_torque", "grav_comp")]:
        assert edge in e, (edge, sorted(e))
    lanes = dict(browser.execute_script(
        "return [...document.querySelectorAll('#graph g.task')].map((b) => [b.dataset.rmod, b.dataset.rtpu]);"))
    assert lanes["puma_torque"] == "robot" and lanes["jpid"] == "ctrl"
    # The status table fills in (chimtop's fields).
    wait(browser, lambda d: len(d.find_elements(By.CSS_SELECTOR, "#status tr[data-rmod]")) == 5)
    browser.save_screenshot(os.path.join(SHOTS, "web-console-fig3_7.png"))


def test_on_off_from_the_command_line_recolours_the_box(master, browser):
    on_fill = box_fill(browser, "jpid")
    r = master.command_line("off jpid")
    assert r.returncode == 0, r.stderr
    wait(browser, lambda d: box_state(d, "jpid") == "OFF")
    assert box_fill(browser, "jpid") != on_fill
    browser.save_screenshot(os.path.join(SHOTS, "web-console-jpid-off.png"))
    r = master.command_line("on jpid")
    assert r.returncode == 0, r.stderr
    wait(browser, lambda d: box_state(d, "jpid") == "ON")
    assert box_fill(browser, "jpid") == on_fill


def add_item(driver, sig, rmod):
    Select(driver.find_element(By.ID, "rc-sig")).select_by_visible_text(sig)
    wait(driver, lambda d: choose(d, "rc-task", rmod))  # rebuilt on every graph push
    driver.find_element(By.ID, "rc-add").click()


def test_reconfig_from_the_page_swaps_pid_for_pid_with_gravity(master, browser):
    browser.find_element(By.ID, "control").click()
    wait(browser, lambda d: d.find_element(By.ID, "mode").text == "in control")
    # Turning jpidg on beside jpid gives T_REF two producers: refused, before anything changes.
    add_item(browser, "on", "jpidg")
    wait(browser, lambda d: "refused" in d.find_element(By.ID, "rc-verdict").text)
    assert "refused" in browser.find_element(By.ID, "rc-verdict").get_attribute("class")
    assert "T_REF is produced by both jpid and jpidg" in browser.find_element(By.ID, "rc-verdict").text
    assert not browser.find_element(By.ID, "rc-apply").is_enabled()
    assert box_state(browser, "jpidg") == "OFF" and box_state(browser, "jpid") == "ON"
    browser.save_screenshot(os.path.join(SHOTS, "web-console-reconfig-refused.png"))
    # The thesis's swap: off jpid, on jpidg, as one reconfig.
    browser.find_element(By.ID, "rc-clear").click()
    add_item(browser, "off", "jpid")
    add_item(browser, "on", "jpidg")
    wait(browser, lambda d: d.find_element(By.ID, "rc-verdict").text.startswith("verifies"))
    browser.find_element(By.ID, "rc-apply").click()
    wait(browser, lambda d: box_state(d, "jpidg") == "ON" and box_state(d, "jpid") == "OFF")
    e = edges(browser)
    assert ("T_REF", "jpidg", "puma_torque") in e
    wait(browser, lambda d: not d.find_elements(By.CSS_SELECTOR, "#graph g.problem"))
    browser.save_screenshot(os.path.join(SHOTS, "web-console-jpidg.png"))
    browser.find_element(By.ID, "control").click()
    wait(browser, lambda d: d.find_element(By.ID, "mode").text.startswith("watching"))


def test_spawn_from_the_library_shows_its_box(master, browser):
    open_console(browser, master)
    wait(browser, lambda d: len(d.find_elements(By.CSS_SELECTOR, "#library li[data-rmod=qmdiff]")) == 1)
    browser.find_element(By.ID, "control").click()
    wait(browser, lambda d: d.find_element(By.ID, "mode").text == "in control")
    try:
        browser.find_element(By.CSS_SELECTOR, "#library li[data-rmod=qmdiff]").click()
        wait(browser, lambda d: "qmdiff" in d.find_element(By.ID, "rmod-title").text)
        wait(browser, lambda d: choose(d, "spawn-rtpu", "ctrl"))  # rebuilt on every graph push
        browser.find_element(By.ID, "spawn").click()
        wait(browser, lambda d: box_state(d, "qmdiff") is not None)
        lanes = dict(browser.execute_script(
            "return [...document.querySelectorAll('#graph g.task')].map((b) => [b.dataset.rmod, b.dataset.rtpu]);"))
        assert lanes["qmdiff"] == "ctrl" and box_state(browser, "qmdiff") == "OFF"
        assert ("Q_MEZ", "puma_torque", "qmdiff") in edges(browser)
        browser.save_screenshot(os.path.join(SHOTS, "web-console-spawned.png"))
    finally:
        r = master_request(browser, "kill qmdiff")
        browser.find_element(By.ID, "control").click()
    assert r["ok"], r
    wait(browser, lambda d: box_state(d, "qmdiff") is None)


def master_request(driver, cmd):
    return driver.execute_async_script("request(arguments[0]).then(arguments[1]);", cmd)


# The page's own copy of every scope batch it receives, to check the export against.
RECORD_BATCHES = """
window.__scope = [];
ui.ws.addEventListener('message', (e) => { const m = JSON.parse(e.data); if (m.stream === 'scope') window.__scope.push(m.data); });
"""

TRACES = [("Q_REF", 0), ("Q_MEZ", 0), ("Q_REF", 1), ("Q_MEZ", 1)]


def add_trace(driver, var, element):
    Select(driver.find_element(By.ID, "sc-var")).select_by_visible_text(var)
    Select(driver.find_element(By.ID, "sc-elem")).select_by_visible_text(str(element))
    driver.find_element(By.ID, "sc-add").click()


def shown(driver):
    return driver.execute_script(
        "const s = sc.shown; return s && {t0: s.t0, t1: s.t1, tRef: s.tRef, triggered: s.triggered, n: s.data.n,"
        " t: s.data.t, v: s.data.v, points: sc.chart.data.datasets.map((d) => d.data.length),"
        " columns: sc.chart.chartArea.width};")


def stream_samples(driver):
    """Sample number -> (t ns, values) from every batch the page received."""
    out = {}
    for b in driver.execute_script("return window.__scope;"):
        for k, n in enumerate(b["n"]):
            assert n not in out, "sample %d delivered twice" % n
            out[n] = (b["t"][k], [col[k] for col in b["values"]])
    return out


def scope_task(master):
    """The sampler tasks running, with their RTPUs."""
    r = master.command_line("status all")
    assert r.returncode == 0, r.stderr
    return [tuple(line.split()[:2]) for line in r.stdout.splitlines() if line.startswith("sample.")]


def run_scope(browser):
    """Runs the scope as the page with control (starting one spawns a sampler
    task, issue #29.1), then watches again: the scope stays the page's."""
    browser.find_element(By.ID, "control").click()
    wait(browser, lambda d: d.find_element(By.ID, "mode").text == "in control")
    browser.find_element(By.ID, "sc-run").click()
    wait(browser, lambda d: d.find_element(By.ID, "sc-state").text not in ("off", "stopped"))
    browser.find_element(By.ID, "control").click()
    wait(browser, lambda d: d.find_element(By.ID, "mode").text.startswith("watching"))


def test_scope_plots_triggers_and_exports_the_stream(master, browser):
    open_console(browser, master)
    wait(browser, lambda d: len(d.find_elements(By.CSS_SELECTOR, "#sc-var option")) > 3)
    browser.execute_script(RECORD_BATCHES)
    for var, element in TRACES:
        add_trace(browser, var, element)
    names = ["%s[%d]" % t for t in TRACES]
    assert [li.get_attribute("data-trace") for li in browser.find_elements(By.CSS_SELECTOR, "#sc-traces li")] == names
    # Normal trigger: Q_REF[0] rising through 0.25 (jtraj's joint 0 swings 0 .. 0.5 rad).
    Select(browser.find_element(By.ID, "sc-tdiv")).select_by_value("0.1")
    Select(browser.find_element(By.ID, "sc-mode")).select_by_visible_text("normal")
    level = browser.find_element(By.ID, "sc-level")
    level.clear()
    level.send_keys("0.25")
    run_scope(browser)
    wait(browser, lambda d: (shown(d) or {}).get("triggered"), timeout=40)
    s = shown(browser)
    assert len(s["points"]) == 4 and all(p > 0 for p in s["points"])
    k = next(i for i, t in enumerate(s["t"]) if t >= s["tRef"])
    q = s["v"][0]
    assert q[k - 1] < 0.25 <= q[k], "the trigger sample is not a rising crossing of 0.25"
    assert abs((s["t1"] - s["t0"]) - 1.0) < 1e-9 and abs((s["tRef"] - s["t0"]) - 0.1) < 1e-9
    assert s["n"] == list(range(s["n"][0], s["n"][0] + len(s["n"]))), "the captured window has a gap"
    assert len(set(q)) > 1  # the trace changes
    browser.save_screenshot(os.path.join(SHOTS, "web-console-scope.png"))
    check_cursors(browser, s)
    check_export(browser, master, s, names)
    check_single(browser)
    check_decimation(browser)
    assert browser.find_element(By.ID, "sc-lost").text == "0"
    # Stopping the scope kills its sampler task; so does leaving the page.
    browser.find_element(By.ID, "sc-stop").click()
    wait(browser, lambda d: not scope_task(master), timeout=20)
    wait(browser, lambda d: choose(d, "sc-rtpu", "robot"))
    run_scope(browser)
    wait(browser, lambda d: scope_task(master), timeout=20)
    assert scope_task(master)[0][1] == "robot"
    browser.get("about:blank")
    wait(browser, lambda d: not scope_task(master), timeout=20)


def choose(driver, select_id, text):
    """Selects `text` in a <select> whose options the page may rebuild meanwhile
    (scopeRtpus() replaces them on every status push, keeping the value): an
    option found a moment before is then stale, so try again. True once chosen."""
    try:
        Select(driver.find_element(By.ID, select_id)).select_by_visible_text(text)
        return Select(driver.find_element(By.ID, select_id)).first_selected_option.text == text
    except StaleElementReferenceException:
        return False


def check_cursors(browser, s):
    chart = browser.find_element(By.ID, "scope-chart")
    width = chart.size["width"]
    for fraction in (0.3, 0.7):  # A, then B
        ActionChains(browser).move_to_element_with_offset(chart, int(width * (fraction - 0.5)), 0).click().perform()
    cursors = browser.execute_script("return sc.cursors;")
    assert None not in cursors and cursors[1] > cursors[0]
    dt = float(browser.find_element(By.CSS_SELECTOR, "#sc-readout td[data-dt]").get_attribute("data-dt"))
    # Δt between the captured samples nearest each cursor.
    near = [min(range(len(s["t"])), key=lambda k: abs(s["t"][k] - c)) for c in cursors]
    assert dt == s["t"][near[1]] - s["t"][near[0]] and dt > 0
    dv = browser.find_element(By.CSS_SELECTOR, "#sc-readout tr[data-row='Q_REF[0]'] td[data-dv]").get_attribute("data-dv")
    assert float(dv) == s["v"][0][near[1]] - s["v"][0][near[0]]


def check_export(browser, master, s, names):
    browser.find_element(By.ID, "sc-pause").click()  # the exported window is the one shown
    for f in os.listdir(DOWNLOADS):
        os.remove(os.path.join(DOWNLOADS, f))
    browser.find_element(By.ID, "sc-export").click()
    path = os.path.join(DOWNLOADS, "scope.csv")
    wait(browser, lambda d: os.path.exists(path) and os.path.getsize(path) > 0)
    time.sleep(0.5)
    text = open(path).read()
    rows = list(csv.reader(io.StringIO(text)))
    assert rows[0] == ["t"] + names
    # `record` writes the same columns.
    out = os.path.join(master.dir, "rec.csv")
    r = master.command_line("record %s 0.05s %s" % (" ".join(names), out))
    assert r.returncode == 0, r.stderr
    assert open(out).readline().strip() == ",".join(rows[0])
    # Every sample of the captured window, at full rate, as the stream gave it.
    stream = stream_samples(browser)
    assert len(rows) - 1 == len(s["n"]) > 400  # 1 s at 500 Hz, no decimation
    t0 = stream[s["n"][0]][0]
    for row, n in zip(rows[1:], s["n"]):
        t_ns, values = stream[n]
        assert float(row[0]) == (t_ns - t0) / 1e9
        assert [float(x) for x in row[1:]] == values
    assert rows[1][0] == "0"
    browser.find_element(By.ID, "sc-pause").click()


def check_single(browser):
    # Single: the newest complete crossing, captured once and held.
    Select(browser.find_element(By.ID, "sc-mode")).select_by_visible_text("single")
    wait(browser, lambda d: d.find_element(By.ID, "sc-state").text.startswith("single: captured"))
    held = shown(browser)
    assert held["triggered"]
    received = int(browser.find_element(By.ID, "sc-received").text)
    wait(browser, lambda d: int(d.find_element(By.ID, "sc-received").text) > received + 200)  # samples keep coming
    assert shown(browser)["t0"] == held["t0"]


def check_decimation(browser):
    # 0.5 s/div, auto: a 5 s window of 2500 samples, drawn as a min and a max per pixel column.
    Select(browser.find_element(By.ID, "sc-tdiv")).select_by_value("0.5")
    Select(browser.find_element(By.ID, "sc-mode")).select_by_visible_text("auto")
    wait(browser, lambda d: (shown(d) or {}).get("n") and len(shown(d)["n"]) > 2000, timeout=40)
    s = shown(browser)
    assert all(0 < p <= 2 * s["columns"] + 2 < len(s["n"]) for p in s["points"]), (s["points"], s["columns"])
    browser.save_screenshot(os.path.join(SHOTS, "web-console-scope-5s.png"))


# std::to_chars (what `record` writes) of each number, printed by a C++ program.
TO_CHARS = [(0.1, "0.1"), (1e-5, "1e-05"), (100000, "1e+05"), (123456, "123456"), (1.5e-7, "1.5e-07"),
            (0.001, "0.001"), (1234567.0, "1234567"), (1e21, "1e+21"), (-2.5, "-2.5"), (0.0001, "1e-04"),
            (1000, "1000"), (0.002012614, "0.002012614"), (-0.058457953069322, "-0.058457953069322"),
            (1e100, "1e+100"), (5e-324, "5e-324"), (0.30000000000000004, "0.30000000000000004"),
            (120000, "120000"), (1.25e-3, "0.00125"), (0, "0")]


def test_scope_csv_numbers_are_written_as_record_writes_them(master, browser):
    open_console(browser, master)
    wait(browser, lambda d: d.execute_script("return typeof cppNumber === 'function';"))
    got = browser.execute_script("return arguments[0].map(cppNumber);", [v for v, _ in TO_CHARS])
    assert got == [text for _, text in TO_CHARS]


def test_bad_token_is_refused(master, browser):
    open_console(browser, master, token="not-the-token")
    wait(browser, lambda d: "wrong token" in d.find_element(By.ID, "login-error").text)
    assert not browser.find_element(By.ID, "console").is_displayed()
    browser.save_screenshot(os.path.join(SHOTS, "web-console-bad-token.png"))
