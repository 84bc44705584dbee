"""The fil tier: Klipper's atmega2560 firmware on simavr, klippy in normal mode.

A test module declares its printer (FIL_SECTIONS: config sections added to
fil_printer.cfg; FIL_SENSOR: the EMS22's pins for the simulator) and gets
one simulator + klippy for the whole module through the `printer` fixture.
Without simavr the tier is skipped with one loud line.
"""

from __future__ import annotations

import contextlib
import math
import shutil
import time
from pathlib import Path

import pytest

from devtools import simavr, stack

HERE = Path(__file__).resolve().parent
MICROSTEPS = 16
FULL_STEPS = 200
ROTATION_DISTANCE = 7.71
COUNTS_PER_MM = 1024 / (math.pi * 3.17)
SENSOR = "flow_sensor filament"


def pytest_terminal_summary(terminalreporter):
    reason = simavr.missing_simavr_reason()
    if reason:
        terminalreporter.write_line("!!! " + reason, red=True, bold=True)


def printer_config(sections: str) -> str:
    return (HERE / "fil_printer.cfg").read_text() + "\n" + sections


def build_or_skip(host: str = "klipper") -> stack.KlipperBuild:
    """The patched Klipper (or Kalico) and the harness, or a skip saying what
    is missing."""
    reason = simavr.missing_simavr_reason()
    if reason:
        pytest.skip(reason)
    missing = stack.missing_klipper_reason(host)
    if missing:
        pytest.skip(missing)
    build = stack.build_klipper(host=host)
    simavr.build_harness()
    return build


@pytest.fixture(scope="module")
def fil_build():
    return build_or_skip()


@contextlib.contextmanager
def fil_printer(build, sections: str, sensor=None,
                rotation_distance: float = ROTATION_DISTANCE,
                hotend_temp_c: float = 25.0):
    """The simulator (its extruder moving rotation_distance per turn, its
    thermistor pin at hotend_temp_c) and klippy on fil_printer.cfg plus
    sections; stopped on leaving."""
    venv = stack.klippy_venv(build.host)
    workdir = stack.short_tempdir("fl-fil-")
    try:
        fil = simavr.start_printer(
            build, venv, printer_config(sections), workdir,
            sensor=sensor or {"cs": "PG0"},
            mm_per_step=rotation_distance / (FULL_STEPS * MICROSTEPS),
            counts_per_mm=COUNTS_PER_MM,
            heater_pin="PB4", adc_channel=13,
            adc_mv=round(simavr.thermistor_mv(hotend_temp_c)))
    except simavr.HarnessError as e:
        shutil.rmtree(workdir, ignore_errors=True)
        pytest.fail(f"fil printer did not start: {e}", pytrace=False)
    try:
        yield fil
        # a simulator fault no test asked for (a test may stop it)
        lost = fil.sim.status()["lost_overflows"] if fil.sim.alive() else "0"
        assert lost == "0", (f"the simulated firmware's clock missed {lost}"
                             f" Timer1 overflow(s): {fil.sim.log_tail(600)}")
    finally:
        simavr.stop_printer(fil)
        shutil.rmtree(workdir, ignore_errors=True)


@pytest.fixture(scope="module")
def printer(request, fil_build):
    """One simulator and one klippy for the module's tests, in order."""
    module = request.module
    with fil_printer(fil_build, module.FIL_SECTIONS,
                     getattr(module, "FIL_SENSOR", None),
                     getattr(module, "TRUE_ROTATION_DISTANCE",
                             ROTATION_DISTANCE)) as fil:
        yield fil


# Moonraker's components subscribe to klippy's objects in their klippy-ready
# handlers, each re-sending the merged subscription; a print_stats change
# between two of them reaches only the later one's answer, and job_state
# (its history) would never see the print start. A user starts a print long
# after; a test waits for the handlers to end.
SUBSCRIPTIONS_SETTLE_S = 2.0


# The printer Moonraker prints jobs on: its virtual_sdcard in Moonraker's
# gcodes folder, the EMS22, the limiter in its default (predictive) mode
JOB_SECTIONS = """
[virtual_sdcard]
path: {gcodes}

[display_status]

[flow_sensor filament]
sensor_type: ems22
cs_pin: PG0

[flowrate_limiter]
"""


@contextlib.contextmanager
def fil_moonraker(build, moonraker_venv, profile: dict,
                  sections: str = JOB_SECTIONS, extra_conf: str = "",
                  hotend_temp_c: float = 25.0):
    """A fil printer with `[virtual_sdcard]` on a Moonraker's gcodes folder
    (sections: a format string given {gcodes}), and that Moonraker, ready
    for a print, with `profile` stored and active on the extruder; both
    stopped on leaving."""
    data_dir = stack.short_tempdir("fl-filmr-")
    gcodes = data_dir / "gcodes"
    gcodes.mkdir(parents=True)
    try:
        with fil_printer(build, sections.format(gcodes=gcodes),
                         hotend_temp_c=hotend_temp_c) as printer:
            server = stack.Moonraker(moonraker_venv, data_dir,
                                     klippy_uds=printer.klippy.api_socket,
                                     extra_conf=extra_conf)
            try:
                server.wait_ready(klippy=True)
                time.sleep(SUBSCRIPTIONS_SETTLE_S)
                activate(server, profile)
                yield printer, server
            finally:
                server.stop()
    finally:
        shutil.rmtree(data_dir, ignore_errors=True)


def activate(server, profile: dict) -> None:
    """Store `profile` in Moonraker and make it the extruder's active one
    (the limiter's grip model starts afresh from it)."""
    for path, body in (
            ("/server/flowloop/profile", {"profile": profile}),
            ("/server/flowloop/profile/activate",
             {"name": profile["identity"]["name"], "extruder": "extruder"})):
        status, answer = server.request("POST", path, body)
        assert status == 200, answer


def wait_for(what: str, fn, timeout: float):
    """fn()'s first true value, polled; the test fails naming `what` if
    none comes within timeout seconds."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = fn()
        if value:
            return value
        time.sleep(0.25)
    pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}",
                pytrace=False)


def start_job(server, name: str, gcode: str) -> None:
    """Upload `gcode` as `name` to Moonraker and start printing it."""
    server.upload(name, gcode.encode())
    status, body = server.request("POST", f"/printer/print/start?filename={name}")
    assert status == 200, body


def ended_job(server, name: str, states, timeout: float = 60) -> dict:
    """The job of file `name` in Moonraker's history once it has ended in
    one of `states`."""
    def ended():
        jobs = server.request("GET", "/server/history/list?limit=3")[1][
            "result"]["jobs"]
        return next((j for j in jobs if j["filename"] == name
                     and j["status"] in states), None)
    return wait_for("the job in Moonraker's history", ended, timeout)


def job_report(server, job: dict, timeout: float = 15) -> dict:
    """The summary /server/flowloop/reports lists for `job` once stored."""
    def listed():
        result = server.request("GET", "/server/flowloop/reports")[1]["result"]
        return next((r for r in result["reports"]
                     if r["job_id"] == job["job_id"]), None)
    return wait_for("the job's flow report", listed, timeout)


def settle(printer, seconds: float = 0.4) -> dict:
    """The sensor's status once the samples of finished moves are in (M400
    returns when the last step is due; samples reach the host in messages
    of at most 20 ms of samples and 100 ms batches)."""
    time.sleep(seconds)
    return printer.query(SENSOR)
