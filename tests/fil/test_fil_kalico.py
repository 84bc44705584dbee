"""The same firmware-in-the-loop path on Kalico (its atmega2560 build with
flowloop's EMS22 option, its klippy in normal mode): samples arrive, a G1 E
move gives the model's grip, and a fault is reported and clears."""

from __future__ import annotations

import time

import pytest

from devtools import stack
from tests.fil.conftest import COUNTS_PER_MM, SENSOR, build_or_skip, fil_printer

SECTIONS = """
[flow_sensor filament]
sensor_type: ems22
cs_pin: PG0
grip_window: 10
"""


@pytest.fixture(scope="module")
def kalico():
    with fil_printer(build_or_skip("kalico"), SECTIONS) as printer:
        yield printer


def test_samples_arrive_on_kalico(kalico):
    assert stack.wait_until(
        lambda: kalico.query(SENSOR)["sample_rate"] >= 240, 3, 0.1)
    lines = kalico.gcode_console("QUERY_FLOW_SENSOR")
    assert any("250 samples/s" in line and "errors none, fault none" in line
               for line in lines), lines


def test_a_g1_e_move_gives_the_models_grip_on_kalico(kalico):
    kalico.sim.control("grip 0.95")
    model0 = float(kalico.sim.status()["filament_mm"])
    sensor0 = kalico.query(SENSOR)["filament_position"]
    kalico.gcode("M83\nG1 E30 F900\nM400")
    time.sleep(0.4)
    status = kalico.query(SENSOR)
    model_mm = float(kalico.sim.status()["filament_mm"]) - model0
    assert abs(status["filament_position"] - sensor0 - model_mm) \
        <= 2.5 / COUNTS_PER_MM
    assert status["grip"] == pytest.approx(0.95, rel=0.002)


def test_a_fault_clears_on_kalico(kalico):
    kalico.sim.control("fault parity")
    try:
        assert stack.wait_until(
            lambda: kalico.query(SENSOR)["fault"] == "parity", 3, 0.1)
    finally:
        kalico.sim.control("fault none")
    assert stack.wait_until(lambda: kalico.query(SENSOR)["fault"] is None, 3, 0.1)
