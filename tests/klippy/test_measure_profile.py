"""MEASURE_MATERIAL_PROFILE end to end on the twin, in klippy batch mode.

The simulated sensor's hotend (40 W, lag, sag, held at a fixed power while
measuring) melts what the active profile's line gives. A test client on
klippy's API socket registers the remote method flowloop_store_profile, as
Moonraker's [flowloop] component does, and records what klippy sends it.
The command starts the run and returns (as SDCARD_PRINT_FILE does), so
the tests wait for the run's end in its status. The measurement must
recover the profile, hand it over once, and give the heater its own control
back whether it succeeds, fails, is cancelled (from the console too) or
meets a sensor fault or another command; an aborted run sends nothing."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from devtools import stack
from devtools.klippy_api import KlippyApi
from flowloop.control.hotend import HotendParams
from flowloop.gcode import measure_part
from flowloop.material import measure
from flowloop.material.profile import profile_from_dict
from tests.samples import TWIN_FLOW, TWIN_SLOPE, TWIN_TEMP, twin_known

HERE = Path(__file__).resolve().parent
CONFIG = HERE / "measure_profile.cfg"
# into_air == real_print: the twin melts exactly this line at any working point
SLOPE, TEMP, FLOW = TWIN_SLOPE, TWIN_TEMP, TWIN_FLOW
KNOWN = twin_known()
# The stated tolerance of the twin test: slope within 5 %, the line's flow at
# the middle level within 3 %, the intercept within 1.5 mm^3/s.
SLOPE_TOLERANCE = 0.05
FLOW_TOLERANCE = 0.03
INTERCEPT_TOLERANCE_MM3_S = 1.5


class Client(KlippyApi):
    """klippy's API socket, with the measurement's status at hand."""

    def __init__(self, path: Path):
        super().__init__(path, timeout=600)

    def status(self):
        return self.query("measure_profile")


class Harnessed:
    """The Klipper build, klippy started through measure_profile_harness.py."""

    def __init__(self, build):
        self.build, self.tree = build, build.tree
        self.klippy = HERE / "measure_profile_harness.py"

    def dictionary(self, target):
        return self.build.dictionary(target)


@pytest.fixture(scope="module")
def printer(klipper_build, klippy_venv):
    workdir = stack.short_tempdir("fl-measure-")
    klippy = stack.Klippy(Harnessed(klipper_build), klippy_venv, CONFIG, workdir,
                          {"mcu": "atmega2560"})
    try:
        runner = klippy.ready_api(api_class=Client)
        watcher = Client(klippy.api_socket)
        runner.call("register_remote_method",
                    response_template={"method": "store"},
                    remote_method="flowloop_store_profile")
        runner.call("flowloop/set_active_profile", extruder="extruder",
                    profile=KNOWN, working_point=0.5)
        yield runner, watcher, klippy
        runner.close()
        watcher.close()
    finally:
        klippy.stop()
        shutil.rmtree(workdir, ignore_errors=True)


def stored(client):
    return [m for m in client.remote if m.get("method") == "store"]


def start(runner, script):
    """Start a run: the command answers at once."""
    runner.call("gcode/script", script=script)


def finished(runner, watcher, timeout=600):
    """The status once the run has ended (the store, if any, read)."""
    status = stack.wait_until(
        lambda: (s := watcher.status())["state"] != "running" and s,
        timeout, 0.05)
    assert status, watcher.status()
    runner.call("info")   # what klippy sent the runner meanwhile is read
    return status


def run_to_end(runner, watcher, script):
    start(runner, script)
    return finished(runner, watcher)


# A long run: level 1 ramps ~110 steps (to grip 0.3), so a stop sent once the
# heater is held arrives mid-ramp however fast batch mode runs it
LONG_RUN = ("MEASURE_MATERIAL_PROFILE NAME=stopped TEMPS=200,220 START_FLOW=2"
            " STEP=0.125 MAX_FLOW=25 MIN_GRIP=0.3")


def holding(watcher):
    """measure_profile's and the extruder's status, read together, once the
    heater is held at a fixed power mid-ramp."""
    def held():
        status = watcher.call("objects/query", objects={
            "measure_profile": None, "extruder": None})["status"]
        run = status["measure_profile"]
        if run["state"] != "running":
            return run
        if run["flow"] is not None and run["heater_control"] == \
                "FixedPowerControl":
            return status
        return None
    status = stack.wait_until(held, 300, 0.05)
    assert status and "extruder" in status, (status, watcher.status())
    assert 0 < status["measure_profile"]["heater_pwm"] < 1
    return status


def assert_heater_given_back(watcher):
    status = watcher.status()
    assert status["heater_control"] == "ControlPID"
    assert status["heater_pwm"] is None


def test_a_level_without_slip_fails_stores_nothing_and_gives_the_heater_back(
        printer):
    runner, watcher, _ = printer
    before = len(stored(runner))
    status = run_to_end(runner, watcher, "MEASURE_MATERIAL_PROFILE NAME=x "
                     "TEMPS=200,220 START_FLOW=4 STEP=0.25 MAX_FLOW=4.5")
    assert status["state"] == "aborted"
    assert re.search("grip stayed above 0.9 up to MAX_FLOW 4.5 mm.3/s.*nothing"
                     " stored", status["message"]), status
    assert_heater_given_back(watcher)
    assert len(stored(runner)) == before


def test_bad_input_changes_nothing(printer):
    runner, watcher, _ = printer
    with pytest.raises(RuntimeError, match="TEMPS: 300 degC is outside the "
                       "profile's 185..250 degC; nothing changed"):
        runner.call("gcode/script", script="MEASURE_MATERIAL_PROFILE NAME=x "
                    "TEMPS=200,300")
    assert watcher.status()["heater_control"] == "ControlPID"


# How a run is stopped mid-ramp: (how, what, why it says it ended)
STOPS = {
    "endpoint": ("call", "measure_profile/cancel", "cancelled"),
    # typed in Mainsail's console: Moonraker sends it as gcode/script
    "console": ("gcode", "CANCEL_MATERIAL_PROFILE",
                "cancelled (CANCEL_MATERIAL_PROFILE)"),
    "fault": ("call", "measure_profile_test/fault/sim",
              "flow sensor fault 'missing'"),
    "pause": ("gcode", "PAUSE", "PAUSE cancels a measurement"),
    "move": ("gcode", "G91\nG1 Z5 F600\nG90",
             "the toolhead was moved by another command"),
    "target": ("gcode", "M104 S230",
               "extruder's target was changed by another command"),
}


@pytest.mark.parametrize("stop", list(STOPS))
def test_a_run_stopped_mid_ramp_stores_nothing_and_gives_the_heater_back(
        printer, stop):
    runner, watcher, _ = printer
    how, what, why = STOPS[stop]
    if stop == "move":
        runner.call("gcode/script", script="G28")
    before = len(stored(runner))
    start(runner, LONG_RUN)
    # the heater answers with the fixed power swapped in (Kalico asks its
    # control for a profile name in every status)
    extruder = holding(watcher)["extruder"]
    assert extruder.get("pid_profile", "fixed_power") == "fixed_power"
    e_before = watcher.query("toolhead")["position"][3]
    try:
        if how == "gcode":
            # the console is not held by the run: the command answers now
            watcher.call("gcode/script", script=what)
        else:
            watcher.call(what, **({"fault": "missing"} if "fault" in what
                                  else {}))
        status = finished(runner, watcher)
    finally:
        if stop == "fault":
            watcher.call(what, fault="none")
        if stop == "pause":
            watcher.call("gcode/script", script="CLEAR_PAUSE")
    assert why in status["message"] and "nothing stored" in status["message"], (
        status)
    assert status["state"] == "aborted"
    assert_heater_given_back(watcher)
    assert len(stored(runner)) == before
    # a G-code move in between goes on from where the run left the filament
    # (not from where G-code last put it: that would pull it all back)
    assert watcher.query("toolhead")["position"][3] >= e_before


def test_a_second_run_or_one_while_paused_is_refused(printer):
    runner, watcher, _ = printer
    start(runner, LONG_RUN)
    try:
        with pytest.raises(RuntimeError, match="a measurement is running"
                           " already"):
            runner.call("gcode/script", script="MEASURE_MATERIAL_PROFILE "
                        "NAME=second TEMPS=200,220")
    finally:
        runner.call("gcode/script", script="CANCEL_MATERIAL_PROFILE")
        assert finished(runner, watcher)["state"] == "aborted"
    runner.call("gcode/script", script="PAUSE")
    try:
        with pytest.raises(RuntimeError, match="paused.*nothing changed"):
            runner.call("gcode/script", script="MEASURE_MATERIAL_PROFILE "
                        "NAME=paused TEMPS=200,220")
    finally:
        runner.call("gcode/script", script="CLEAR_PAUSE")
    assert_heater_given_back(watcher)


def test_the_measurement_recovers_the_profile_and_hands_it_to_moonraker(printer):
    runner, watcher, klippy = printer
    before = len(stored(runner))
    run_to_end(runner, watcher, "MEASURE_MATERIAL_PROFILE NAME=measured "
            "TEMPS=200,220,240 START_FLOW=4 STEP=0.25 MAX_FLOW=14 "
            "MIN_GRIP=0.9 ACTIVATE=1")
    calls = stored(runner)[before:]
    assert len(calls) == 1
    params = calls[0]["params"]
    assert params["activate_extruder"] == "extruder"
    profile = profile_from_dict(params["profile"])
    line = profile.lines.into_air.line()
    assert profile.name == "measured"
    assert line.slope_mm3_s_per_c == pytest.approx(SLOPE, rel=SLOPE_TOLERANCE)
    true_intercept = FLOW - SLOPE * TEMP
    assert abs(line.intercept_mm3_s - true_intercept) <= INTERCEPT_TOLERANCE_MM3_S
    assert line.flow_mm3_s(220.0) == pytest.approx(
        SLOPE * 220.0 + true_intercept, rel=FLOW_TOLERANCE)
    # the points are kept, each with its temperature, flow, grip and power
    points = [p for p in profile.points if p.kind == "into_air"]
    assert len(points) == 3
    assert all(p.grip < 0.9 and 0 < p.heater_pwm < 255 for p in points)
    assert sorted(p.temp_c for p in points) == [p.temp_c for p in points]
    # (the power line is optional: refused when the points scatter about it)
    power = profile.lines.into_air_power
    assert power is None or power.slope_mm3_s_per_pwm > 0
    assert profile.provenance.method == "into_air"
    assert profile.provenance.min_grip == 0.9
    # the base's real-print line is kept
    assert profile.lines.real_print.slope_mm3_s_per_c == SLOPE
    status = watcher.status()
    assert status["state"] == "stored"
    assert status["result"]["slope_mm3_s_per_c"] == pytest.approx(
        line.slope_mm3_s_per_c)
    assert_heater_given_back(watcher)
    log = (klippy.workdir / "klippy.log").read_text(errors="replace")
    assert "level 3/3 (240 degC): heater held at" in log


# The twin's flow-vs-power line lies between two lines the hotend model
# gives: idle, a held power P (share of the 40 W heater) settles the nozzle
# where the loss to the room takes it, ambient + 40 W * P / loss, and the
# twin melts the known line there; fully sagged, the nozzle at its limit
# flow for good, (loss + filament heat * flow) * (T - ambient) = 40 W * P.
# A ramp starts idle and sags a few degC, more at the higher flows of the
# higher powers, so its line lies between (ddPrint's points too sit where
# the heater sagged). Stated tolerance of POWERS=: the slope between the
# two lines' (0.150 and 0.269 mm^3/s per PWM; 10 % above the idle one),
# the flow at the middle power between theirs; each point's temperature
# between its power's fully sagged temperature and its idle one plus
# ABOVE_IDLE_C (a level heats to within 2 degC of where its power should
# hold, from powers read off the heater's own control); the temperature
# line from the same points within 5 % (SLOPE_TOLERANCE).
TWIN = HotendParams(max_power_w=40.0)
POWERS = (0.30, 0.33, 0.36)
ABOVE_IDLE_C = 3.0


def idle_temp_c(pwm):
    return TWIN.ambient_c + (pwm / measure.PWM_MAX * TWIN.max_power_w
                             / TWIN.loss_w_per_c)


def sagged_temp_c(pwm):
    """Where the held power keeps the nozzle melting its limit for good."""
    power_w = pwm / measure.PWM_MAX * TWIN.max_power_w
    low, high = TWIN.ambient_c, idle_temp_c(pwm)
    for _ in range(60):    # bisection: the loss rises with the temperature
        temp = (low + high) / 2
        melt = max(0.0, FLOW + SLOPE * (temp - TEMP))
        loss = (TWIN.loss_w_per_c + TWIN.filament_j_per_mm3_c * melt) \
            * (temp - TWIN.ambient_c)
        low, high = (temp, high) if loss < power_w else (low, temp)
    return low


def melt_at(temp_c):
    return FLOW + SLOPE * (temp_c - TEMP)


def power_line(temp_of):
    """(slope per PWM, flow at the middle power) of the twin's line."""
    pwms = [level * measure.PWM_MAX for level in POWERS]
    flows = [melt_at(temp_of(pwm)) for pwm in pwms]
    return (flows[-1] - flows[0]) / (pwms[-1] - pwms[0]), flows[1]


