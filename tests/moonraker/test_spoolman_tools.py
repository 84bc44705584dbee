"""The Spoolman link on a two-tool printer (config/printer.cfg with
config/toolchanger.cfg, klippy in batch mode behind Moonraker, a real
Spoolman): Moonraker keeps one active spool, and each spool set goes to the
tool that prints when it is set (docs/toolchangers.md): the tool change
macro's SET_ACTIVE_SPOOL, here Moonraker's endpoint right after T1."""

from __future__ import annotations

import pytest

from devtools import stack
from tests.moonraker.test_spoolman import linked_spoolman
from tests.samples import make


@pytest.fixture(scope="module")
def two_tools(moonraker_venv):
    with linked_spoolman("fl-tools-sm-") as (sm, conf, data_dir):
        cfg = data_dir / "two_tools.cfg"
        cfg.write_text(f"[include {stack.PROJECT}/config/printer.cfg]\n"
                       f"[include {stack.PROJECT}/config/toolchanger.cfg]\n")
        with stack.printer_stack(printer_cfg=cfg, moonraker_conf=conf,
                                 data_dir=data_dir / "printer") as ps:
            yield sm, ps.moonraker


def _active(mr):
    return {extruder: entry["name"] for extruder, entry in mr.request(
        "GET", "/server/flowloop/profiles")[1]["result"]["active"].items()}


def _gcode(mr, script):
    status, body = mr.request("POST", "/printer/gcode/script", {"script": script})
    assert status == 200, body


def _spool_of(sm, mr, name):
    filament = sm.add_filament(name)
    assert mr.request("POST", "/server/flowloop/profile", {"profile": make(
        name=name, identity={"spoolman_filament_id": filament["id"]})})[0] == 200
    return sm.add_spool(filament["id"])["id"]


def test_each_spool_goes_to_the_tool_that_prints_when_it_is_set(two_tools):
    sm, mr = two_tools
    red, blue = _spool_of(sm, mr, "pla red"), _spool_of(sm, mr, "petg blue")
    _gcode(mr, "T0")
    mr.request("POST", "/server/spoolman/spool_id", {"spool_id": red})
    assert stack.wait_until(lambda: _active(mr) == {"extruder": "pla red"}, 10.0)
    _gcode(mr, "T1")
    mr.request("POST", "/server/spoolman/spool_id", {"spool_id": blue})
    assert stack.wait_until(lambda: _active(mr) == {
        "extruder": "pla red", "extruder1": "petg blue"}, 10.0), _active(mr)
    # klippy has each tool's profile: its limiter and autotemp use it
    status = mr.request("GET", "/printer/objects/query?flowrate_limiter%20extruder1"
                        "&autotemp")[1]["result"]["status"]
    assert status["flowrate_limiter extruder1"]["profile"] == "petg blue"
    assert status["autotemp"]["profile"] == "pla red"
