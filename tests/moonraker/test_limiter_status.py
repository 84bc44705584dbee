"""The flowrate limiter's status reaches a Moonraker client (what Mainsail and
Fluidd read), and a change made with SET_FLOWRATE_LIMIT shows in it."""

from __future__ import annotations

import pytest

# klippy's config in the printer fixture (tests/moonraker/conftest.py)
PRINTER_CFG = """\
[include {project}/config/printer.cfg]

[flowrate_limiter]
max_flow: 9
"""

FIELDS = {"enabled", "cap", "reason", "slowed_time", "slowed_moves", "model"}


def gcode(ps, script):
    status, body = ps.moonraker.request("POST", "/printer/gcode/script",
                                        {"script": script})
    assert status == 200, body


def test_the_limiter_status_reaches_a_moonraker_client(printer):
    status = printer.query("flowrate_limiter")
    assert FIELDS <= set(status), sorted(status)
    assert status["enabled"] is True
    assert status["cap"] == pytest.approx(9.0)


def test_a_new_max_flow_shows_in_the_status_a_client_reads(printer):
    gcode(printer, "SET_FLOWRATE_LIMIT MAX_FLOW=4.5")
    assert printer.query("flowrate_limiter")["cap"] == pytest.approx(4.5)
    gcode(printer, "SET_FLOWRATE_LIMIT ENABLE=0")
    assert printer.query("flowrate_limiter")["enabled"] is False


def test_bad_input_through_moonraker_changes_nothing(printer):
    gcode(printer, "SET_FLOWRATE_LIMIT ENABLE=1 MAX_FLOW=6")
    status, body = printer.moonraker.request(
        "POST", "/printer/gcode/script", {"script": "SET_FLOWRATE_LIMIT MAX_FLOW=-3"})
    assert status == 400, body
    assert "MAX_FLOW" in str(body) or "max_flow" in str(body)
    assert printer.query("flowrate_limiter")["cap"] == pytest.approx(6.0)
