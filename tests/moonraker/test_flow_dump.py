"""flow_sensor/dump_flow streams samples to API clients, as angle/dump_angle does.

A client connects to klippy's own API socket (what Moonraker and Klipper's
scripts/motan use), subscribes, and the simulated sensor of the demo printer
follows a real extrude move.
"""

from __future__ import annotations

import pytest

from devtools.klippy_api import KlippyApi
from flowloop.sensor import ems22


def test_dump_flow_streams_sensor_and_commanded_filament(printer):
    with KlippyApi(printer.klippy.api_socket, timeout=0.5) as client:
        client.send("flow_sensor/dump_flow", sensor="sim",
                    response_template={"key": "flow"})
        first = next(client.messages(5))
        assert first["result"]["header"] == ["time", "filament_mm", "commanded_mm"]
        # 2 s at 5 mm/s is 12 mm^3/s, more than the twin melts at 200 C. Print
        # time does not follow the clock in batch mode: M400 makes klippy
        # generate the steps, which is when the twin samples.
        printer.gcode("G28\nM83\nSET_HEATER_TEMPERATURE HEATER=extruder TARGET=200\n"
                      "G1 E10 F300\nM400")
        rows = []
        for msg in client.messages(3):
            if msg.get("key") == "flow":  # the template, merged at top level
                rows += msg["params"].get("data", [])
    times = [r[0] for r in rows]
    assert times == sorted(times)
    moving = [r for r in rows if r[2] > rows[0][2]]
    # every read of about 2 s of extrusion at the default sample_period
    assert len(moving) > 1.5 / ems22.DEFAULT_SAMPLE_PERIOD_S
    commanded = rows[-1][2] - rows[0][2]
    measured = rows[-1][1] - rows[0][1]
    assert commanded == pytest.approx(10, abs=0.5)
    # the twin melts 10 mm^3/s at 200 C of the 12 asked: the sensor sees it slip
    assert 0.6 * commanded < measured < 0.95 * commanded


def test_dump_flow_names_an_unknown_sensor(printer):
    with KlippyApi(printer.klippy.api_socket, timeout=0.5) as client:
        client.send("flow_sensor/dump_flow", sensor="nope",
                    response_template={"key": "x"})
        reply = next(client.messages(5))
    assert "nope" in reply["error"]["message"]
