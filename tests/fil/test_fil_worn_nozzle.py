"""A worn nozzle through the real firmware (issue 41): the hotend melts 15 %
less than its active profile says. A job printed through a real Moonraker
asks for a flow the profile says the hotend melts; the harness's filament
slips where the worn melt line cannot keep up (the grip the EMS22 model's
shaft sees), and flowloop's flow report says how much was under-extruded.
With the predictive limiter off the whole job slips; with it on the limiter
learns what this hotend melts from the sensor's grip windows, says so in its
status, and slows the rest of the job to it."""

from __future__ import annotations

import math

import pytest

from devtools import simavr
from devtools.demo_flowrate_limiter import WEAK_PROFILE
from flowloop.material.profile import (
    DEFAULT_WORKING_POINT,
    profile_from_dict,
    profile_line,
)
from flowloop.sensor.twin import scaled_line
from tests.fil.conftest import (
    FULL_STEPS,
    MICROSTEPS,
    ROTATION_DISTANCE,
    activate,
    ended_job,
    fil_moonraker,
    job_report,
    start_job,
)

HOTEND_C = 215.0  # the harness holds the thermistor pin here
WEAR = 0.85       # the bench's worn nozzle (bench_flowrate_limiter.HOTENDS)
PROFILE_LINE = profile_line(profile_from_dict(WEAK_PROFILE), DEFAULT_WORKING_POINT)
WORN_LINE = scaled_line(PROFILE_LINE, WEAR)
AREA_MM2 = math.pi * 1.75 ** 2 / 4
MM_PER_STEP = ROTATION_DISTANCE / (FULL_STEPS * MICROSTEPS)
# Asked of the hotend: under the profile's line at HOTEND_C (5.5 mm^3/s),
# above what the worn nozzle melts there (4.68)
FLOW_MM3_S = 5.2
MOVES, MOVE_MM = 30, 2.0  # 60 mm of filament, about 28 s
# On / off at most (measured: 0.10x by the report, 0.12x by the harness).
# The limiter slips until its first grip windows come back and a buffer's
# worth of moves has run: about 3 s here, a large share of a 28 s print;
# the bench's 346 s print of the same worn nozzle leaves 0.015x.
RATIO_GOAL = 0.25


class HeldHotend:
    """The hotend model HotendDriver steps, held at a temperature (as the
    harness holds the thermistor pin): only the melt line changes grip."""

    class params:
        max_power_w = 40.0

    def __init__(self, temp_c: float):
        self.temp_c, self.time_s, self.fixed_power_w = temp_c, 0.0, 0.0

    def advance(self, time_s: float, melted_mm3_s: float) -> None:
        self.time_s = time_s


def gcode_file() -> str:
    feed = FLOW_MM3_S / AREA_MM2 * 60
    return "M83\n" + f"G1 E{MOVE_MM} F{feed:.2f}\n" * MOVES


@pytest.fixture(scope="module")
def worn(fil_build, moonraker_venv):
    with fil_moonraker(fil_build, moonraker_venv, WEAK_PROFILE,
                       hotend_temp_c=HOTEND_C) as (printer, server):
        with simavr.HotendDriver(printer.sim, HeldHotend(HOTEND_C),
                                 WORN_LINE, MM_PER_STEP, AREA_MM2):
            yield printer, server


def _set_limiter(server, on: bool) -> None:
    status, body = server.request(
        "POST", "/printer/gcode/script",
        {"script": f"SET_FLOWRATE_LIMIT ENABLE={int(on)}"})
    assert status == 200, body


def _job(printer, server, name: str, limiter_on: bool) -> dict:
    """Print the file as job `name` with a fresh grip model (the profile
    activated again) and the limiter on or off; its flow report's summary,
    what the harness's model fed against what the steps commanded, and the
    limiter's status at the end."""
    activate(server, WEAK_PROFILE)
    _set_limiter(server, limiter_on)
    before = printer.sim.status()
    start_job(server, name, gcode_file())
    job = ended_job(server, name, ("completed",), timeout=120)
    limiter = printer.query("flowrate_limiter")
    summary = job_report(server, job)
    after = printer.sim.status()
    commanded = (int(after["steps"]) - int(before["steps"])) * MM_PER_STEP
    fed = float(after["filament_mm"]) - float(before["filament_mm"])
    return {"summary": summary, "truth_mm": commanded - fed,
            "limiter": limiter}


def test_the_limiter_learns_a_worn_nozzle_and_prevents_its_slip(worn):
    printer, server = worn
    on = _job(printer, server, "worn_on.gcode", limiter_on=True)
    off = _job(printer, server, "worn_off.gcode", limiter_on=False)
    _set_limiter(server, True)
    under_on = on["summary"]["under_extruded_mm"]
    under_off = off["summary"]["under_extruded_mm"]
    believed = on["limiter"]["caps"]["model"]
    worn_capacity = WORN_LINE.flow_mm3_s(HOTEND_C)
    print(f"worn nozzle ({worn_capacity:.3f} mm^3/s at {HOTEND_C:g} C, the"
          f" profile {PROFILE_LINE.flow_mm3_s(HOTEND_C):.3f}), asked"
          f" {FLOW_MM3_S} mm^3/s: limiter off {under_off:.3f} mm under-"
          f"extruded (the harness: {off['truth_mm']:.3f}) in"
          f" {off['summary']['duration_s']:.1f} s; on {under_on:.3f} mm (the"
          f" harness: {on['truth_mm']:.3f}) in {on['summary']['duration_s']:.1f}"
          f" s, slowed {on['summary']['slowed_s']:.1f} s; {under_on / under_off:.3f}x;"
          f" the limiter believes the hotend melts {believed} mm^3/s")
    # the report measures what the harness's filament really lost, as well
    # as it can: from the grip of the window last closed when it samples,
    # where grip is more than its noise (2 %) below 1. Off, the slip is 10 %:
    # all of it counts. On, what is left after the limiter learned slips
    # under 1 %, which the report does not count (0.57 of 0.83 mm once)
    assert under_off == pytest.approx(off["truth_mm"], rel=0.15), off
    assert under_on <= on["truth_mm"] + 0.25, on
    # off, the whole job slips: 1 - 4.68 / 5.2 of 60 mm
    assert under_off == pytest.approx(
        MOVES * MOVE_MM * (1 - worn_capacity / FLOW_MM3_S), rel=0.15)
    assert under_on <= RATIO_GOAL * under_off
    assert on["truth_mm"] <= RATIO_GOAL * off["truth_mm"]
    # it says what it believes the hotend melts, and it is the worn line
    assert believed == pytest.approx(worn_capacity, rel=0.05)
    assert on["summary"]["slowed_s"] > 0
    assert off["summary"]["slowed_s"] == 0
