"""The EMS22 on the atmega2560's hardware SPI, read by the real firmware on
simavr and decoded by klippy in normal mode over a pty: samples arrive at the
configured rate, QUERY_FLOW_SENSOR reports them, G1 E moves give the grip the
model was given, klippy's clock follows the firmware's, and each fault the
chip or its wiring can have gives its documented status and console line,
pauses a print, and clears with the next good frame."""

from __future__ import annotations

import time

import pytest

from devtools import simavr, stack
from tests.fil.conftest import COUNTS_PER_MM, SENSOR

FIL_SECTIONS = """
[flow_sensor filament]
sensor_type: ems22
cs_pin: PG0
# 10 mm windows: one count (9.7 um) is 0.1 % of a window
grip_window: 10
on_fault: pause
"""
# M400 returns when the last step is due; its samples reach the host in
# messages of at most 20 ms of samples (ems22.MAX_BATCH_AGE_S) and 100 ms batches
SETTLE_S = 0.4
CLOCK = {}  # the firmware clock at the module's first test


def _status(printer) -> dict:
    return printer.query(SENSOR)


def test_klippy_connects_in_normal_mode(printer, fil_build):
    CLOCK["clock"] = simavr.FirmwareClock(printer, fil_build.elf("atmega2560"))
    CLOCK["start"] = CLOCK["clock"].read()
    harness = printer.sim.status()
    CLOCK["harness"] = (float(harness["cpu_s"]), float(harness["sim_s"]))
    log = printer.klippy.log_path.read_text()
    assert "Configured MCU 'mcu'" in log
    mcu = printer.query("mcu")
    assert mcu["mcu_constants"]["MCU"] == "atmega2560"
    assert mcu["mcu_constants"]["CLOCK_FREQ"] == 16000000


def test_the_harness_counts_the_firmwares_idle_cycles(printer, fil_build):
    start, end = simavr.idle_loop(fil_build.elf("atmega2560"))
    assert 0 < end - start <= 16
    s0 = printer.sim.status()
    time.sleep(0.5)
    s1 = printer.sim.status()
    idle = int(s1["idle_cycles"]) - int(s0["idle_cycles"])
    cycles = int(s1["cycle"]) - int(s0["cycle"])
    assert 0.5 < idle / cycles < 1.0  # the AVR mostly waits at 250 samples/s


def test_samples_arrive_and_query_flow_sensor_reports_them(printer):
    before = _status(printer)
    time.sleep(1.0)
    after = _status(printer)
    arrived = after["samples"] - before["samples"]
    assert 200 <= arrived <= 300, arrived  # 250 per second by default
    assert after["errors"] == {} and after["fault"] is None
    lines = printer.gcode_console("QUERY_FLOW_SENSOR")
    assert any("250 samples/s" in line and "errors none, fault none" in line
               for line in lines), lines


@pytest.mark.parametrize("grip", [1.0, 0.9])
def test_g1_e_moves_give_the_models_grip(printer, grip):
    printer.sim.control(f"grip {grip}")
    model_before = float(printer.sim.status()["filament_mm"])
    sensor_before = _status(printer)["filament_position"]
    printer.gcode("M83\nG1 E30 F900\nM400")
    time.sleep(SETTLE_S)
    model_mm = float(printer.sim.status()["filament_mm"]) - model_before
    status = _status(printer)
    sensor_mm = status["filament_position"] - sensor_before
    print(f"grip {grip}: flowloop {status['grip']}, sensor {sensor_mm:.4f} mm,"
          f" model {model_mm:.4f} mm")
    assert abs(sensor_mm - model_mm) <= 2.5 / COUNTS_PER_MM
    assert status["grip"] == pytest.approx(grip, rel=0.002)
    assert status["errors"] == {}


def test_the_sensor_follows_a_grip_ramp(printer):
    # grip 1.0 -> 0.9 over the 3 s of G1 E30 F600: the shaft slows step by step
    model0 = float(printer.sim.status()["filament_mm"])
    sensor0 = _status(printer)["filament_position"]
    printer.sim.control("grip 1.0")
    printer.sim.control("grip 0.9 3.0")
    printer.gcode("M83\nG1 E30 F600\nM400")
    time.sleep(SETTLE_S)
    status = _status(printer)
    model_mm = float(printer.sim.status()["filament_mm"]) - model0
    printer.sim.control("grip 1.0")
    assert 28.0 < model_mm < 29.0  # about the ramp's mean, 0.95
    assert abs(status["filament_position"] - sensor0 - model_mm) \
        <= 2.5 / COUNTS_PER_MM
    assert 0.9 < status["grip"] < 0.95  # the last 10 mm, late in the ramp


