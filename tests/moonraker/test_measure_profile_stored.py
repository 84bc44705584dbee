"""MEASURE_MATERIAL_PROFILE between a real batch-mode klippy (the twin of
tests/klippy/measure_profile.cfg) and the real Moonraker: the measured
profile arrives through flowloop_store_profile, is stored with its points
and provenance, shows in Moonraker's API and comes back activated in klippy."""

from __future__ import annotations

from urllib.parse import quote

import pytest

from devtools import stack
from tests.samples import make

KNOWN = make(name="known pla", bounds=(185.0, 210.0, 250.0),
             air=(0.12, 210.0, 6.0), real=(0.12, 210.0, 6.0))
MEASURE = ("MEASURE_MATERIAL_PROFILE NAME=\"measured pla\" TEMPS=200,220,240 "
           "START_FLOW=4 STEP=0.25 MAX_FLOW=14 MIN_GRIP=0.9 ACTIVATE=1")
# klippy's config in the printer fixture (tests/moonraker/conftest.py)
PRINTER_CFG = "[include {project}/tests/klippy/measure_profile.cfg]\n"


def request(ps, method, path, body=None):
    return ps.moonraker.request(method, path, body)


def test_a_measured_profile_is_stored_with_its_points_and_provenance(printer):
    status, body = request(printer, "POST", "/server/flowloop/profile",
                           {"profile": KNOWN})
    assert status == 200, body
    status, body = request(printer, "POST", "/server/flowloop/profile/activate",
                           {"name": "known pla"})
    assert status == 200, body

    def measure():
        # The command starts the run and returns; Moonraker registers its
        # remote methods once klippy is ready: until then the run ends
        # measured but not stored, and runs again.
        printer.gcode(MEASURE)
        status = stack.wait_until(
            lambda: (s := printer.query("measure_profile"))["state"]
            != "running" and s, 120.0, 0.2)
        if status["state"] == "measured" and "not stored" in status["message"]:
            return False
        assert status["state"] == "stored", status
        return True
    assert stack.wait_until(measure, 60.0, 1.0)

    def stored():
        status, body = request(printer, "GET", "/server/flowloop/profile?name="
                               + quote("measured pla"))
        return body["result"]["profile"] if status == 200 else None
    profile = stack.wait_until(stored, 20.0)
    assert profile, "the measured profile never reached Moonraker"
    points = [p for p in profile["points"] if p["kind"] == "into_air"]
    assert len(points) == 3
    assert all(p["grip"] < 0.9 and 0 < p["heater_pwm"] < 255 for p in points)
    provenance = profile["provenance"]
    assert provenance["method"] == "into_air"
    assert provenance["source"] == "MEASURE_MATERIAL_PROFILE"
    assert provenance["min_grip"] == 0.9
    assert provenance["measured_at"].endswith("Z")
    assert "the other line from 'known pla'" in provenance["note"]
    assert profile["lines"]["into_air"]["slope_mm3_s_per_c"] == pytest.approx(
        0.12, rel=0.05)
    # listed, and active in klippy (ACTIVATE=1)
    status, body = request(printer, "GET", "/server/flowloop/profiles")
    summary = {p["name"]: p for p in body["result"]["profiles"]}["measured pla"]
    assert summary["method"] == "into_air"
    assert stack.wait_until(
        lambda: printer.query("flowloop")["profiles"].get("extruder", {}).get(
            "name") == "measured pla", 20.0)
    assert printer.query("measure_profile")["state"] == "stored"
