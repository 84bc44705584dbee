"""The Spoolman link against a real Spoolman (devtools/spoolman.py: its own
source and virtualenv, its real API and database; the web client is a
placeholder) and a real Moonraker whose [spoolman] talks to it: loading a
spool activates the profile of its filament; a spool loaded while Spoolman
is down changes nothing until Spoolman is back."""

from __future__ import annotations

import shutil
import time

import pytest

from devtools import spoolman, stack
from tests.samples import make


@pytest.fixture(scope="module")
def farm(moonraker_venv):
    """(Spoolman, Moonraker with flowloop's spoolman_link on it)."""
    reason = spoolman.missing_spoolman_reason()
    if reason:
        pytest.skip(reason)
    data_dir = stack.short_tempdir("fl-spoolman-")
    sm = spoolman.Spoolman(data_dir / "spoolman")
    mr = None
    try:
        sm.wait_ready()
        conf = f"spoolman_link: True\n\n[spoolman]\nserver: {sm.url}\n"
        mr = stack.Moonraker(moonraker_venv, data_dir / "moonraker",
                             extra_conf=conf)
        mr.wait_ready()
        yield sm, mr
    finally:
        if mr is not None:
            mr.stop()
        sm.stop()
        shutil.rmtree(data_dir, ignore_errors=True)


def _active(mr):
    result = mr.request("GET", "/server/flowloop/profiles")[1]
    return result["result"]["active"].get("extruder")


def _load_spool(mr, spool_id):
    status, body = mr.request("POST", "/server/spoolman/spool_id",
                              {"spool_id": spool_id})
    assert status == 200, body


def test_loading_a_spool_activates_the_profile_of_its_filament(farm):
    sm, mr = farm
    red = sm.add_filament("PLA red")
    other = sm.add_filament("PETG grey", material="PETG", density=1.27)
    red_spool = sm.add_spool(red["id"])["id"]
    other_spool = sm.add_spool(other["id"])["id"]
    profile = make(name="red pla", identity={"spoolman_filament_id": red["id"]})
    assert mr.request("POST", "/server/flowloop/profile",
                      {"profile": profile})[0] == 200
    assert _active(mr) is None
    _load_spool(mr, red_spool)
    assert stack.wait_until(lambda: _active(mr), 10.0) == {
        "name": "red pla", "working_point": 0.5}
    # a spool whose filament has no profile leaves the active one alone
    _load_spool(mr, other_spool)
    time.sleep(1.0)
    assert _active(mr) == {"name": "red pla", "working_point": 0.5}


def test_a_spool_loaded_while_spoolman_is_down_is_looked_up_when_it_is_back(farm):
    sm, mr = farm
    blue = sm.add_filament("PLA blue")
    blue_spool = sm.add_spool(blue["id"])["id"]
    assert mr.request("POST", "/server/flowloop/profile", {"profile": make(
        name="blue pla", identity={"spoolman_filament_id": blue["id"]})})[0] == 200
    before = _active(mr)
    sm.stop()
    try:
        # Moonraker takes the spool id; flowloop cannot read its filament
        mr.request("POST", "/server/spoolman/spool_id", {"spool_id": blue_spool})
        time.sleep(3.0)    # flowloop's request times out in 2 s
        assert _active(mr) == before
        log = (mr.data_dir / "moonraker.log").read_text()
        assert f"flowloop: Spoolman spool {blue_spool}:" in log
    finally:
        sm.restart()    # the same Spoolman, its data kept
    sm.wait_ready()
    # Moonraker does not announce the same spool again: flowloop asks once
    # Moonraker has reconnected to Spoolman
    assert stack.wait_until(lambda: _active(mr) == {
        "name": "blue pla", "working_point": 0.5}, 20.0)
    assert "flowloop: Spoolman is back: looking up spool" in (
        mr.data_dir / "moonraker.log").read_text()