def test_klippys_clock_follows_the_firmwares(printer):
    clock = CLOCK["clock"]
    wall0, ticks0, cycles0 = CLOCK["start"]
    cpu0, sim0 = CLOCK["harness"]
    wall1, ticks1, cycles1 = clock.read()
    firmware_hz = (ticks1 - ticks0) / (wall1 - wall0)
    cycles_hz = (cycles1 - cycles0) / (wall1 - wall0)
    klippy_hz = printer.query("mcu")["last_stats"]["freq"]
    status = printer.sim.status()
    cpu_per_sim_s = ((float(status["cpu_s"]) - cpu0)
                     / (float(status["sim_s"]) - sim0))
    print(f"over {wall1 - wall0:.1f} s: simulated {cycles_hz:.0f} cycles/s,"
          f" firmware clock {firmware_hz:.0f} Hz, klippy's estimate "
          f"{klippy_hz:.0f} Hz; the harness used {cpu_per_sim_s:.2f} CPU s per"
          f" simulated s; simulation at most {status['max_lag_ms']} ms behind"
          f" the wall clock (at {status['max_lag_at_s']} s), of it"
          f" {status['max_own_lag_ms']} ms running slower than real time")
    assert cycles_hz == pytest.approx(16e6, rel=0.001)
    # the firmware clock is read in 4 ms (65536 tick) steps
    resolution = 65536 / (wall1 - wall0) / 16e6
    assert klippy_hz == pytest.approx(firmware_hz, rel=0.001 + resolution)
    # The harness keeps real time with room to catch up: it never fell
    # behind by running slower than the firmware's 16 MHz. Time it was not
    # running at all (descheduled, the machine stalled) also shows in
    # max_lag_ms; that is the machine's, and CI once saw 65 ms of it.
    assert float(status["max_own_lag_ms"]) < 50
    assert cpu_per_sim_s < 0.8
    # every Timer1 overflow since reset reached timer_high (the harness
    # watches its steps): without flowloop's simavr timer fix one in a few
    # seconds did not, and the firmware's clock jumped 4.1 ms back
    assert status["lost_overflows"] == "0"


# harness fault -> the fault flowloop reports
FAULTS = {"parity": "parity", "not_ready": "not_ready",
          "cordic": "cordic_overflow", "linearity": "linearity",
          "magnet": "magnet", "miso_high": "missing", "miso_low": "missing",
          "absent": "missing"}
# fault_samples (100) at 250 samples/s, plus a batch and a margin
FAULT_WAIT_S = 3.0


def _wait_for_fault(printer, kind):
    """The sensor's status once its fault is `kind`, or None at the timeout."""
    def faulted():
        status = _status(printer)
        return status if status["fault"] == kind else None
    return stack.wait_until(faulted, FAULT_WAIT_S, 0.1)


@pytest.mark.parametrize("fault", FAULTS)
def test_a_fault_is_reported_and_clears_with_the_next_good_frame(printer, fault):
    kind = FAULTS[fault]
    before = _status(printer)
    printer.console()
    printer.sim.control(f"fault {fault}")
    try:
        faulted = _wait_for_fault(printer, kind)
        assert faulted, _status(printer)
        expected = (f"// flow_sensor filament: fault '{kind}' (100 consecutive"
                    " bad samples, or stuck windows); grip is not judged until"
                    " it clears")
        lines = printer.console_until(lambda line: line == expected)
    finally:
        printer.sim.control("fault none")
    assert faulted["grip"] is None
    assert faulted["errors"].get(kind, 0) >= 100
    assert expected in lines
    # idle: warned, not paused
    assert printer.query("pause_resume")["is_paused"] is False
    assert _wait_for_fault(printer, None), _status(printer)
    cleared = settle_status(printer)
    assert cleared["samples"] > faulted["samples"]
    # an absolute encoder loses nothing while it was not read
    assert cleared["filament_position"] == before["filament_position"]


def test_a_short_stall_of_the_sensor_task_is_counted_not_a_fault(printer):
    # The next SPI byte completes 50 ms late: the task sits in its transfer
    # while the timer keeps counting polls (12 of them at 250 a second).
    before = _status(printer)
    printer.sim.control("stall 50")
    time.sleep(1.0)
    after = _status(printer)
    added = {kind: after["errors"].get(kind, 0) - before["errors"].get(kind, 0)
             for kind in after["errors"]}
    print("errors from a 50 ms stall:", added)
    assert added["spi_time"] == 1  # the read that was held
    assert 10 <= added["overflow"] <= 13  # the polls missed meanwhile
    assert after["fault"] is None
    assert after["samples"] - before["samples"] > 200
    assert printer.api.call("info")["state"] == "ready"


def test_a_fault_while_printing_pauses(printer):
    printer.console()
    printer.gcode("M83\nG1 E15 F600")  # 1.5 s of extrusion, not waited for
    time.sleep(0.3)
    printer.sim.control("fault magnet")
    try:
        assert _wait_for_fault(printer, "magnet"), _status(printer)
        assert stack.wait_until(
            lambda: printer.query("pause_resume")["is_paused"], 2.0)
        lines = printer.console_until(_pausing_line)
    finally:
        printer.sim.control("fault none")
    assert any(_pausing_line(line) for line in lines), lines
    printer.gcode("M400")
    assert _wait_for_fault(printer, None)
    printer.gcode("RESUME")
    assert printer.query("pause_resume")["is_paused"] is False


def _pausing_line(line: str) -> bool:
    return (line.startswith("// flow_sensor filament: fault 'magnet'")
            and line.endswith(": pausing"))


def settle_status(printer) -> dict:
    time.sleep(SETTLE_S)
    return _status(printer)