def test_a_powers_run_recovers_the_flow_vs_power_line_and_stores_it(printer):
    runner, watcher, klippy = printer
    before = len(stored(runner))
    levels = ",".join(f"{level:g}" for level in POWERS)
    run_to_end(runner, watcher, "MEASURE_MATERIAL_PROFILE NAME=powers "
            f"POWERS={levels} STEP=0.25 MAX_FLOW=14 MIN_GRIP=0.9")
    calls = stored(runner)[before:]
    assert len(calls) == 1
    profile = profile_from_dict(calls[0]["params"]["profile"])
    points = [p for p in profile.points if p.kind == "into_air"]
    # each level held the power asked for (PWM on ddPrint's 0..255 scale)
    assert [p.heater_pwm for p in points] == pytest.approx(
        [level * 255 for level in POWERS])
    # ... at the temperature that power holds (sagged by the ramp, not as
    # far as for good), not where the last level left the nozzle
    for p in points:
        assert sagged_temp_c(p.heater_pwm) <= p.temp_c <= idle_temp_c(
            p.heater_pwm) + ABOVE_IDLE_C, p
    power = profile.lines.into_air_power
    assert power is not None
    sagged, idle = power_line(sagged_temp_c), power_line(idle_temp_c)
    assert sagged[0] < power.slope_mm3_s_per_pwm < 1.1 * idle[0], (
        power, sagged, idle)
    middle = POWERS[1] * 255
    flow = power.slope_mm3_s_per_pwm * (middle - power.pwm) + power.flow_mm3_s
    assert sagged[1] < flow < idle[1] + SLOPE * ABOVE_IDLE_C, (flow, sagged,
                                                                idle)
    # the temperature line from the same points is the twin's too
    line = profile.lines.into_air.line()
    assert line.slope_mm3_s_per_c == pytest.approx(SLOPE, rel=SLOPE_TOLERANCE)
    assert watcher.status()["state"] == "stored"
    assert_heater_given_back(watcher)
    log = (klippy.workdir / "klippy.log").read_text(errors="replace")
    assert "level 1/3 (power 30%): heating to 210 degC for the power" in log
    assert "where 33.0% power should hold" in log


