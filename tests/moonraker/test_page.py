"""The live page (/server/flowloop/page/) in a real browser: headless
Chromium from Debian driven by selenium, against the real Moonraker and a
batch-mode klippy with the simulated sensor, a flowrate limiter and autotemp.

It checks what a user relies on: the timeline fills with samples, the numbers
on the page are the printer objects' numbers, nothing is loaded from outside
127.0.0.1, no console errors, the page carries on after klippy restarts, and
bad input reads as words where the chart would be. On klippy paced to the
clock (devtools/realtime_klippy.py) the page moves while a real slicer
file prints; FLOWLOOP_PAGE_SCREENSHOT=docs/page.png saves that view, the
screenshot docs/page.md shows.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from devtools import browser as browser_tools
from devtools import stack
from flowloop.gcode.annotate import annotate_file
from tests.moonraker.conftest import stack_with_cfg
from tests.samples import make

PROJECT = stack.PROJECT
EXCERPT = PROJECT / "tests" / "data" / "gcode" / "block_layers_1_2.gcode"

# klippy's config in the printer fixture (tests/moonraker/conftest.py)
PRINTER_CFG = """\
[include {project}/config/printer.cfg]

[flow_sensor_simulation sim]
heater_power: 40

[flowrate_limiter]
max_flow: 9

[autotemp]

# a second extruder with no sensor and no profile: the page says so
[extruder1]
step_pin: PC1
dir_pin: PC3
enable_pin: !PC7
microsteps: 16
rotation_distance: 33.5
nozzle_diameter: 0.400
filament_diameter: 1.750
heater_pin: PH6
sensor_type: EPCOS 100K B57560G104F
sensor_pin: PK7
control: pid
pid_Kp: 22.2
pid_Ki: 1.08
pid_Kd: 114
min_temp: 0
max_temp: 260
"""


def _chrome():
    reason = browser_tools.missing_reason()
    if reason:
        pytest.skip(reason)
    return browser_tools.chrome(1400, 1100, performance_log=True)


@pytest.fixture(scope="module")
def browser():
    driver = _chrome()
    try:
        yield driver
    finally:
        driver.quit()


@pytest.fixture
def own_browser(browser):
    """A browser of its own, for a test that changes how its clock runs
    (after the shared one: a missing chromium skips before any stack starts)."""
    driver = _chrome()
    try:
        yield driver
    finally:
        driver.quit()


def prepare_printer(ps):
    """The printer fixture's files to print (tests/moonraker/conftest.py;
    its klippy runs PRINTER_CFG)."""
    gcodes = ps.data_dir / "gcodes"
    annotate_file(EXCERPT, gcodes / "annotated.gcode")
    shutil.copy(EXCERPT, gcodes / "plain.gcode")


def page_url(ps, extruder=None):
    url = ps.moonraker.url + "/server/flowloop/page/"
    return url + (f"?extruder={extruder}" if extruder else "")


def open_page(driver, url):
    """Load url, the browser's logs emptied first: each test judges its own."""
    driver.get_log("browser"), driver.get_log("performance")
    driver.get(url)


def js(driver, script):
    return driver.execute_script(script)


def wait_for(driver, script, timeout=20.0):
    """The value of a JavaScript expression once it is true."""
    value = stack.wait_until(lambda: js(driver, "return " + script), timeout, 0.2)
    assert value, f"never true: {script}\n{page_state(driver)}"
    return value


def page_state(driver):
    return js(driver, "return document.body.innerText")


FIELD = "document.querySelector('td[data-field=\"{}\"]')"


def field(driver, name):
    return js(driver, f"return {FIELD.format(name)}.dataset.value")


def message(driver, chart):
    return js(driver, f"return document.getElementById('{chart}').dataset.message")


def severe_console(driver):
    return [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]


def request_urls(driver):
    """Every URL the page asked for since the last call (DevTools log)."""
    urls = []
    for entry in driver.get_log("performance"):
        msg = json.loads(entry["message"])["message"]
        if msg["method"] == "Network.requestWillBeSent":
            urls.append(msg["params"]["request"]["url"])
        elif msg["method"] == "Network.webSocketCreated":
            urls.append(msg["params"]["url"])
    return urls


