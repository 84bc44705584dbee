"""Realtime klippy (devtools/realtime_klippy.py): batch mode with print time
paced to the clock. A G-code move of N seconds takes about N seconds of wall
time, and the simulated sensor's samples and grip windows arrive while it
runs, never ahead of the clock. (Timing figures: make bench, not here.)"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from devtools import stack
from devtools.klippy_api import KlippyApi

# paced to the wall clock, and judged by it: no other test beside these
pytestmark = pytest.mark.alone

HERE = Path(__file__).resolve().parent
MOVE_S = 6.0
SENSOR = "flow_sensor sim"


def _poll(path, polls, stop):
    with KlippyApi(path) as api:
        while not stop.is_set():
            status = api.call("objects/query", objects={
                SENSOR: None, "toolhead": ["estimated_print_time"]})["status"]
            polls.append((time.monotonic(), status[SENSOR],
                          status["toolhead"]["estimated_print_time"]))
            time.sleep(0.25)


def test_a_move_takes_its_time_and_the_sensor_follows_the_clock(
        klipper_build, klippy_venv, short_tmp):
    klippy = stack.Klippy(klipper_build, klippy_venv,
                          HERE / "simulated_realtime.cfg", short_tmp,
                          {"mcu": "atmega2560"}, realtime=True)
    polls, stop = [], threading.Event()
    try:
        api = klippy.ready_api()
        api.gcode("SET_HEATER_TEMPERATURE HEATER=extruder TARGET=210\nG28\n"
                  "M83\nG1 Z1 F600\nM400")
        poller = threading.Thread(target=_poll,
                                  args=(klippy.api_socket, polls, stop))
        poller.start()
        start = time.monotonic()
        # 120 mm at 20 mm/s feeding 6 mm of filament (2.4 mm^3/s)
        api.gcode(f"G1 X120 E6 F{120 / MOVE_S * 60:.0f}\nM400")
        took = time.monotonic() - start
        time.sleep(0.5)
        stop.set()
        poller.join()
        final = api.query(SENSOR)
    finally:
        stop.set()
        klippy.stop()
    # about N seconds of wall time (accelerations add a little)
    assert MOVE_S * 0.9 < took < MOVE_S + 3.0, klippy.log_tail()
    assert final["simulation"] == {
        "clock": "step_generator" if klipper_build.host == "kalico"
        else "motion_queuing", "realtime": True}
    during = [p for p in polls if start + 0.5 < p[0] < start + took - 0.5]
    assert len(during) >= 8
    samples = [s["samples"] for _, s, _ in during]
    positions = [s["filament_position"] for _, s, _ in during]
    # samples keep arriving while the move runs, the filament moves with them
    assert samples == sorted(samples) and len(set(samples)) >= 6
    assert positions == sorted(positions)
    assert positions[0] < positions[-1] < final["filament_position"]
    # grip windows were judged before the move ended
    assert any(s["grip"] is not None and 0.95 < s["grip"] < 1.05
               for _, s, _ in during)
    # print time follows the wall clock: about as much of it passed
    (w0, _, p0), (w1, _, p1) = during[0], during[-1]
    assert 0.8 < (p1 - p0) / (w1 - w0) < 1.25
    # and about 250 samples a second of it, never many ahead of the clock
    rate = (samples[-1] - samples[0]) / (w1 - w0)
    assert 150 < rate < 350
    assert final["filament_position"] > 5.5


def test_the_printer_klippy_builds_after_a_restart_is_paced_too(
        klipper_build, klippy_venv, short_tmp):
    klippy = stack.Klippy(klipper_build, klippy_venv,
                          HERE / "simulated_realtime.cfg", short_tmp,
                          {"mcu": "atmega2560"}, realtime=True)
    try:
        api = klippy.ready_api()
        api.send("gcode/script", script="RESTART")
        api.close()
        # the old printer's socket closes; the new one opens the same path
        time.sleep(2.0)
        api = stack.wait_until(lambda: _reconnect(klippy), 30)
        api.gcode("SET_HEATER_TEMPERATURE HEATER=extruder TARGET=210\nG28\nM83")
        start = time.monotonic()
        api.gcode("G1 X60 E3 F1200\nM400")   # 3 s
        took = time.monotonic() - start
        status = api.query(SENSOR)
    finally:
        klippy.stop()
    assert 2.7 < took < 6.0
    assert status["simulation"]["realtime"] is True
    assert status["filament_position"] > 2.5


def _reconnect(klippy):
    try:
        api = KlippyApi(klippy.api_socket, timeout=5)
        if api.call("info")["state"] == "ready":
            return api
        api.close()
    except (OSError, RuntimeError, ValueError):
        pass
    return None
