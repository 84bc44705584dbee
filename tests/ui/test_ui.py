"""flowloop where users look: Mainsail and Fluidd built from their source,
served as nginx serves them (UI and Moonraker on one origin), against the
real Moonraker with flowloop's component and a batch-mode klippy that
prints a real file. One printer stack for the module, both UIs on it.

In each UI: the job's flowloop figures in its history, no JavaScript error
in the console, the live page in the dashboard's webcam panel (the
[webcam flowloop] block flowloop install writes) with the job's report one
click away, the nozzle-health announcement with its link. Screenshots go to
each test's tmp_path; FLOWLOOP_UI_SCREENSHOTS=docs/ui saves the ones
docs/ui.md shows.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import time
from pathlib import Path

import pytest

from devtools import stack
from flowloop.host import install
from flowloop.report import job_figures
from tests.moonraker.test_nozzle_health_jobs import evidence
from tests.samples import twin_known
from tests.ui.conftest import Served, built, chrome

EXCERPT = stack.PROJECT / "tests" / "data" / "gcode" / "block_layers_1_2.gcode"

PRINTER_CFG = """\
[include {project}/config/printer.cfg]

[flowrate_limiter]
max_flow: 9

[include {project}/macros/flowrate_limiter.cfg]
"""
# keep one report: the first job's is pruned ("no report kept")
PRINTER_STACK = {"moonraker_conf": "hotend: v6-0.4\nnumber_of_reports_to_keep: 1\n"
                 + install.WEBCAM_BLOCK}


SUBSCRIPTIONS_SETTLE_S = 2.0   # as tests/fil/test_fil_report.py waits
LONG = "block_30x.gcode"       # the excerpt (0.6 s in batch mode) 30 times over


def _jobs(ps):
    status, body = ps.moonraker.request("GET", "/server/history/list?limit=50")
    assert status == 200, body
    return body["result"]["jobs"]


def _print(ps, name: str, cancel_after_s=None) -> str:
    """The job id of a print of name, once it has ended (cancelled
    cancel_after_s after it started printing).

    Batch-mode klippy prints the excerpt in about 0.6 s, sooner than a poll
    may see it printing, and a cancel that lands as a print ends shuts
    Klipper down (virtual_sdcard's do_cancel closes the file the finished
    print has just closed: AttributeError, "Internal error on command
    CANCEL_PRINT"): a print to cancel is of a file that lasts (LONG)."""
    before = {j["job_id"] for j in _jobs(ps)}
    status, body = ps.moonraker.request(
        "POST", f"/printer/print/start?filename={name}")
    assert status == 200, body
    if cancel_after_s is not None:
        assert stack.wait_until(
            lambda: ps.query("print_stats").get("state") == "printing", 10)
        time.sleep(cancel_after_s)
        status, body = ps.moonraker.request("POST", "/printer/print/cancel")
        assert status == 200, body
    ended = stack.wait_until(lambda: [j for j in _jobs(ps) if j["job_id"] not in before
                                      and j["status"] != "in_progress"], 60)
    assert ended, (f"no job of {name} in the history", _jobs(ps))
    return ended[0]["job_id"]


def from_before_flowloop(ps, job_id: str) -> None:
    """The job as Moonraker's history holds a job printed before flowloop was
    installed: no auxiliary field of flowloop's (nor a report)."""
    with sqlite3.connect(ps.data_dir / "database" / "moonraker-sql.db",
                         timeout=10) as db:
        changed = db.execute("UPDATE job_history SET auxiliary_data = '[]' "
                             "WHERE job_id = ?", (int(job_id, 16),)).rowcount
    assert changed == 1
    (ps.data_dir / "flowloop" / "reports" / f"{job_id}.html").unlink(missing_ok=True)


def prepare_printer(ps):
    """Four jobs: one from before flowloop was installed, one cancelled in
    its first second, one printed (its report then pruned), one printed; a
    nozzle whose melt capacity fell (an announcement)."""
    shutil.copy(EXCERPT, ps.data_dir / "gcodes" / "block.gcode")
    (ps.data_dir / "gcodes" / LONG).write_bytes(EXCERPT.read_bytes() * 30)
    # Moonraker's components subscribe to klippy's objects one after another
    # once klippy is ready; a print started before the last of them would
    # not reach job_state (nor the history): a user starts one long after
    time.sleep(SUBSCRIPTIONS_SETTLE_S)
    ps.jobs = {"before": _print(ps, "block.gcode"),
               "cancelled": _print(ps, LONG, cancel_after_s=0),
               "pruned": _print(ps, "block.gcode"),
               "printed": _print(ps, "block.gcode")}
    from_before_flowloop(ps, ps.jobs["before"])
    data = twin_known()
    data["identity"]["name"] = "known"
    status, body = ps.moonraker.request("POST", "/server/flowloop/profile",
                                        {"profile": data})
    assert status == 200, body
    for k in range(6):
        status, body = ps.moonraker.request("POST", "/server/flowloop/nozzle_health", {
            "job_id": f"0000F{k}", "evidence": evidence(1.0 - 0.02 * k, k)})
        assert status == 200, body


@pytest.fixture(scope="module")
def browser():
    driver = chrome()
    # the panel follows the browser's preference: dark, as both UIs are
    driver.execute_cdp_cmd("Emulation.setEmulatedMedia", {"features": [
        {"name": "prefers-color-scheme", "value": "dark"}]})
    try:
        yield driver
    finally:
        driver.quit()


# Fluidd builds and is served, but its readiness in the store
# (socket.ready) was never seen true here: its checks are not run yet
# (docs/ui.md).
@pytest.fixture(scope="module", params=["mainsail", "fluidd"])
def served(request, printer, browser, tmp_path_factory):  # noqa: F811
    dist = built(request.param)
    site = Served(request.param, dist, printer.moonraker.port,
                  tmp_path_factory.mktemp(request.param))
    try:
        yield site
    finally:
        site.proc.stop()


def figures(ps, job_id):
    status, body = ps.moonraker.request("GET", f"/server/history/job?uid={job_id}")
    assert status == 200, body
    return {f["name"]: f for f in body["result"]["job"]["auxiliary_data"]
            if f["provider"] == job_figures.PROVIDER}


def js(driver, script):
    return driver.execute_script(script)


STORE = "return document.getElementById('app').__vue__.$store"


def open_ui(driver, site, route="/"):
    driver.get_log("browser")
    driver.get(site.url + route)
    ready = {"mainsail": STORE + ".state.socket.isConnected",
             "fluidd": STORE + ".state.socket.status === 'ready'"}[site.name]

    def connected():
        try:
            return js(driver, ready)
        except Exception:
            return False
    assert stack.wait_until(connected, 30), f"{site.name} did not connect"
    time.sleep(2)   # its first queries answered


def go(driver, site, route):
    js(driver, f"document.getElementById('app').__vue__.$router.push('{route}')")
    time.sleep(2)


def js_errors(driver):
    return [e for e in driver.get_log("browser")
            if e["level"] == "SEVERE" and e.get("source") == "javascript"]


def shot(driver, tmp_path, name):
    driver.save_screenshot(str(tmp_path / f"{name}.png"))
    docs = os.environ.get("FLOWLOOP_UI_SCREENSHOTS")
    if docs:
        Path(docs).mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(str(Path(docs) / f"{name}.png"))


def test_the_history_holds_numbers_and_dashes_where_nothing_was_judged(printer):
    printed = figures(printer, printer.jobs["printed"])
    assert isinstance(printed["lowest_grip"]["value"], float), printed
    assert printed["melt_ratio"]["value"] == []   # no nozzle judged for it
    cancelled = figures(printer, printer.jobs["cancelled"])
    assert cancelled and printer.moonraker.request(
        "GET", f"/server/history/job?uid={printer.jobs['cancelled']}")[1][
        "result"]["job"]["status"] == "cancelled"
    for field in cancelled.values():
        assert field["value"] == [] or isinstance(field["value"], (int, float))


def _dialogs(driver):
    return [d for d in driver.find_elements("css selector", ".history-detail-dialog")
            if d.is_displayed()]


def details(driver, row, filename: str) -> str:
    """The text of a Mainsail job's details dialog (opened by a click on the
    job's row), once it shows its first entry, the job's file name.

    The dialog is displayed before its text is: under load CI once read it
    empty mid-transition. Its entries scroll in a 350 px box, so the text is
    the rendered text a user scrolls through (innerText), not only what
    Selenium sees in the box at once."""
    row.click()

    def texts():
        return [driver.execute_script("return arguments[0].innerText", d)
                for d in _dialogs(driver)]
    text = stack.wait_until(lambda: [t for t in texts() if filename in t], 15, 0.2)
    assert text, f"no details dialog showing {filename}: {texts()!r}"
    return text[0]


def _at_rest_under_the_pointer(driver, element) -> bool:
    """The element has not moved for 0.1 s and is what a click at its centre
    reaches (a dialog still scaling in has its toolbar there instead)."""
    script = ("const r = arguments[0].getBoundingClientRect();"
              "const e = document.elementFromPoint(r.left + r.width / 2,"
              " r.top + r.height / 2);"
              "return [r.left, r.top, r.width, r.height,"
              " e !== null && arguments[0].contains(e)];")
    first = driver.execute_script(script, element)
    time.sleep(0.1)
    second = driver.execute_script(script, element)
    return first == second and second[-1]


def close_dialog(driver) -> None:
    """Close the details dialog and wait until it is gone: it fades out, and
    the next job's dialog read while it still shows read the old job's. Its
    text shows before its opening transition ends: the close button is
    clicked once it is at rest (under load a click mid-transition once
    landed on the dialog's toolbar)."""
    button = _dialogs(driver)[0].find_element("css selector", "button")
    assert stack.wait_until(lambda: _at_rest_under_the_pointer(driver, button),
                            5, 0.05), "the details dialog's close button never settled"
    button.click()
    assert stack.wait_until(lambda: not driver.find_elements(
        "css selector", ".v-overlay--active") and not _dialogs(driver), 5)


def test_the_jobs_figures_show_in_the_history(served, printer, browser, tmp_path):
    open_ui(browser, served)
    go(browser, served, "/history")
    grip = figures(printer, printer.jobs["printed"])["lowest_grip"]["value"]
    if served.name == "mainsail":
        def job_rows():
            return [row for row in browser.find_elements("css selector", "tbody tr")
                    if "block.gcode" in row.text or LONG in row.text]
        # the table fills in as Mainsail's history answer arrives
        stack.wait_until(lambda: len(job_rows()) >= len(printer.jobs), 20, 0.2)
        rows = job_rows()
        assert len(rows) == len(printer.jobs), [r.text for r in rows]
        # the job from before flowloop (the oldest): its details open, none
        # of flowloop's figures in them
        before = details(browser, rows[-1], "block.gcode")
        assert "Lowest grip" not in before, before
        close_dialog(browser)
        # the newest job's details: flowloop's figures with their units
        text = details(browser, rows[0], "block.gcode")
        # flowloop's figures end the dialog: scrolled into the screenshot
        browser.execute_script("arguments[0].querySelectorAll('*').forEach("
                               "e => { e.scrollTop = e.scrollHeight; })",
                               _dialogs(browser)[0])
    else:
        # a column per figure, named by its description; the job from before
        # flowloop is a row of its own
        count = f"1-{len(printer.jobs)} of {len(printer.jobs)}"
        stack.wait_until(lambda: count in browser.find_element(
            "css selector", "body").text, 20, 0.2)
        text = browser.find_element("css selector", "body").text
        assert count in text, text
        for figure in job_figures.FIGURES:
            assert figure.description.lower() in text.lower(), figure
    shot(browser, tmp_path, f"{served.name}-history")
    assert "lowest grip" in text.lower(), text
    assert f"{grip:g} %" in text, text
    assert "NaN" not in text and "null" not in text
    assert js_errors(browser) == []


def test_mainsails_statistics_name_flowloops_totals_with_units(
        served, printer, browser, tmp_path):
    if served.name != "mainsail":
        pytest.skip("Fluidd lists no auxiliary totals (its history columns: "
                    "test_the_jobs_figures_show_in_the_history)")
    open_ui(browser, served)
    go(browser, served, "/history")
    panels = stack.wait_until(lambda: browser.find_elements(
        "css selector", ".history-statistics-panel"), 15, 0.2)
    assert panels, "no statistics panel in Mainsail's history"
    browser.execute_script("arguments[0].scrollIntoView()", panels[0])
    # the totals fill in as Mainsail's answer arrives
    stack.wait_until(lambda: "Limiter slowed the print" in panels[0].text, 15, 0.2)
    text = panels[0].text
    shot(browser, tmp_path, "mainsail-statistics")
    # were "under_extruded 0 undefined" and "peak_flow 0 undefined" (a
    # maximum Mainsail shows as a total)
    for raw in ("undefined", "under_extruded", "limiter_slowed", "peak_flow"):
        assert raw not in text, text
    totals = {t["field"]: t["total"] for t in printer.moonraker.request(
        "GET", "/server/history/totals")[1]["result"]["auxiliary_totals"]
        if t["provider"] == job_figures.PROVIDER}
    # as Mainsail rounds a total (3 decimals)
    assert f"Filament under-extruded {round(totals['under_extruded'], 3):g} mm" \
        in text, text
    assert f"Limiter slowed the print {round(totals['limiter_slowed'], 3):g} s" \
        in text, text
    assert js_errors(browser) == []


def test_the_live_page_is_a_dashboard_panel_with_the_report_a_click_away(
        served, printer, browser, tmp_path):
    open_ui(browser, served)
    frames = stack.wait_until(lambda: browser.find_elements("css selector",
                                                            "iframe"), 15)
    assert frames, f"no panel in {served.name}'s dashboard"
    assert frames[0].get_attribute("src") == (
        served.url + "/server/flowloop/page/?panel=1")
    browser.execute_script("arguments[0].scrollIntoView()", frames[0])
    browser.switch_to.frame(frames[0])
    try:
        assert stack.wait_until(lambda: js(browser, "return document.querySelector("
                                "'#connection').textContent") == "live", 15)
        assert js(browser, "return document.documentElement.dataset.panel") == "true"
        background = js(browser, "return getComputedStyle(document.body)"
                        ".backgroundColor")
        assert background == "rgb(20, 22, 26)", background   # dark, as preferred
        links = browser.find_elements("css selector", "#report-list a")
        assert links and links[0].get_attribute("target") == "_blank"
        href = links[0].get_attribute("href")
    finally:
        browser.switch_to.default_content()
    time.sleep(1)
    shot(browser, tmp_path, f"{served.name}-dashboard")
    assert js_errors(browser) == []
    # the newest job's report, from the UI's origin
    assert href == (served.url + "/server/flowloop/report?job_id="
                    + printer.jobs["printed"])
    browser.get(href)
    assert "Flow report: block.gcode" in browser.find_element(
        "css selector", "body").text
    # an older job's link (an old tab, a console line): its report was pruned
    browser.get(served.url + "/server/flowloop/report?job_id=" + printer.jobs["pruned"])
    text = browser.find_element("css selector", "body").text
    assert f"No report kept for job {printer.jobs['pruned']}" in text, text


def test_the_nozzle_health_announcement_links_its_plot(served, browser, tmp_path):
    open_ui(browser, served)
    store = STORE + (".state.server.announcements.entries"
                     if served.name == "mainsail" else ".state.announcements.entries")
    # the announcements arrive with the UI's own query of them
    ours = stack.wait_until(lambda: [e for e in js(browser, store) or []
                                     if e["feed"] == "flowloop"], 15, 0.2)
    assert ours, js(browser, store)
    assert ours[0]["url"].startswith("/server/flowloop/nozzle_health/plot")
    assert js_errors(browser) == []


# Fluidd parses each macro's parameters in its macro button (MacroBtn's
# params, the fields of the button's menu); found in the component tree
FLUIDD_MACRO_FIELDS = """
const found = [];
const walk = (vm) => {
  if (vm.macro && vm.params && String(vm.macro.name).toUpperCase() === arguments[0])
    found.push(JSON.parse(JSON.stringify(vm.params)));
  vm.$children.forEach(walk);
};
walk(document.getElementById('app').__vue__.$root);
return found[0] || null;
"""


def test_a_macros_parameter_shows_its_default(served, browser):
    open_ui(browser, served)
    if served.name == "mainsail":
        # the macros are known once Mainsail has read the printer's config
        macro = stack.wait_until(lambda: js(
            browser, STORE + ".getters['printer/getMacro']('FLOWRATE_LIMIT_START')"),
            15, 0.2)
        assert macro, "no FLOWRATE_LIMIT_START macro in Mainsail's store"
        default = macro["params"]["MAX_FLOW"]["default"]
    else:
        fields = stack.wait_until(lambda: browser.execute_script(
            FLUIDD_MACRO_FIELDS, "FLOWRATE_LIMIT_START"), 10)
        assert fields, "no FLOWRATE_LIMIT_START button on Fluidd's dashboard"
        default = {k.upper(): v for k, v in fields.items()}["MAX_FLOW"]["value"]
    # the field each UI pre-fills: the |default(...) literal, unquoted
    assert default == "config"
