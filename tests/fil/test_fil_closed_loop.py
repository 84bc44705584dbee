"""The closed loop on the real firmware's steps: the model's extruder feeds 5 %
more than its configured rotation_distance says; the calibration commands
find that from the sensor, and the flowrate limiter slows the moves that
follow a drop of the model's grip (the reaction measured in real time at the
extruder's step pin)."""

from __future__ import annotations

import re
import time

import numpy as np
import pytest

from devtools.klippy_api import KlippyApi
from tests.fil.conftest import ROTATION_DISTANCE, SENSOR, settle

TRUE_ROTATION_DISTANCE = ROTATION_DISTANCE * 1.05
FIL_SECTIONS = """
[flow_sensor filament]
sensor_type: ems22
cs_pin: PG0

[flowrate_limiter]
mode: reactive
"""
AREA_MM2 = np.pi * 1.75 ** 2 / 4


def _toolhead_e(printer) -> float:
    return printer.query("toolhead")["position"][3]


def _extrude(printer, script: str):
    """(sensor status before, after, toolhead E moved, model filament fed)"""
    before, e0 = settle(printer), _toolhead_e(printer)
    model0 = float(printer.sim.status()["filament_mm"])
    printer.gcode(script + "\nM400")
    after, e1 = settle(printer), _toolhead_e(printer)
    return before, after, e1 - e0, float(printer.sim.status()["filament_mm"]) - model0


def test_calibrate_flow_sensor_finds_what_the_extruder_really_feeds(printer):
    lines = printer.gcode_console(
        "CALIBRATE_FLOW_SENSOR LENGTH=10 SPEEDS=4,8")
    print("\n".join(lines))
    assert settle(printer)["calibration"] == pytest.approx(1.05, rel=0.002)
    # The sensor's position restarts at its first sample after a new
    # calibration; the calibration moved the toolhead, not G-code's position
    # (test_a_g1_e_after_a_calibration_feeds_what_it_says checks that G-code
    # follows): measure against the toolhead's E.
    printer.gcode("M83\nG1 E1 F3000\nM400")
    before, after, moved, _ = _extrude(printer, "G1 E15 F600")
    assert moved > 10
    # the grip of the whole move (filament_position is in calibrated mm)
    sensor_mm = after["filament_position"] - before["filament_position"]
    assert sensor_mm / moved == pytest.approx(1.0, rel=0.002)


def test_calibrate_extruder_rotation_distance_recovers_the_true_one(printer):
    lines = printer.gcode_console(
        "CALIBRATE_EXTRUDER_ROTATION_DISTANCE LENGTH=20 SPEED=5")
    text = "\n".join(lines)
    print(text)
    found = re.search(r"extruder rotation_distance ([0-9.]+) -> ([0-9.]+)", text)
    assert found, text
    assert float(found.group(1)) == pytest.approx(ROTATION_DISTANCE)
    assert float(found.group(2)) == pytest.approx(TRUE_ROTATION_DISTANCE,
                                                  rel=0.002)
    assert settle(printer)["calibration"] == 1.0
    printer.gcode("M83\nG1 E20 F1200\nM400")
    _, after, moved, fed = _extrude(printer, "G1 E20 F1200")
    assert moved > 10
    assert fed / moved == pytest.approx(1.0, rel=0.002)
    assert after["grip"] == pytest.approx(1.0, abs=0.012)  # 1.25 mm windows


def test_a_g1_e_after_a_calibration_feeds_what_it_says(printer):
    printer.gcode("CALIBRATE_EXTRUDER_ROTATION_DISTANCE LENGTH=10 SPEED=5")
    _, _, moved, fed = _extrude(printer, "M83\nG1 E10 F1200")
    assert fed == pytest.approx(10.0, rel=0.002), (moved, fed)


FLOW_MM3_S, SEGMENT_E_MM = 7.0, 0.5
DROP_AFTER_S, PRINT_S = 4.0, 10.0
GRIP_AFTER_DROP = 0.8


def _step_rate(samples, start, end):
    (t, steps) = samples
    inside = (t >= start) & (t <= end)
    if inside.sum() < 2:
        return None
    return np.ptp(steps[inside]) / np.ptp(t[inside])


def test_the_limiter_slows_the_next_moves_after_the_grip_drops(printer):
    printer.sim.control("grip 1.0")
    e_speed = FLOW_MM3_S / AREA_MM2
    count = int(PRINT_S * e_speed / SEGMENT_E_MM)
    script = "\n".join(["M83"] + [f"G1 E{SEGMENT_E_MM} F{e_speed * 60:.1f}"]
                       * count + ["M400"])
    polls = []
    with KlippyApi(printer.klippy.api_socket) as printing:
        first_steps = int(printer.sim.status()["steps"])
        printing.send("gcode/script", script=script)
        deadline = time.monotonic() + PRINT_S + 10
        drop_at = None
        while time.monotonic() < deadline:
            status = printer.sim.status()
            now, steps = time.monotonic(), int(status["steps"])
            polls.append((now, steps))
            if drop_at is None and steps > first_steps:
                started = now
                drop_at = started + DROP_AFTER_S
            if drop_at and now >= drop_at and polls[-2][0] < drop_at:
                printer.sim.control(f"grip {GRIP_AFTER_DROP}")
                drop_at = now
            if drop_at and now > started + PRINT_S * 1.3:
                break
            time.sleep(0.05)
    printer.sim.control("grip 1.0")
    samples = tuple(np.array(c, dtype=float) for c in zip(*polls))
    steady = _step_rate(samples, drop_at - 2.5, drop_at)
    slowed_at = None
    for t in samples[0][samples[0] > drop_at]:
        rate = _step_rate(samples, t, t + 0.5)
        if rate is not None and rate < 0.93 * steady:
            slowed_at = t
            break
    limiter = printer.query("flowrate_limiter")
    print(f"steady {steady:.0f} steps/s; grip {GRIP_AFTER_DROP} at the model;"
          f" first slowed steps {None if slowed_at is None else slowed_at - drop_at}"
          f" s later; limiter {limiter['reason']}, cap {limiter['cap']},"
          f" slowed_moves {limiter['slowed_moves']}")
    assert limiter["grip_windows"]["below_min_grip"] > 0, limiter
    assert limiter["slowed_moves"] > 0, limiter
    assert slowed_at is not None, "the step rate never fell after the drop"
    # a grip window (0.43 s here), a batch, and klippy's ~1 s of buffered moves
    assert slowed_at - drop_at < 3.0
    assert printer.query(SENSOR)["fault"] is None