def activate_profile(ps, name="page-pla"):
    for path, body in (("/server/flowloop/profile", {"profile": make(name=name)}),
                       ("/server/flowloop/profile/activate",
                        {"name": name, "extruder": "extruder",
                         "working_point": 0.5})):
        status, answer = ps.moonraker.request("POST", path, body)
        assert status == 200, answer


def test_the_page_shows_the_printer_objects_numbers_live(browser, printer):
    activate_profile(printer)
    printer.gcode("SET_HEATER_TEMPERATURE HEATER=extruder TARGET=205\n"
                  "SET_FLOWRATE_LIMIT MAX_FLOW=7.5")
    open_page(browser, page_url(printer))
    wait_for(browser, "document.getElementById('connection').dataset.state == 'live'")
    samples = int(wait_for(
        browser, "+document.getElementById('flow-chart').dataset.samples > 2 && "
                 "document.getElementById('flow-chart').dataset.samples"))
    assert samples > 2
    # an extrusion: the sensor, the limiter (its temperature cap follows the
    # twin's cold nozzle) and the heater all change
    printer.gcode("G28\nM83\nG1 E20 F300\nM400")
    sensor = printer.query("flow_sensor sim")
    limiter = printer.query("flowrate_limiter")
    heater = printer.query("extruder")
    for name, value in (("commanded_flow", sensor["commanded_flow"]),
                        ("measured_flow", sensor["measured_flow"]),
                        ("cap", limiter["cap"]), ("target", heater["target"])):
        assert value is not None
        wait_for(browser, f"Math.abs(+{FIELD.format(name)}.dataset.value - {value})"
                          f" < 1e-6")
    assert float(field(browser, "commanded_flow")) > 0
    assert field(browser, "reason") == limiter["reason"]
    autotemp = printer.query("autotemp")
    assert field(browser, "source") == (autotemp["source"] or "")
    # the profile's lines are drawn, the operating point with them
    assert message(browser, "profile-chart") == ""
    assert "page-pla" in js(browser, "return document.getElementById('profile-name')"
                                     ".textContent")
    assert js(browser, "return !!document.querySelector('#profile-chart canvas')")
    assert severe_console(browser) == []
    outside = [u for u in request_urls(browser)
               if not u.startswith((printer.moonraker.url,
                                    printer.moonraker.url.replace("http", "ws", 1),
                                    "data:"))]
    assert outside == []


def legend(driver, chart):
    """{label: (shown value, marker colour)} of a chart's legend."""
    return js(driver, f"""
        const out = {{}};
        for (const row of document.querySelectorAll('#{chart} .u-legend .u-series')) {{
          const marker = row.querySelector('.u-marker');
          out[row.querySelector('.u-label').textContent] = [
            row.querySelector('.u-value').textContent,
            marker ? getComputedStyle(marker).borderTopColor : null];
        }}
        return out;""")


def legend_value(chart, label):
    """JavaScript: the value a chart's legend shows for one series."""
    return (f"[...document.querySelectorAll('#{chart} .u-legend .u-series')]"
            f".find((row) => row.querySelector('.u-label').textContent == "
            f"'{label}').querySelector('.u-value').textContent")


def rgb(color):
    return "rgb({}, {}, {})".format(*(int(color[i:i + 2], 16) for i in (1, 3, 5)))


def test_the_charts_show_now_in_the_plots_colours_on_a_readable_scale(browser,
                                                                      printer):
    from flowloop.material.plot import COLORS
    activate_profile(printer)
    printer.gcode("SET_HEATER_TEMPERATURE HEATER=extruder TARGET=205")
    open_page(browser, page_url(printer))
    wait_for(browser, "+document.getElementById('temp-chart').dataset.samples > 4 && "
                      "!!document.querySelector('#profile-chart canvas')")
    # no hover: every legend shows the value now, not uPlot's "--"
    wait_for(browser, "document.querySelector('#temp-chart .u-legend')"
                      ".innerText.includes('205.0')")
    temp = legend(browser, "temp-chart")
    assert temp["target"][0] == "205.0"
    assert temp["temperature"][0] == f"{float(field(browser, 'temperature')):.1f}"
    # the commanded flow (a number even when idle) as the readout has it
    wait_for(browser, f"{legend_value('flow-chart', 'commanded')} == "
                      f"(+{FIELD.format('commanded_flow')}.dataset.value).toFixed(2)")
    profile = legend(browser, "profile-chart")
    # a steady hotend: the axis spans 10 C around it, not its 0.1 C of noise
    low, high = map(float, js(browser, "return document.getElementById("
                                       "'temp-chart').dataset.yRange").split(","))
    assert high - low >= 10 - 1e-9
    # the page's colours are the CLI plots' colours
    assert profile["into air"][1] == rgb(COLORS["into_air"])
    assert profile["real print"][1] == rgb(COLORS["real_print"])
    assert profile["working point 0.5"][1] == rgb(COLORS["working"])
    assert temp["target"][1] == rgb(COLORS["target"])
    assert severe_console(browser) == []


