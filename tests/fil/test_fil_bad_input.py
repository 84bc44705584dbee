"""Bad input gives one clear line and a bounded wait: no simavr, a firmware
without the EMS22 option, a simulator that cannot start, a pty that closes
under klippy."""

from __future__ import annotations

import shutil
import time

import pytest

from devtools import simavr, stack
from tests.fil.conftest import fil_printer


def test_without_simavr_the_tier_says_how_to_get_it(monkeypatch, tmp_path):
    monkeypatch.setenv("SIMAVR_PATH", str(tmp_path))
    reason = simavr.missing_simavr_reason()
    assert reason.startswith(f"no simavr source at {tmp_path}: the fil tier is"
                             " SKIPPED")
    assert "git clone https://github.com/buserror/simavr" in reason


def test_a_firmware_without_the_ems22_option_is_named(fil_build, tmp_path):
    tree = tmp_path / "klipper"
    (tree / "flowloop-dict").mkdir(parents=True)
    shutil.copy(fil_build.elf("atmega2560"), tree / "flowloop-dict")
    config = (fil_build.dict_dir / "atmega2560.config").read_text()
    (tree / "flowloop-dict" / "atmega2560.config").write_text(
        config.replace("CONFIG_WANT_SENSOR_EMS22=y",
                       "# CONFIG_WANT_SENSOR_EMS22 is not set"))
    build = stack.KlipperBuild(tree)
    with pytest.raises(simavr.HarnessError, match="built without flowloop's "
                       "EMS22 option"):
        simavr.start_printer(build, stack.klippy_venv(), "", tmp_path,
                             sensor={"cs": "PG0"}, mm_per_step=1,
                             counts_per_mm=1)


def test_a_simulator_that_cannot_start_says_why(fil_build):
    workdir = stack.short_tempdir("fl-fil-")
    not_elf = workdir / "klipper.elf"
    not_elf.write_text("not an ELF file")
    sim = simavr.Simulator(not_elf, workdir, sensor={"cs": "PG0"},
                           mm_per_step=1, counts_per_mm=1)
    start = time.monotonic()
    try:
        with pytest.raises(simavr.HarnessError,
                           match="the simulator did not start: fil_harness: "
                           "cannot read firmware"):
            sim.wait_ready()
    finally:
        sim.stop()
        shutil.rmtree(workdir, ignore_errors=True)
    assert time.monotonic() - start < 10


def test_klippy_shuts_down_when_the_pty_closes(fil_build):
    with fil_printer(fil_build, "") as printer:
        printer.sim.stop()  # the pty closes with the simulator
        state = stack.wait_until(
            lambda: printer.api.call("info")["state"] != "ready", 15, 0.2)
        info = printer.api.call("info")
    assert state, "klippy still ready 15 s after its MCU's pty closed"
    print(info["state_message"])
    assert info["state"] == "shutdown"
    assert "Lost communication with MCU 'mcu'" in info["state_message"]


def test_a_sensor_task_held_past_the_watchdog_shuts_the_mcu_down(fil_build):
    sections = "[flow_sensor filament]\nsensor_type: ems22\ncs_pin: PG0\n"
    with fil_printer(fil_build, sections) as printer:
        printer.sim.control("stall 600")  # the next SPI byte, 600 ms late
        state = stack.wait_until(
            lambda: printer.api.call("info")["state"] != "ready", 10, 0.2)
        info = printer.api.call("info")
    assert state, "klippy still ready 10 s after a 600 ms stall"
    assert info["state"] == "shutdown"
    assert "MCU 'mcu' shutdown: Watchdog timer!" in info["state_message"]
