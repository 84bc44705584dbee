"""[flowrate_limiter] judged on what Klipper really sends to the MCU: the
batch output decoded with Klipper's own parsedump.py, the extruder's steps
rebuilt into flow over time (flowrate_limiter_steps.py)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from devtools.klippy_test import run_file
from tests.klippy.flowrate_limiter_steps import parsedump, stepper_steps, windowed_flow

HERE = Path(__file__).resolve().parent
GCODE = HERE.parent / "data" / "gcode" / "block_layers_1_2.gcode"
CLOCK_HZ = 16e6                       # atmega2560
MM_PER_STEP = 7.71 / (200 * 16)       # flow_sensor_printer.cfg's extruder
AREA = math.pi * 1.75 ** 2 / 4
CAP = 4.0                             # flowrate_limiter_file.cfg
WINDOW_S = 0.1


def gcode_extrusion(path: Path) -> float:
    """Net E of a slicer file (absolute E, G92 resets), as the slicer meant it."""
    total = e = 0.0
    for line in path.read_text().splitlines():
        words = line.split(";")[0].split()
        if not words:
            continue
        if words[0] == "G92":
            total += e
            e = 0.0
        elif words[0] in ("G0", "G1"):
            for w in words[1:]:
                if w[0] == "E":
                    e = float(w[1:])
    return total + e


def run(klipper_build, klippy_venv, tmp, first_lines=""):
    gcode = tmp / "print.gcode"
    gcode.write_text(first_lines + GCODE.read_text())
    test = tmp / "file.test"
    test.write_text(f"DICTIONARY atmega2560.dict\n"
                    f"CONFIG {HERE / 'flowrate_limiter_file.cfg'}\n"
                    f"GCODE {gcode}\n")
    log = run_file(test, klipper_build, klippy_venv, tmp)
    lines = parsedump(klipper_build, klippy_venv,
                      klipper_build.dictionary("atmega2560"), tmp / "run0.output")
    return log, lines


@pytest.fixture(scope="module")
def runs(klipper_build, klippy_venv, tmp_path_factory):
    on = run(klipper_build, klippy_venv, tmp_path_factory.mktemp("on"))
    off = run(klipper_build, klippy_venv, tmp_path_factory.mktemp("off"),
              "SET_FLOWRATE_LIMIT ENABLE=0\n")
    return on, off


def test_flow_never_exceeds_the_cap_on_a_slicer_file(runs):
    (_, on), (_, off) = runs
    limited = windowed_flow(*stepper_steps(on, "PA4"), CLOCK_HZ, MM_PER_STEP,
                            AREA, WINDOW_S)
    free = windowed_flow(*stepper_steps(off, "PA4"), CLOCK_HZ, MM_PER_STEP,
                         AREA, WINDOW_S)
    # one step of quantisation in a window, nothing more
    allowed_steps = CAP * WINDOW_S / (AREA * MM_PER_STEP)
    assert limited["max_steps"] <= math.ceil(allowed_steps) + 1
    # the same file without the limiter asks for far more
    assert free["max_flow"] > 2 * CAP


def test_e_totals_and_positions_are_unchanged(runs):
    (_, on), (_, off) = runs
    want = gcode_extrusion(GCODE)
    for lines in (on, off):
        clocks, dirs = stepper_steps(lines, "PA4")
        assert dirs.sum() * MM_PER_STEP == pytest.approx(want, abs=2 * MM_PER_STEP)
    for pin in ("PF0", "PF6", "PL3"):  # x, y, z end where the file says
        assert stepper_steps(on, pin)[1].sum() == stepper_steps(off, pin)[1].sum()


def test_the_limiter_slows_the_print_and_says_by_how_much(runs):
    (log_on, on), (log_off, off) = runs
    end_on = stepper_steps(on, "PA4")[0][-1] / CLOCK_HZ
    end_off = stepper_steps(off, "PA4")[0][-1] / CLOCK_HZ
    assert end_on > end_off + 30.0
    assert "slowed 0 moves" not in log_on