def screenshot(driver):
    """Saved where FLOWLOOP_PAGE_SCREENSHOT says (docs/page.png for the docs)."""
    shot = os.environ.get("FLOWLOOP_PAGE_SCREENSHOT")
    if shot:
        Path(shot).parent.mkdir(parents=True, exist_ok=True)
        driver.set_window_size(1400, 1500)
        assert driver.save_screenshot(shot)
        driver.set_window_size(1400, 1100)


def print_file(ps, name):
    ps.gcode(f"SDCARD_PRINT_FILE FILENAME={name}")
    done = stack.wait_until(
        lambda: ps.query("print_stats").get("state") in ("complete", "error"), 60)
    assert done, ps.query("print_stats")


def test_the_printed_files_plan_shows_with_the_position_marked(browser, printer):
    activate_profile(printer)
    open_page(browser, page_url(printer))
    wait_for(browser, "document.getElementById('connection').dataset.state == 'live'")
    # asked once the profile's lines are in
    wait_for(browser, "document.getElementById('plan-chart').dataset.message"
                      ".includes('No file is being printed')")
    print_file(printer, "annotated.gcode")
    wait_for(browser, "!!document.querySelector('#plan-chart canvas')")
    assert message(browser, "plan-chart") == ""
    assert "annotated.gcode" in js(
        browser, "return document.getElementById('plan-name').textContent")
    # the whole file ran in batch mode: the mark is at the print's end
    plan = printer.moonraker.request(
        "GET", "/server/flowloop/page/plan?filename=annotated.gcode")[1]["result"]
    assert plan["annotated"] is True and plan["why"] is None
    end = printer.query("virtual_sdcard")["file_position"]
    assert end == (printer.data_dir / "gcodes" / "annotated.gcode").stat().st_size
    wait_for(browser, "Math.abs(document.getElementById('plan-chart').dataset"
                      f".position - {plan['print_time_s']}) < 0.01")
    # off the chart its legend shows the plan there
    wait_for(browser, f"Math.abs({legend_value('plan-chart', 's')} - "
                      f"{plan['print_time_s']}) <= 1")
    print_file(printer, "plain.gcode")
    wait_for(browser, "document.getElementById('plan-chart').dataset.message"
                      ".includes('plain.gcode has no autotemp annotations')")
    assert severe_console(browser) == []


def tools_rows(driver):
    """{tool: [its cells]} of the page's Tools table."""
    return js(driver, """
        const out = {};
        for (const row of document.querySelectorAll('#tools tbody tr')) {
          out[row.dataset.tool] = [...row.cells].map((c) => c.textContent);
        }
        return out;""")


def test_the_page_lists_every_tool_and_follows_a_tool_change(browser, printer):
    activate_profile(printer)
    open_page(browser, page_url(printer))
    wait_for(browser, "document.getElementById('connection').dataset.state == 'live'"
                      " && document.querySelectorAll('#tools tbody tr').length == 2")
    limiter = printer.query("flowrate_limiter")
    wait_for(browser, "document.querySelector('#tools tr[data-tool=extruder]')"
                      f".cells[2].textContent == '{limiter['cap']:.2f}"
                      f" ({limiter['reason']})'")
    rows = tools_rows(browser)
    assert rows["extruder"][0] == "extruder (printing)"
    assert rows["extruder"][5] == "page-pla"
    # the second tool has no sensor, limiter, autotemp or profile: said so
    assert rows["extruder1"] == ["extruder1", "no sensor", "no limiter",
                                 "no autotemp", "0.0", "none"]
    try:
        printer.gcode("ACTIVATE_EXTRUDER EXTRUDER=extruder1")
        # without ?extruder= the page follows the tool that prints
        wait_for(browser, "document.querySelector('#extruders [aria-current]')"
                          ".textContent == 'extruder1'")
        wait_for(browser, "document.querySelector('#tools tr[data-tool=extruder1]')"
                          ".cells[0].textContent == 'extruder1 (printing)'")
        assert "No [flow_sensor] watches extruder1" in message(browser, "flow-chart")
    finally:
        printer.gcode("ACTIVATE_EXTRUDER EXTRUDER=extruder")
    wait_for(browser, "document.querySelector('#extruders [aria-current]')"
                      ".textContent == 'extruder'")
    assert severe_console(browser) == []


