"""flowloop doctor against the real stack: a healthy demo printer passes every
check; broken ones (a missing link, firmware without the sensor command, an
invalid section, no active profile) are each named with their fix."""

from __future__ import annotations

import json
import shutil
import socket
from pathlib import Path

import pytest

from devtools import stack
from flowloop.cli import main
from tests.samples import make


def doctor(ps, moonraker_venv, capsys) -> tuple:
    """(exit status, {check name: line}) of `flowloop doctor` on this machine."""
    code = main(["doctor", "--moonraker", ps.moonraker.url,
                 "--moonraker-dir", str(moonraker_venv.path)])
    lines = capsys.readouterr().out.splitlines()
    return code, {line.split(":")[0][5:]: line for line in lines}


def klippy_connected(ps) -> bool:
    def connected():
        status, body = ps.moonraker.request("GET", "/server/info")
        return status == 200 and body["result"]["klippy_state"] in (
            "ready", "error", "shutdown")
    return stack.wait_until(connected, 30)


@pytest.fixture(scope="module")
def demo(klipper_build, klippy_venv, moonraker_venv):
    with stack.printer_stack() as ps:
        yield ps


def test_the_demo_printer_without_an_active_profile_is_told_how_to_activate(
        demo, moonraker_venv, capsys):
    active = demo.query("flowloop")["profiles"]
    assert active == {}  # nothing activated yet on this stack
    code, lines = doctor(demo, moonraker_venv, capsys)
    assert code == 1
    assert lines["profiles"].startswith("FAIL profiles: no active profile for"
                                        " extruder")
    assert "fix: store a profile and activate it" in lines["profiles"]
    for name in ("klipper", "links", "moonraker", "config", "firmware"):
        assert lines[name].startswith("ok"), lines[name]


def test_the_demo_printer_passes_every_check(demo, moonraker_venv, capsys):
    status, body = demo.moonraker.request("POST", "/server/flowloop/profile",
                                          {"profile": make(name="doctor-pla")})
    assert status == 200, body
    status, body = demo.moonraker.request("POST", "/server/flowloop/profile/activate",
                                          {"name": "doctor-pla"})
    assert status == 200, body
    assert stack.wait_until(lambda: demo.query("flowloop")["profiles"], 20)
    # The simulated sensor samples as klippy generates steps (batch mode).
    demo.gcode("G28\nM83\nSET_HEATER_TEMPERATURE HEATER=extruder TARGET=200\n"
               "G1 E2 F300\nM400")
    code, lines = doctor(demo, moonraker_venv, capsys)
    failing = [line for line in lines.values() if line.startswith("FAIL")]
    assert failing == [] and code == 0
    assert lines["klipper"].startswith("ok   klipper: Klipper v")
    assert lines["links"].startswith("ok   links: installed and pointing at")
    assert lines["firmware"] == "ok   firmware: 'mcu' firmware carries query_ems22"
    assert lines["sensor sim"].startswith("ok   sensor sim: ")
    assert lines["profiles"] == "ok   profiles: extruder 'doctor-pla'"
    # No processor is reported by the component yet: said, not passed.
    assert lines["gcode processor"].startswith(("skip", "ok"))


