"""The hotend through the real firmware: the heater pin's PWM (Klipper's
software PWM on PB4) drives flowloop's hotend model, whose temperature goes
back to the thermistor's ADC pin, and whose melt line sets how much of the
commanded filament the model's shaft sees. Klipper's PID holds a target
through it, and a short MEASURE_MATERIAL_PROFILE (fixed heater power per
level, flow ramps until grip drops) stores a profile near the model's line,
and autotemp heats ahead of an announced flow so that the model melts it."""

from __future__ import annotations

import math
import time

import pytest

from devtools import simavr, stack
from devtools.klippy_api import KlippyApi
from flowloop.control.autotemp import TemperaturePlan, TempLimits
from flowloop.control.hotend import HotendModel, HotendParams
from flowloop.material.profile import FlowLine, profile_from_dict, profile_line
from tests.fil.conftest import FULL_STEPS, MICROSTEPS, ROTATION_DISTANCE, fil_printer
from tests.klippy.test_measure_profile import FLOW, KNOWN, SLOPE, TEMP

SECTIONS = """
[flow_sensor filament]
sensor_type: ems22
cs_pin: PG0

[measure_profile]
step_time: 1
settle_time: 2

[autotemp]
heater_power: 40
# "about a third of the time a 10 degC step takes to settle": this PID on
# this hotend takes about 27 s
time_constant: 9
"""
# The model melts the line the twin melts in the klippy tier's measurement
# (the profile the run starts from says the same)
MELT = FlowLine(slope_mm3_s_per_c=SLOPE, temp_c=TEMP, flow_mm3_s=FLOW)
START_C = 200.0  # the hotend starts hot: heating from the room takes minutes
HOTEND = HotendParams()  # flowloop's default: 40 W into a V6-like block
TARGET_C = 205.0


@pytest.fixture(scope="module")
def hot(fil_build):
    with fil_printer(fil_build, SECTIONS, hotend_temp_c=START_C) as printer:
        model = HotendModel(HOTEND, temp_c=START_C)
        with simavr.HotendDriver(
                printer.sim, model, MELT.line(),
                ROTATION_DISTANCE / (FULL_STEPS * MICROSTEPS),
                math.pi * 1.75 ** 2 / 4) as driver:
            yield printer, driver


def _extruder_temp(printer) -> float:
    return printer.query("extruder")["temperature"]


def test_klippys_pid_holds_a_target_through_the_firmwares_pwm(hot):
    printer, driver = hot
    printer.gcode(f"SET_HEATER_TEMPERATURE HEATER=extruder TARGET={TARGET_C}")
    reached = stack.wait_until(
        lambda: abs(_extruder_temp(printer) - TARGET_C) < 1.0, 45, 0.2)
    assert reached, (_extruder_temp(printer), driver.model.temp_c, driver.error)
    readings = []
    for _ in range(6):  # held for 3 s
        readings.append((_extruder_temp(printer), driver.model.temp_c,
                         driver.duty))
        time.sleep(0.5)
    print("klippy's reading, the model's temperature, heater duty:", readings)
    for klippy_c, model_c, duty in readings:
        assert klippy_c == pytest.approx(TARGET_C, abs=1.5)
        # 10-bit ADC, oversampled: within about a count (1.3 C at 205 C)
        assert klippy_c == pytest.approx(model_c, abs=1.5)
        assert 0.05 < duty < 0.95
    assert driver.error is None


def test_a_short_measure_material_profile_stores_a_profile(hot):
    printer, driver = hot
    with KlippyApi(printer.klippy.api_socket, timeout=30) as store:
        store.call("register_remote_method", response_template={"method": "store"},
                   remote_method="flowloop_store_profile")
        store.call("flowloop/set_active_profile", extruder="extruder",
                   profile=KNOWN, working_point=0.5)
        printer.gcode("MEASURE_MATERIAL_PROFILE NAME=fil TEMPS=205,215"
                      " STEP=0.5 MAX_FLOW=10")
        status = stack.wait_until(
            lambda: (s := printer.query("measure_profile"))["state"]
            != "running" and s, 150, 0.5)
        store.call("info")  # reads what klippy sent meanwhile
        calls = [m for m in store.remote if m.get("method") == "store"]
    print(status)
    assert status and status["state"] == "stored", (status, printer.console())
    assert len(calls) == 1
    line = profile_from_dict(calls[0]["params"]["profile"]).lines.into_air
    print(f"measured into_air line: {line.flow_mm3_s:.2f} mm^3/s at "
          f"{line.temp_c:.0f} C, slope {line.slope_mm3_s_per_c:.3f}; the model:"
          f" {MELT.flow_mm3_s} at {MELT.temp_c:.0f}, slope {SLOPE}")
    assert line.flow_mm3_s + (TEMP - line.temp_c) * line.slope_mm3_s_per_c \
        == pytest.approx(FLOW, rel=0.15)
    assert line.slope_mm3_s_per_c > 0
    assert driver.error is None


