"""The web console in a real browser (issue 17, item 8): headless Chromium
driven through Selenium against the running Fig 3.7 demo. The graph shows
Fig 3.7's tasks and edges, an on/off from the command line recolours the box,
a reconfiguration built on the page swaps PID for PID with gravity
compensation (and one verification refuses is shown refused first, with
nothing changed), and a bad token is refused. Screenshots go to
WEB_SCREENSHOT_DIR."""

import os
import shutil

import pytest

from webharness import TOKEN, Master

webdriver = pytest.importorskip("selenium.webdriver")
from selenium.webdriver.chrome.service import Service  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import Select, WebDriverWait  # noqa: E402

CHROMEDRIVER = "/usr/bin/chromedriver"
SHOTS = os.environ.get("WEB_SCREENSHOT_DIR", ".")

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
              "--user-data-dir=/tmp/chimera-web-chrome-%d" % os.getpid()):
        opts.add_argument(a)
    driver = webdriver.Chrome(service=Service(executable_path=CHROMEDRIVER), options=opts)
    yield driver
    driver.quit()


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
    Select(driver.find_element(By.ID, "rc-task")).select_by_visible_text(rmod)
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


def test_bad_token_is_refused(master, browser):
    open_console(browser, master, token="not-the-token")
    wait(browser, lambda d: "wrong token" in d.find_element(By.ID, "login-error").text)
    assert not browser.find_element(By.ID, "console").is_displayed()
    browser.save_screenshot(os.path.join(SHOTS, "web-console-bad-token.png"))