def copy_tree_without(build: stack.KlipperBuild, module: str, where: Path):
    """The patched Klipper's runnable part (klippy/, src/) without one of
    flowloop's links; the MCU dictionaries stay the build's."""
    for part in ("klippy", "src"):
        shutil.copytree(build.tree / part, where / part, symlinks=True,
                        ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(build.tree / "Makefile", where / "Makefile")
    (where / "klippy" / "extras" / module).unlink()
    broken = stack.KlipperBuild(where)
    broken.dict_dir = build.dict_dir
    return broken


def test_a_missing_link_is_named_with_flowloop_install(klipper_build, klippy_venv,
                                                       moonraker_venv, capsys):
    where = stack.short_tempdir("fl-doc-tree-")
    try:
        broken = copy_tree_without(klipper_build, "flow_sensor_simulation",
                                   where)
        with stack.printer_stack(build=broken, klippy_ready=False) as ps:
            assert klippy_connected(ps)
            code, lines = doctor(ps, moonraker_venv, capsys)
    finally:
        shutil.rmtree(where, ignore_errors=True)
    assert code == 1
    assert lines["links"].startswith("FAIL links: flowloop is not installed from"
                                     " this checkout: install would link")
    assert "klippy/extras/flow_sensor_simulation ->" in lines["links"]
    assert "fix: run flowloop install" in lines["links"]
    # klippy cannot load [flow_sensor_simulation sim] without its module:
    # said in its words
    assert lines["config"].startswith(
        "FAIL config: klippy stopped (error): Section 'flow_sensor_simulation"
        " sim' is not a valid config section; fix:")


def test_firmware_without_the_sensor_command_gives_the_menuconfig_step(
        klipper_build, klippy_venv, moonraker_venv, capsys):
    where = stack.short_tempdir("fl-doc-dict-")
    try:
        data = json.loads(klipper_build.dictionary("atmega2560").read_text())
        data["commands"] = {cmd: tag for cmd, tag in data["commands"].items()
                            if "ems22" not in cmd}
        (where / "atmega2560.dict").write_text(json.dumps(data))
        unflashed = stack.KlipperBuild(klipper_build.tree)
        unflashed.dict_dir = where  # the MCU as built before flowloop install
        with stack.printer_stack(build=unflashed) as ps:
            code, lines = doctor(ps, moonraker_venv, capsys)
    finally:
        shutil.rmtree(where, ignore_errors=True)
    assert code == 1
    line = lines["firmware"]
    assert line.startswith("FAIL firmware: 'mcu' firmware lacks flowloop's"
                           " query_ems22 command; fix: flowloop firmware menuconfig")
    assert "CONFIG_WANT_SENSOR_EMS22" in line
    # the one command that puts it back: Klipper's own make flash on a copy
    assert "flowloop firmware flash FLASH_DEVICE=" in line
    assert lines["links"].startswith("ok")


def test_an_invalid_section_is_quoted_with_klippys_message(
        klipper_build, klippy_venv, moonraker_venv, capsys, short_tmp):
    cfg = short_tmp / "bad.cfg"
    cfg.write_text(f"[include {stack.PROJECT}/config/printer.cfg]\n\n"
                   "[flow_sensor_simulation sim]\nsample_period: 5\n")
    with stack.printer_stack(printer_cfg=cfg, klippy_ready=False) as ps:
        assert klippy_connected(ps)
        code, lines = doctor(ps, moonraker_venv, capsys)
    assert code == 1
    line = lines["config"]
    assert line.startswith("FAIL config: klippy stopped (error):")
    assert "'sample_period' in section 'flow_sensor_simulation sim'" in line
    assert "fix: correct printer.cfg" in line


def moonraker_api_key(ps) -> str:
    """The API key, asked on Moonraker's unix socket (trusted, as KlipperScreen
    asks it)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(10)
        sock.connect(str(ps.data_dir / "comms" / "moonraker.sock"))
        sock.sendall(json.dumps({"jsonrpc": "2.0", "method": "access.get_api_key",
                                 "id": 1}).encode() + b"\x03")
        data = b""
        while not data.endswith(b"\x03"):
            data += sock.recv(65536)
    for raw in data.split(b"\x03"):
        if raw and json.loads(raw).get("id") == 1:
            return json.loads(raw)["result"]
    raise AssertionError(data)


def test_from_another_machine_with_an_api_key(klipper_build, klippy_venv,
                                              moonraker_venv, capsys, monkeypatch):
    # Not a trusted client: Moonraker asks for the key
    with stack.printer_stack(trusted="10.255.255.0/24", klippy_ready=False) as ps:
        code, lines = doctor(ps, moonraker_venv, capsys)
        assert code == 1
        assert lines["moonraker"].startswith(
            f"FAIL moonraker: Moonraker at {ps.moonraker.url}: HTTP 401")
        assert "is --api-key (or $MOONRAKER_API_KEY) right?" in lines["moonraker"]
        key = moonraker_api_key(ps)
        monkeypatch.setattr("flowloop.cli.doctor.LOOPBACK", ())  # as if remote
        assert stack.wait_until(lambda: ps.moonraker.request(
            "GET", "/server/info", headers={"X-Api-Key": key})[1]["result"][
                "klippy_state"] == "ready", 30)
        code = main(["doctor", "--moonraker", ps.moonraker.url, "--api-key", key])
        lines = {line.split(":")[0][5:]: line
                 for line in capsys.readouterr().out.splitlines()}
    assert lines["klipper"].startswith("ok   klipper: Klipper v0.13.0-")
    assert lines["links"].startswith("skip links: not checked from another machine")
    assert "the hosts run flowloop" in lines["links"]
    for name in ("moonraker", "config", "firmware"):
        assert lines[name].startswith("ok"), lines[name]
    assert lines["profiles"].startswith("FAIL profiles")
    assert code == 1
