"""The moonraker tier: the real Moonraker from PyPI with flowloop's component."""

from __future__ import annotations

import os
import signal
import time

import pytest

from devtools import stack
from flowloop.host import install
from tests.moonraker.conftest import copy_of_moonraker, moonraker_from


@pytest.fixture(scope="module")
def moonraker_only(moonraker_venv):
    with stack.printer_stack(with_klippy=False) as printer:
        yield printer


@pytest.fixture(scope="module")
def full_stack(klipper_build, klippy_venv, moonraker_venv):
    with stack.printer_stack() as printer:
        yield printer


def test_info_without_klippy_says_it_is_not_connected(moonraker_only):
    status, body = moonraker_only.moonraker.request("GET", "/server/flowloop/info")
    assert status == 200
    info = body["result"]
    assert info["klippy_connected"] is False
    assert info["version"] == __import__("flowloop").__version__


def test_info_reports_what_klippy_loaded(full_stack):
    status, body = full_stack.moonraker.request("GET", "/server/flowloop/info")
    assert status == 200
    info = body["result"]
    assert info["klippy_connected"] is True
    assert info["klippy_version"] == info["version"]
    assert "mcu" in info["sensor_firmware"]
    cfg = (stack.PROJECT / "config" / "printer.cfg").read_text()
    declared = sorted(line.strip("[]") for line in cfg.splitlines()
                      if line.startswith("[") and line.strip("[]").split()[0] in (
                          "flow_sensor", "flow_sensor_simulation",
                          "flowrate_limiter", "autotemp",
                          "diff_ab_calibrate", "endstop_calibrate"))
    assert declared and info["sections"] == declared


@pytest.mark.alone  # measures how long the answer takes
def test_info_answers_in_bounded_time_while_klippy_does_not(full_stack):
    def info(timeout=10.0):
        status, body = full_stack.moonraker.request("GET", "/server/flowloop/info",
                                                    timeout=timeout)
        assert status == 200, body
        return body["result"]
    before = info()
    os.kill(full_stack.klippy.pid, signal.SIGSTOP)  # connected, never answering
    try:
        start = time.monotonic()
        stopped = info(timeout=6.0)
        elapsed = time.monotonic() - start
    finally:
        os.kill(full_stack.klippy.pid, signal.SIGCONT)
    assert elapsed < 4.0
    assert before["klippy_answered"] is True
    assert stopped["klippy_connected"] is True and stopped["klippy_answered"] is False
    assert stopped["klippy_state"] == "ready"
    # what klippy said last
    for key in ("klippy_version", "sections", "sensor_firmware"):
        assert stopped[key] == before[key], key
    assert stack.wait_until(lambda: info()["klippy_answered"], 10.0)


def test_sensor_firmware_check_matches_the_built_dictionary(full_stack, klipper_build):
    from flowloop.sensor import ems22
    has_command = ems22.QUERY_CMD.split()[0] in klipper_build.dictionary(
        "atmega2560").read_text()
    info = full_stack.moonraker.request("GET", "/server/flowloop/info")[1]["result"]
    assert info["sensor_firmware"]["mcu"] is has_command


def test_gcode_reaches_the_batch_mode_klippy(full_stack):
    full_stack.gcode("G28\nG1 X12 Y7 F3000")
    assert full_stack.query("toolhead")["position"][:2] == [12.0, 7.0]


def test_installing_flowloop_moved_no_pinned_moonraker_package(moonraker_venv):
    assert moonraker_venv.moved_by_flowloop() == {}
    assert "klipper-flowloop" in moonraker_venv.freeze("flowloop")


def test_component_is_linked_the_way_flowloop_install_links_it(moonraker_venv):
    components = install.moonraker_components_dir(moonraker_venv.path)
    link = components / "flowloop"
    assert link.is_symlink()
    assert link.resolve() == stack.PROJECT / "moonraker_components" / "flowloop"
    assert not (components / "flowloop.py").exists()  # an older install's module


def test_moonraker_loads_the_component_package(moonraker_only):
    status, body = moonraker_only.moonraker.request("GET", "/server/info")
    assert status == 200
    result = body["result"]
    assert "flowloop" in result["components"]
    assert "flowloop" not in result["failed_components"]
    log = (moonraker_only.data_dir / "moonraker.log").read_text()
    assert "moonraker.components.flowloop" not in log  # no import traceback


def test_install_then_uninstall_in_a_moonraker_that_then_loads_it(moonraker_venv,
                                                                   tmp_path):
    """The installer on a copy of the real Moonraker package: after install that
    Moonraker loads the component package; uninstall restores every byte."""
    site = tmp_path / "site"
    copy_of_moonraker(moonraker_venv, site)

    def snapshot():
        return {str(p.relative_to(site)): (os.readlink(p) if p.is_symlink()
                                           else p.read_bytes() if p.is_file()
                                           else "dir")
                for p in sorted(site.rglob("*")) if "__pycache__" not in p.parts}
    before = snapshot()
    install.apply(install.plan_moonraker(site, stack.PROJECT))
    link = site / "moonraker" / "components" / "flowloop"
    assert os.readlink(link) == str(stack.PROJECT / "moonraker_components" / "flowloop")
    with moonraker_from(site, moonraker_venv, "fl-inst-"):
        pass  # it started and loaded flowloop from the copy: what is checked
    install.apply(install.plan_moonraker(site, stack.PROJECT, uninstall=True))
    assert snapshot() == before
