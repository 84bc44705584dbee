"""The flowrate limiter's status reaches a Moonraker client (what Mainsail and
Fluidd read), and a change made with SET_FLOWRATE_LIMIT shows in it."""

from __future__ import annotations

from urllib.parse import quote

import pytest

from flowloop.control import nozzle_health as nh
from flowloop.control.grip_model import CLIMB_FROM
from flowloop.control.limiter import SEED_PROBE
from tests.nozzle_prints import PROFILE, simulate_print
from tests.samples import twin_known

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


def test_an_activation_seeds_the_model_with_the_hotends_newest_melt_ratio(
        printer):
    # issue 41's carry-over: what nozzle health judged of this hotend and
    # profile in its last print goes with the next activation to klippy
    data = twin_known()
    status, body = printer.moonraker.request("POST", "/server/flowloop/profile",
                                             {"profile": data})
    assert status == 200, body
    name = data["identity"]["name"]

    def activated():
        status, body = printer.moonraker.request(
            "POST", "/server/flowloop/profile/activate", {"name": name})
        assert status == 200 and body["result"]["sent_to_klippy"], body
        return printer.query("flowrate_limiter")

    fresh = activated()
    assert fresh["seed_melt_ratio"] is None and fresh["profile"] == name
    # a first print's model climbs from CLIMB_FROM of the profile's capacity
    assert fresh["model"]["climb_ratio"] == pytest.approx(CLIMB_FROM, abs=1e-4)
    line_capacity = fresh["model"]["capacity_mm3_s"] / fresh["model"]["climb_ratio"]
    evidence = nh.evidence_of(simulate_print(0.8, seed=3), PROFILE).to_dict()
    status, body = printer.moonraker.request(
        "POST", "/server/flowloop/nozzle_health",
        {"job_id": "00000A", "evidence": {**evidence, "profile": name}})
    assert status == 200, body
    ratio = body["result"]["entry"]["ratio"]
    assert ratio == pytest.approx(0.8, abs=0.03)
    seeded = activated()
    assert seeded["seed_melt_ratio"] == pytest.approx(ratio, abs=1e-4)
    # (SEED_PROBE above it, so that its first capped windows can confirm
    # it; no climb)
    assert seeded["model"]["capacity_mm3_s"] == pytest.approx(
        ratio * (1.0 + SEED_PROBE) * line_capacity, rel=1e-3)
    assert seeded["model"]["climb_ratio"] is None
    # a new nozzle: its profile's history deleted, the profile's line again
    status, body = printer.moonraker.request(
        "DELETE", f"/server/flowloop/nozzle_health?profile={quote(name)}")
    assert status == 200, body
    assert activated()["seed_melt_ratio"] is None