def test_the_page_links_the_flow_reports_and_nozzle_health(browser, printer):
    from flowloop.report import dump, render
    from flowloop.report.recorder import Job, Recorder, Sample
    rec = Recorder(job=Job(job_id="00002A", filename="benchy.gcode"))
    for i in range(20):
        rec.sample(Sample(time_s=0.25 * i, commanded_flow_mm3_s=5.0,
                          measured_flow_mm3_s=5.0, grip=1.0))
    rec.finish("completed", 5.0)
    folder = printer.data_dir / "flowloop" / "reports"
    folder.mkdir(parents=True, exist_ok=True)
    try:
        dump.save(folder / "00002A.json", dump.dumps(rec))
        dump.save(folder / "00002A.html", render.html(rec))
        open_page(browser, page_url(printer))
        href = wait_for(browser, "document.querySelector('#report-list a')"
                                 " && document.querySelector('#report-list a').href")
        assert href == printer.moonraker.url + "/server/flowloop/report?job_id=00002A"
        assert "benchy.gcode" in js(browser, "return document.querySelector("
                                             "'#report-list li').textContent")
        # the link is what Moonraker serves
        status, page = printer.moonraker.request(
            "GET", href[len(printer.moonraker.url):])
        assert status == 200 and "benchy.gcode" in page
        # no job judged on this printer: said where the list would be
        assert "No print judged yet" in js(
            browser, "return document.querySelector('#health-list')"
                     ".previousElementSibling.textContent")
        assert severe_console(browser) == []
    finally:
        for suffix in (".json", ".html"):
            (folder / f"00002A{suffix}").unlink(missing_ok=True)


def test_the_page_carries_on_after_klippy_restarts(browser, printer):
    open_page(browser, page_url(printer))
    wait_for(browser, "document.getElementById('connection').dataset.state == 'live'")
    status, body = printer.moonraker.request("POST", "/printer/restart")
    assert status == 200, body
    wait_for(browser, "document.getElementById('connection').dataset.state != 'live'")
    printer.moonraker.wait_ready(klippy=True)
    wait_for(browser, "document.getElementById('connection').dataset.state == 'live'")
    printer.gcode("SET_AUTOTEMP ENABLE=0\n"
                  "SET_HEATER_TEMPERATURE HEATER=extruder TARGET=201")
    wait_for(browser, f"+{FIELD.format('target')}.dataset.value == 201")
    before = int(js(browser, "return document.getElementById('flow-chart')"
                             ".dataset.samples"))
    wait_for(browser, f"+document.getElementById('flow-chart').dataset.samples"
                      f" > {before}")
    assert severe_console(browser) == []


def test_bad_input_is_said_where_the_chart_would_be(browser, printer):
    open_page(browser, page_url(printer, "extruder7"))
    wait_for(browser, "document.getElementById('flow-chart').dataset.message")
    for chart in ("flow-chart", "temp-chart", "profile-chart", "plan-chart"):
        assert "This printer has no [extruder7]: its extruders are extruder, " \
               "extruder1." == message(browser, chart)
    open_page(browser, page_url(printer, "extruder1"))
    wait_for(browser, "document.getElementById('connection').dataset.state == 'live'")
    assert message(browser, "flow-chart").startswith(
        "No [flow_sensor] watches extruder1")
    assert message(browser, "temp-chart") == ""
    wait_for(browser, "document.getElementById('profile-chart').dataset.message")
    assert message(browser, "profile-chart").startswith(
        "No active profile for extruder1")
    assert field(browser, "grip") == ""
    # the active profile deleted while the page shows it
    activate_profile(printer, "short-lived")
    open_page(browser, page_url(printer))
    wait_for(browser, "!!document.querySelector('#profile-chart canvas')")
    status, body = printer.moonraker.request(
        "DELETE", "/server/flowloop/profile?name=short-lived")
    assert status == 200, body
    wait_for(browser, "document.getElementById('profile-chart').dataset.message"
                      ".startsWith('No active profile for extruder')")
    assert severe_console(browser) == []


