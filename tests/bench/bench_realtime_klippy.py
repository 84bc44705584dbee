"""Realtime klippy (devtools/realtime_klippy.py): how closely batch-mode
klippy paced to the clock keeps real time, on the simulated sensor's printer
(tests/klippy/simulated_realtime.cfg).

- Pace: wall time of two G-code moves (M400 after them) against the print
  time the toolhead advanced over them in the same klippy (which includes
  the 0.25 s it starts ahead of the clock). Goal: 0.95x..1.05x.
- Lead: how far the toolhead's print time ran ahead of the clock when the
  G-code call returned (the G-code reader is held there), against Klipper's
  BUFFER_TIME_HIGH of the same tree. Goal: <= 1.0x.
- Sensor: simulated samples per second of wall time during the move, against
  the rate its sample_period asks for. Goal: 0.95x..1.05x.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from devtools import stack
from tests.bench.size import pick

# paced to the wall clock: under make test's scheduler, with no other test beside it
pytestmark = pytest.mark.alone

CFG = Path(__file__).resolve().parents[1] / "klippy" / "simulated_realtime.cfg"
SENSOR = "flow_sensor sim"
MOVE_S = pick(8.0, 2.0)
SAMPLE_PERIOD_S = 0.004  # flow_sensor_sim.cfg: the default


def _buffer_time_high(build) -> float:
    for line in (build.tree / "klippy" / "toolhead.py").read_text().splitlines():
        if line.startswith("BUFFER_TIME_HIGH"):
            return float(line.split("=")[1])
    pytest.skip("no BUFFER_TIME_HIGH in this klippy's toolhead.py")


def test_realtime_klippy_keeps_time(bench, klipper_build, klippy_venv, short_tmp):
    klippy = stack.Klippy(klipper_build, klippy_venv, CFG, short_tmp,
                          {"mcu": "atmega2560"}, realtime=True)
    try:
        with klippy.ready_api() as api:
            api.gcode("SET_HEATER_TEMPERATURE HEATER=extruder TARGET=210\n"
                      "G28\nM83\nG1 Z1 F600\nM400")
            samples0 = api.query(SENSOR)["samples"]
            print0 = api.query("toolhead")["print_time"]
            start = time.monotonic()
            api.gcode(f"G1 X150 E8 F{150 / MOVE_S * 60:.0f}\n"
                      f"G1 X10 F{140 / MOVE_S * 60:.0f}")
            returned = time.monotonic()
            head = api.call("objects/query", objects={
                "toolhead": ["print_time", "estimated_print_time"]})["status"]
            api.gcode("M400")
            wall = time.monotonic() - start
            samples = api.query(SENSOR)["samples"] - samples0
            moved = api.query("toolhead")["print_time"] - print0
    finally:
        klippy.stop()
    bench.ratio("realtime klippy: wall time of the moves / their print time",
                wall, moved, " s", "0.95x..1.05x")
    lead = head["toolhead"]["print_time"] - head["toolhead"]["estimated_print_time"]
    bench.ratio("realtime klippy: print time ahead of the clock when G-code "
                f"returned ({returned - start:.1f} s in) / BUFFER_TIME_HIGH",
                lead, _buffer_time_high(klipper_build), " s", "<= 1.0x")
    bench.ratio("realtime klippy: simulated samples per wall second / "
                "1 / sample_period", samples / wall, 1.0 / SAMPLE_PERIOD_S,
                "/s", "0.95x..1.05x")