FLOW_AHEAD, LEAD_S, WINDOW_S = 8.0, 20.0, 4.0
SLOW_FLOW = 1.0  # the print before the window: autotemp acts as motion flushes


def test_autotemp_heats_ahead_so_the_model_melts_an_announced_flow(hot):
    printer, driver = hot
    printer.api.call("flowloop/set_active_profile", extruder="extruder",
                     profile=KNOWN, working_point=0.5)
    printer.gcode(f"SET_HEATER_TEMPERATURE HEATER=extruder TARGET={TARGET_C}")
    # Start where the model would slip at this flow: the measurement before
    # may leave the hotend hotter (217 C once), melting it unaided.
    slips = stack.wait_until(
        lambda: MELT.line().flow_mm3_s(driver.model.temp_c) < 0.85 * FLOW_AHEAD,
        60, 0.2)
    start_c = driver.model.temp_c
    assert slips, (start_c, driver.error)
    area = math.pi * 1.75 ** 2 / 4
    mm_per_step = ROTATION_DISTANCE / (FULL_STEPS * MICROSTEPS)
    script = "\n".join([
        # no move first: an announcement read while the toolhead idles is
        # counted from the present (the test below)
        "M83",
        f"AUTOTEMP_FLOW FLOW={FLOW_AHEAD} LEAD={LEAD_S} DURATION={WINDOW_S}",
        f"G1 E{SLOW_FLOW / area * LEAD_S:.3f} F{SLOW_FLOW / area * 60:.2f}",
        f"G1 E{FLOW_AHEAD / area * WINDOW_S:.3f} F{FLOW_AHEAD / area * 60:.2f}",
        "M400"])
    rows = []  # (s since the announcement, target, model C, steps, model mm)
    with KlippyApi(printer.klippy.api_socket, timeout=LEAD_S + WINDOW_S + 20) \
            as printing:
        printing.send("gcode/script", script=script)
        announced = time.monotonic()
        while time.monotonic() < announced + LEAD_S + WINDOW_S + 2:
            status = printer.sim.status()
            rows.append((time.monotonic() - announced,
                         printer.query("extruder")["target"], driver.model.temp_c,
                         int(status["steps"]), float(status["filament_mm"])))
            time.sleep(0.2)
        printing.call("info")  # after the script's answer
    raised = [r for r in rows if r[1] > TARGET_C + 5]
    assert raised, rows[-1]
    window = [r for r in rows if LEAD_S + 0.5 <= r[0] <= LEAD_S + WINDOW_S - 0.5]
    first, last = window[0], window[-1]
    grip = (last[4] - first[4]) / ((last[3] - first[3]) * mm_per_step)
    print(f"from {start_c:.1f} C autotemp raised the target {raised[0][0]:.1f} s"
          f" after the announcement, to {max(r[1] for r in rows):.1f} C; the model at"
          f" {first[2]:.1f} C as the window starts, {last[2]:.1f} C near its"
          f" end; the model fed {grip:.3f} of the commanded filament there")
    assert raised[0][0] < LEAD_S
    assert MELT.line().flow_mm3_s(first[2]) >= 0.9 * FLOW_AHEAD
    assert grip >= 0.97
    assert driver.error is None


IDLE_S, SHORT_LEAD_S, SHORT_WINDOW_S = 5.0, 1.0, 3.0
AREA_MM2 = math.pi * 1.75 ** 2 / 4