@pytest.fixture(scope="module")
def locked(moonraker_venv):
    """A Moonraker that trusts no client (trusted_clients names another host),
    and its API key, read while it still trusted this one (GET /access/api_key,
    what a user does from a trusted machine)."""
    data_dir = stack.short_tempdir("fl-page-auth-")
    try:
        with stack.printer_stack(with_klippy=False, data_dir=data_dir) as ps:
            status, body = ps.moonraker.request("GET", "/access/api_key")
            assert status == 200, body
            key = body["result"]
        with stack.printer_stack(with_klippy=False, data_dir=data_dir,
                                 trusted="192.0.2.1") as ps:
            yield ps, key
    finally:
        shutil.rmtree(data_dir, ignore_errors=True)


def test_without_authorization_the_page_shows_nothing(browser, locked):
    ps, _ = locked
    for path in ("/server/flowloop/page/", "/server/flowloop/page/lines",
                 "/server/flowloop/page/plan?filename=x.gcode"):
        assert ps.moonraker.request("GET", path)[0] == 401, path
    open_page(browser, page_url(ps) + "#api_key=wrong")
    assert "Unauthorized" in page_state(browser)
    assert js(browser, "return document.getElementById('readout')") is None


def test_an_api_key_opens_the_page_where_moonraker_asks_for_one(browser, locked):
    ps, key = locked
    status, body = ps.moonraker.request("GET", "/access/oneshot_token",
                                        headers={"X-Api-Key": key})
    assert status == 200, body
    # the oneshot token authorises the page's one request; the key in the
    # fragment (never sent to a server) the page's websocket
    open_page(browser, page_url(ps) + f"?token={body['result']}#api_key={key}")
    state = wait_for(browser, "document.getElementById('connection').dataset.state"
                              " == 'waiting' && document.body.innerText")
    assert "klippy is" in state  # Moonraker answered: no klippy behind it
    assert key not in browser.current_url  # taken out of the address
    browser.execute_script("localStorage.clear()")


def test_flowloop_info_prints_the_address_that_serves_the_page(printer):
    out = subprocess.run([sys.executable, "-m", "flowloop", "info", "--moonraker",
                          printer.moonraker.url], capture_output=True, text=True,
                         check=True).stdout
    (line,) = [x for x in out.splitlines() if x.startswith("live page: ")]
    url = line.split(": ", 1)[1]
    status, body = printer.moonraker.request("GET", url[len(printer.moonraker.url):])
    assert status == 200 and "<title>flowloop live</title>" in body


def test_the_page_connects_again_after_moonraker_restarts(browser, moonraker_venv):
    with stack.printer_stack(with_klippy=False) as ps:
        open_page(browser, page_url(ps))
        connection = "document.getElementById('connection').dataset.state"
        wait_for(browser, f"{connection} == 'waiting'")  # no klippy behind it
        port = ps.moonraker.port
        ps.moonraker.stop()
        wait_for(browser, f"{connection} == 'down'")
        again = stack.Moonraker(moonraker_venv, ps.data_dir, port=port)
        try:
            again.wait_ready()
            wait_for(browser, f"{connection} == 'waiting'")
            assert "klippy is" in page_state(browser)
        finally:
            again.stop()


REALTIME_CFG = PRINTER_CFG.split("# a second extruder")[0] + """
# realtime klippy's M109 does not wait (batch mode) while its twin nozzle
# heats in real time: extrusion is allowed cold, and the limiter keeps to
# max_flow (its temperature cap would hold the cold start to a crawl)
[extruder]
min_extrude_temp: 0

[flowrate_limiter]
mode: static

# a strong heater: the twin's nozzle is hot enough to melt within seconds
[flow_sensor_simulation sim]
heater_power: 150

# realtime klippy has no endstops that answer: homing declares the position
[force_move]
enable_force_move: True

[homing_override]
gcode: SET_KINEMATIC_POSITION X=0 Y=0 Z=0
"""


