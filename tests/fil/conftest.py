"""The fil tier: Klipper's atmega2560 firmware on simavr, klippy in normal mode.

A test module declares its printer (FIL_SECTIONS: config sections added to
fil_printer.cfg; FIL_SENSOR: the EMS22's pins for the simulator) and gets
one simulator + klippy for the whole module through the `printer` fixture.
Without simavr the tier is skipped with one loud line.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import pytest

from devtools import simavr, stack

HERE = Path(__file__).resolve().parent
MICROSTEPS = 16
FULL_STEPS = 200
ROTATION_DISTANCE = 7.71
COUNTS_PER_MM = 1024 / (math.pi * 3.17)
ROOM_TEMP_MV = 4775  # EPCOS 100K at 25 C behind a 4.7k pull-up on 5 V
SENSOR = "flow_sensor filament"


def pytest_terminal_summary(terminalreporter):
    reason = simavr.missing_simavr_reason()
    if reason:
        terminalreporter.write_line("!!! " + reason, red=True, bold=True)


def printer_config(sections: str) -> str:
    return (HERE / "fil_printer.cfg").read_text() + "\n" + sections


@pytest.fixture(scope="module")
def fil_build():
    reason = simavr.missing_simavr_reason()
    if reason:
        pytest.skip(reason)
    missing = stack.missing_klipper_reason()
    if missing:
        pytest.skip(missing)
    build = stack.build_klipper()
    simavr.build_harness()
    return build


@pytest.fixture(scope="module")
def printer(request, fil_build):
    """One simulator and one klippy for the module's tests, in order."""
    module = request.module
    venv = stack.klippy_venv()
    workdir = stack.short_tempdir("fl-fil-")
    mm_per_step = getattr(module, "TRUE_ROTATION_DISTANCE", ROTATION_DISTANCE) / (
        FULL_STEPS * MICROSTEPS)
    try:
        fil = simavr.start_printer(
            fil_build, venv, printer_config(module.FIL_SECTIONS), workdir,
            sensor=getattr(module, "FIL_SENSOR", {"cs": "PG0"}),
            mm_per_step=mm_per_step, counts_per_mm=COUNTS_PER_MM,
            heater_pin="PB4", adc_channel=13, adc_mv=ROOM_TEMP_MV)
    except simavr.HarnessError as e:
        shutil.rmtree(workdir, ignore_errors=True)
        pytest.fail(f"fil printer did not start: {e}", pytrace=False)
    yield fil
    simavr.stop_printer(fil)
    shutil.rmtree(workdir, ignore_errors=True)