def _activate_and_need(printer) -> float:
    """The known profile active at WP 0.5; the plan's need for FLOW_AHEAD."""
    printer.api.call("flowloop/set_active_profile", extruder="extruder",
                     profile=KNOWN, working_point=0.5)
    profile = profile_from_dict(KNOWN)
    max_temp = printer.query("configfile")["settings"]["extruder"]["max_temp"]
    return TemperaturePlan(profile_line(profile, 0.5),
                           TempLimits.of(profile, max_temp)).need_c(FLOW_AHEAD)


def _targets_within_a_short_lead(printer, first: str) -> list:
    """Run `first`, a short window's announcement and its moves (SLOW_FLOW
    for its lead, FLOW_AHEAD through it); the heater's targets read within
    the lead."""
    script = "\n".join([
        first,
        f"AUTOTEMP_FLOW FLOW={FLOW_AHEAD} LEAD={SHORT_LEAD_S}"
        f" DURATION={SHORT_WINDOW_S}",
        f"G1 E{SLOW_FLOW / AREA_MM2 * SHORT_LEAD_S:.3f}"
        f" F{SLOW_FLOW / AREA_MM2 * 60:.2f}",
        f"G1 E{FLOW_AHEAD / AREA_MM2 * SHORT_WINDOW_S:.3f}"
        f" F{FLOW_AHEAD / AREA_MM2 * 60:.2f}",
        "M400"])
    rows = []  # (s since the announcement, the heater's target)
    with KlippyApi(printer.klippy.api_socket, timeout=30) as printing:
        printing.send("gcode/script", script=script)
        announced = time.monotonic()
        while time.monotonic() < announced + SHORT_LEAD_S + SHORT_WINDOW_S + 1:
            rows.append((time.monotonic() - announced,
                         printer.query("extruder")["target"]))
            time.sleep(0.1)
        printing.call("info")  # after the script's answer
    return [t for s, t in rows if s <= SHORT_LEAD_S]


def test_an_announcement_after_the_toolhead_idled_is_planned_from_now(hot):
    """An AUTOTEMP_FLOW read while the toolhead idles (nothing queued since
    the heater command IDLE_S ago) counts its LEAD from the MCU's present,
    where the next move starts, not from the end of the last move: counted
    from there (toolhead.print_time, stale while idle) this window fell
    IDLE_S in the past and its moves ran at the profile's minimum."""
    printer, driver = hot
    need = _activate_and_need(printer)
    # the heater command syncs the toolhead's print time to the present
    printer.gcode(f"SET_HEATER_TEMPERATURE HEATER=extruder TARGET={TARGET_C}")
    time.sleep(IDLE_S)
    # the plan heats at once (its nozzle is short of the need by the
    # window) and lets the heater go before the window's end (the nozzle
    # cools slower than the window lasts): raised within the lead
    ahead = _targets_within_a_short_lead(printer, "M83")
    print(f"the target within the lead: {min(ahead):.1f}-{max(ahead):.1f} C"
          f" (the flow's need {need:.1f} C)")
    assert max(ahead) >= need, ahead
    assert driver.error is None


def test_autotemp_takes_over_from_what_the_heater_reads_not_its_target(hot):
    """A start that does not wait for its temperature (M104, not M109):
    autotemp takes over while the nozzle reads well under the heater's
    target. Its model starts at the reading, so it heats at once for a
    window that needs about that target; started at the target, it
    believed the nozzle there and planned no push."""
    printer, driver = hot
    need = _activate_and_need(printer)
    # the print before is over: the heater turned off stands autotemp down
    # at the next flush (a print's end: M104 S0), so that the file's M104
    # below is obeyed and autotemp takes over afresh
    printer.gcode(f"M104 S0\nM83\nG1 E0.02 F{SLOW_FLOW / AREA_MM2 * 60:.2f}"
                  "\nM400")
    assert printer.query("autotemp")["source"] is None
    # well below the window's need (the test above left it hot)
    cooled = stack.wait_until(lambda: _extruder_temp(printer) < need - 15, 60,
                              0.2)
    reads = _extruder_temp(printer)
    assert cooled, reads
    ahead = _targets_within_a_short_lead(printer, f"M104 S{need + 3:.0f}")
    print(f"the nozzle read {reads:.1f} C; the target within the lead:"
          f" {min(ahead):.1f}-{max(ahead):.1f} C (the flow's need {need:.1f} C)")
    assert max(ahead) >= need + 10, ahead
    assert driver.error is None