def test_the_macro_lifts_the_nozzle_and_measures_the_active_profile(printer):
    runner, watcher, _ = printer
    before = len(stored(runner))
    run_to_end(runner, watcher, "MEASURE_PROFILE_INTO_AIR TEMPS=200,230 "
            "START_FLOW=4 STEP=0.5 MAX_FLOW=14 Z=20")
    calls = stored(runner)[before:]
    assert len(calls) == 1
    params = calls[0]["params"]
    assert params["profile"]["identity"]["name"] == "known measured"
    assert params["activate_extruder"] is None
    toolhead = watcher.call("objects/query", objects={"toolhead": None}
                            )["status"]["toolhead"]
    assert toolhead["homed_axes"] == "xyz"
    assert toolhead["position"][2] == pytest.approx(20.0)


def test_the_print_measurement_finds_the_real_print_line_in_the_part(printer):
    runner, watcher, _ = printer
    before = len(stored(runner))
    part = measure_part.render(measure_part.PartOptions(
        length_mm=100.0, width_mm=4.0, height_mm=3.0, start_flow_mm3_s=3.0,
        rise=0.1, max_flow_mm3_s=12.0, hotend_temp_c=TEMP))
    # no heated bed in this printer; the twin heats during a dwell first
    lines = [ln for ln in part.splitlines()
             if not ln.startswith(("M140", "M190"))]
    runner.call("gcode/script", script="MEASURE_MATERIAL_PROFILE_PRINT "
                "NAME=printed MIN_GRIP=0.9")
    assert watcher.status()["state"] == "watching"
    runner.call("gcode/script", script=f"M104 S{TEMP:g}\nG4 P100000")
    for i in range(0, len(lines), 40):
        runner.call("gcode/script", script="\n".join(lines[i:i + 40] + ["M400"]))
        if watcher.status()["state"] != "watching":
            break
    status = watcher.status()
    assert status["state"] == "stored", status
    runner.call("info")  # the store came after the runner's last answer
    calls = stored(runner)[before:]
    assert len(calls) == 1
    profile = profile_from_dict(calls[0]["params"]["profile"])
    real = profile.lines.real_print.line()
    # one point, with the into-air slope: the twin's line at that point
    assert real.slope_mm3_s_per_c == SLOPE
    assert real.flow_mm3_s(TEMP) == pytest.approx(FLOW, rel=FLOW_TOLERANCE)
    assert [p.kind for p in profile.points].count("real_print") == 1
    assert profile.provenance.method == "real_print"
    assert profile.lines.into_air == profile_from_dict(KNOWN).lines.into_air
    # the point is where the part's flow passed what the hotend melts
    point = [p for p in profile.points if p.kind == "real_print"][0]
    assert point.grip < 0.9 and point.heater_pwm is None


def test_the_print_macro_watches_until_cancelled_and_stores_nothing(printer):
    runner, watcher, _ = printer
    before = len(stored(runner))
    runner.call("gcode/script", script="MEASURE_PROFILE_PRINT MIN_GRIP=0.85")
    status = watcher.status()
    assert (status["state"], status["name"]) == ("watching", "known measured")
    runner.call("gcode/script", script="CANCEL_MATERIAL_PROFILE")
    status = watcher.status()
    assert status["state"] == "aborted" and "cancelled" in status["message"]
    runner.call("info")
    assert len(stored(runner)) == before


def test_a_shutdown_mid_ramp_gives_the_heater_back_and_stores_nothing(printer):
    # Last in this file: the printer stays shut down.
    runner, watcher, _ = printer
    before = len(stored(runner))
    # MIN_TEMP=150: the ramp's sag (185 degC and below by its end) cannot
    # end the run before the emergency stop arrives, however slow that is
    start(runner, LONG_RUN + " MIN_TEMP=150")
    holding(watcher)
    watcher.call("emergency_stop")
    status = finished(runner, watcher)
    assert status["state"] == "aborted"
    assert "shut down" in status["message"], status
    assert_heater_given_back(watcher)
    assert len(stored(runner)) == before