@pytest.fixture(scope="module")
def live_printer(klipper_build, klippy_venv, moonraker_venv):
    """The same printer on klippy paced to the clock (devtools/realtime_klippy.py):
    a print runs in real time, as the page is meant to watch it."""
    with stack_with_cfg(REALTIME_CFG.format(project=PROJECT), realtime=True) as ps:
        annotate_file(EXCERPT, ps.data_dir / "gcodes" / "annotated.gcode")
        yield ps


@pytest.mark.alone  # paced to the wall clock
def test_the_page_moves_while_a_print_runs_in_real_time(browser, live_printer):
    ps = live_printer
    activate_profile(ps)
    open_page(browser, page_url(ps))
    wait_for(browser, "document.getElementById('connection').dataset.state == 'live'")
    ps.gcode("SDCARD_PRINT_FILE FILENAME=annotated.gcode")
    wait_for(browser, "!!document.querySelector('#plan-chart canvas')")
    seen, marks = set(), []
    deadline = time.monotonic() + 25
    while time.monotonic() < deadline:
        seen.add((field(browser, "measured_flow"), field(browser, "temperature")))
        mark = js(browser, "return document.getElementById('plan-chart')"
                           ".dataset.position")
        if mark:
            marks.append(float(mark))
        time.sleep(0.5)
    # flow and the twin's nozzle change under the page's eyes, and the mark
    # moves along the plan as the file is read
    assert len(seen) > 10, seen
    assert marks and marks[-1] > marks[0] + 5, marks
    assert ps.query("print_stats")["state"] == "printing"
    screenshot(browser)
    assert severe_console(browser) == []


def test_sensor_faults_are_listed_as_they_happen(browser, printer):
    open_page(browser, page_url(printer))
    wait_for(browser, "document.getElementById('connection').dataset.state == 'live'")
    printer.gcode("SET_FLOW_SENSOR_SIMULATION FAULT=magnet\nG28\nM83\n"
                  "G1 E5 F300\nM400")
    fault = printer.query("flow_sensor sim")["fault"]
    assert fault == "magnet"
    events = "document.getElementById('events').innerText"
    wait_for(browser, f"{events}.includes('sensor sim: fault (magnet)')")
    wait_for(browser, f"{events}.includes('more magnet')")
    # the magnet back: the fault it made ends (a cold twin nozzle may make
    # the next one, 'stuck' filament): the page lists what the sensor says
    printer.gcode("SET_FLOW_SENSOR_SIMULATION FAULT=none\nG1 E5 F300\nM400")
    now = printer.query("flow_sensor sim")["fault"]
    assert now != "magnet"
    wait_for(browser, f"{FIELD.format('fault')}.dataset.value == '{now or ''}'")
    wait_for(browser, f"{events}.includes('sensor sim: "
                      f"{f'fault ({now})' if now else 'fault cleared'}')")
    assert severe_console(browser) == []


def test_the_timeline_holds_five_minutes_however_long_it_runs(own_browser, printer):
    browser = own_browser
    open_page(browser, page_url(printer))
    wait_for(browser, "document.getElementById('connection').dataset.state == 'live'")
    samples = "+document.getElementById('flow-chart').dataset.samples"
    # Twelve minutes of the page's clock (its timers and Date) pass at once.
    browser.execute_cdp_cmd("Emulation.setVirtualTimePolicy",
                            {"policy": "advance", "budget": 12 * 60 * 1000})
    wait_for(browser, f"{samples} >= 1200", timeout=60)
    browser.execute_cdp_cmd("Emulation.setVirtualTimePolicy",
                            {"policy": "advance", "budget": 60 * 1000})
    time.sleep(2)
    assert js(browser, f"return {samples}") == 1200  # 300 s at 4 a second
    assert severe_console(browser) == []


def test_the_page_endpoints_refuse_bad_input_in_one_line(printer):
    def get(path):
        return printer.moonraker.request("GET", path)

    status, body = get("/server/flowloop/page/plan?filename=../config/printer.cfg")
    assert status == 404 and 'no G-code file named "../config/printer.cfg"' in str(body)
    status, body = get("/server/flowloop/page/plan")
    assert status == 400 and "argument 'filename'" in str(body)
    status, body = get("/server/flowloop/page/lines?extruder=nozzle")
    assert status == 400 and '"nozzle" is not an extruder name' in str(body)
    status, body = get("/server/flowloop/page/lines?extruder=extruder1")
    assert status == 200
    assert body["result"] == {"extruder": "extruder1", "lines": None,
                              "why": "no active profile for extruder1"}
