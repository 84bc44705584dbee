"""flow_sensor klippy runs judged on their logs: old firmware is told to
rebuild, on_fault: pause pauses, and a calibration whose speeds disagree
changes nothing. (Bad options name themselves through the EXPECT_LOG lines
of the flow_sensor_fail_*.test files.)"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from devtools.klippy_test import run_file, write_test
from flowloop.sensor import ems22
from flowloop.sensor.grip import FLOW_PIECE_S

HERE = Path(__file__).resolve().parent


class Harnessed:
    """The Klipper build, klippy started through flow_sensor_harness.py (a
    window subscriber on every sensor, FLOW_SENSOR_FEED on ems22 ones)."""

    def __init__(self, build):
        self.tree, self.dict_dir = build.tree, build.dict_dir
        self.klippy = HERE / "flow_sensor_harness.py"


def test_real_format_payloads_reach_the_status(klipper_build, klippy_venv,
                                               short_tmp):
    run_file(HERE / "flow_sensor_feed.batch", Harnessed(klipper_build),
             klippy_venv, short_tmp)


def test_the_linux_mcu_hands_payloads_to_the_sensor(klipper_build, klippy_venv,
                                                    short_tmp):
    # flow_sensor_linux.cfg reads in SPI mode 1
    read = ems22.spi_read_model(ems22.make_frame(100), 1)
    payload = ems22.pack_messages(0, [(0, read)],
                                  ems22.bit_offset_for_mode(1))[0].hex()
    _, test = write_test(
        short_tmp, "linux", f"FLOW_SENSOR_FEED SENSOR=host SEQUENCE=0 DATA={payload}\n"
        "QUERY_FLOW_SENSOR SENSOR=host\n", config=HERE / "flow_sensor_linux.cfg",
        dictionary="linuxprocess.dict")
    log = run_file(test, Harnessed(klipper_build), klippy_venv, short_tmp)
    # one good sample arrived: the position exists (none before any)
    assert "flow_sensor host: grip not judged" in log
    assert "filament position 0.000 mm" in log


def test_a_real_sensor_offers_no_testing_command(klipper_build, klippy_venv,
                                                 short_tmp):
    _, test = write_test(
        short_tmp, "feed", "FLOW_SENSOR_FEED SENSOR=filament SEQUENCE=0 "
        "DATA=000019201ba0\n", config=HERE / "flow_sensor.cfg")
    log = run_file(test, klipper_build, klippy_venv, short_tmp,
                   allow_unknown=True)
    assert 'Unknown command:"FLOW_SENSOR_FEED"' in log


def test_firmware_without_the_command_is_told_to_rebuild(klipper_build, klippy_venv,
                                                         short_tmp):
    data = json.loads(klipper_build.dictionary("atmega2560").read_text())
    for fmt in (ems22.CONFIG_CMD, ems22.QUERY_CMD):
        del data["commands"][fmt]
    old = short_tmp / "old-firmware.dict"
    old.write_text(json.dumps(data))
    _, test = write_test(short_tmp, "old", config=HERE / "flow_sensor.cfg",
                         dictionary=old, should_fail=True)
    log = run_file(test, klipper_build, klippy_venv, short_tmp)
    assert "firmware has no EMS22 sensor support" in log
    # the one command that puts it back (Klipper's own make on a patched copy)
    assert "flowloop firmware flash FLASH_DEVICE=" in log


def test_on_fault_pause_pauses_after_the_fault(klipper_build, klippy_venv,
                                               short_tmp):
    log = run_file(HERE / "flow_sensor_sim.test", klipper_build, klippy_venv,
                   short_tmp)
    fault = log.index("flow_sensor sim: fault 'missing'")
    assert log.index("action:paused", fault) > fault
    assert "Transition to shutdown" not in log


# 8 reads of all ones, the most whole-read records a message holds
MISSING_FRAMES = ("1800" + "000102ffffff" * 8)


def test_on_fault_pause_leaves_an_idle_printer_alone(klipper_build, klippy_venv,
                                                     short_tmp):
    # A sensor unplugged at boot: a fault, said on the console, no PAUSE
    _, test = write_test(
        short_tmp, "idle",
        f"FLOW_SENSOR_FEED SENSOR=filament SEQUENCE=0 DATA={MISSING_FRAMES}\n"
        f"FLOW_SENSOR_FEED SENSOR=filament SEQUENCE=1 DATA={MISSING_FRAMES}\n"
        f"FLOW_SENSOR_FEED SENSOR=filament SEQUENCE=2 DATA={MISSING_FRAMES}\n"
        "G4 P100\nQUERY_FLOW_SENSOR\n",
        cfg=f"[include {HERE / 'flow_sensor.cfg'}]\n"
            "[flow_sensor filament]\non_fault: pause\n")
    log = run_file(test, Harnessed(klipper_build), klippy_venv, short_tmp)
    assert "fault missing" in log          # the query saw the fault
    # logged, then said on the console by the callback that would pause
    assert log.count("flow_sensor filament: fault 'missing'") == 2
    assert "pausing" not in log and "action:paused" not in log


def test_calibration_with_slipping_speeds_changes_nothing(klipper_build,
                                                          klippy_venv, short_tmp):
    # 8 mm/s of 1.75 mm filament is 19 mm^3/s: the twin melts only 10 at 200 C
    _, test = write_test(
        short_tmp, "slip", "SET_HEATER_TEMPERATURE HEATER=extruder TARGET=200\n"
        "CALIBRATE_FLOW_SENSOR SENSOR=sim LENGTH=20 SPEEDS=1,8\n",
        config=HERE / "flow_sensor_sim.cfg", should_fail=True)
    log = run_file(test, klipper_build, klippy_venv, short_tmp)
    assert "the speeds disagree by more than 2.00%; calibration unchanged" in log
    assert "save_config: set [flow_sensor" not in log


def test_a_reversed_sensor_is_named_in_calibration(klipper_build, klippy_venv,
                                                  short_tmp):
    # the twin counts forward; configured reverse, it reads backwards
    _, test = write_test(
        short_tmp, "reversed", "SET_HEATER_TEMPERATURE HEATER=extruder TARGET=210\n"
        "CALIBRATE_FLOW_SENSOR SENSOR=cal LENGTH=5 SPEEDS=1,2\n",
        cfg=f"[include {HERE / 'flow_sensor_cal.cfg'}]\n"
            "[flow_sensor_simulation cal]\ndirection: reverse\n",
        should_fail=True)
    log = run_file(test, klipper_build, klippy_venv, short_tmp)
    assert ("the sensor counts backwards (ratio -1.0" in log
            and "set direction: forward in [flow_sensor_simulation cal];"
            " calibration"
            " unchanged" in log)
    assert "save_config: set [flow_sensor" not in log


def test_only_a_simulation_section_imports_the_twin(klipper_build, klippy_venv,
                                                    short_tmp):
    def twin_modules(name, config):
        (short_tmp / name).mkdir()   # a log of its own
        _, test = write_test(short_tmp / name, name, "QUERY_FLOW_SENSOR\n",
                             config=HERE / config)
        log = run_file(test, Harnessed(klipper_build), klippy_venv,
                       short_tmp / name)
        return log, log.split("TWIN_MODULES ", 1)[1].split("\n", 1)[0].split()

    # A printer with a real sensor never imports the simulated sensor's code
    assert twin_modules("real", "flow_sensor.cfg")[1] == ["none"]
    # [flow_sensor_simulation sim] does, and is the flow sensor "sim"
    log, twins = twin_modules("sim", "flow_sensor_sim.cfg")
    assert "flowloop.sensor.twin" in twins
    assert any(name.endswith("flow_sensor_simulation.twin") for name in twins)
    assert "flow_sensor sim: grip not judged" in log


def test_a_simulation_and_a_real_sensor_of_one_name_are_refused(
        klipper_build, klippy_venv, short_tmp):
    _, test = write_test(
        short_tmp, "clash", cfg=f"[include {HERE / 'flow_sensor_sim.cfg'}]\n"
        "[flow_sensor sim]\nsensor_type: ems22\ncs_pin: PG0\n", should_fail=True)
    log = run_file(test, klipper_build, klippy_venv, short_tmp)
    assert ("Section [flow_sensor_simulation sim]: [flow_sensor sim] exists too;"
            " a simulated sensor and a real one need names of their own") in log


def test_pressure_advance_at_corners_is_not_a_retraction(klipper_build,
                                                         klippy_venv, short_tmp):
    # A zigzag of 0.4 x 0.2 mm lines at 50 mm/s (4 mm^3/s): each corner
    # slows to the square corner velocity and pressure advance pulls the
    # extruder stepper back ~0.07 mm; the planned E never goes back.
    e_per_line = 20 * 0.4 * 0.2 / 2.405
    lines = "".join(f"G1 X{60 if i % 2 else 40} Y{40 + i} E{e_per_line:.4f}\n"
                    for i in range(1, 41))
    _, test = write_test(
        short_tmp, "pa", "SET_HEATER_TEMPERATURE HEATER=extruder TARGET=200\n"
        "G28\nG1 X40 Y40 Z0.2 F6000\nM83\nG1 F3000\n" + lines
        + "M400\nQUERY_FLOW_SENSOR\n",
        cfg=f"[include {HERE / 'flow_sensor_sim.cfg'}]\n"
            "[extruder]\npressure_advance: 0.05\n")
    log = run_file(test, Harnessed(klipper_build), klippy_venv, short_tmp)
    reasons = [json.loads(line.split("GRIP_WINDOW ", 1)[1])["reason"]
               for line in log.splitlines() if "GRIP_WINDOW " in line]
    # 40 lines of 0.665 mm of filament: about 21 windows of 1.25 mm
    assert reasons.count("judged") >= 18
    assert "retraction" not in reasons


def _feed(messages):
    return "".join(f"FLOW_SENSOR_FEED SENSOR=filament SEQUENCE={seq}"
                   f" DATA={payload.hex()}\n" for seq, payload in messages)


def _reads(positions):
    return [(3, ems22.spi_read_model(ems22.make_frame(p), 2)) for p in positions]


def test_time_lost_by_the_mcu_restarts_the_query(klipper_build, klippy_venv,
                                                 short_tmp):
    # The MCU's task fell so far behind that its pending count saturated:
    # the 9 reads after its 254 overflow records are timed wrongly, never used
    records = (_reads([100]) + [ems22.error_record(ems22.ERR_OVERFLOW)]
               * (ems22.MAX_PENDING - 1) + _reads(range(101, 110)))
    lost = list(enumerate(ems22.pack_messages(0, records)))
    # the host restarts the query at once: the MCU counts from 0 again
    fresh = list(enumerate(ems22.pack_messages(0, _reads([140]))))
    _, test = write_test(
        short_tmp, "time_lost", _feed(lost)
        + "ASSERT_FLOW SAMPLES=1 POSITION=0 ERROR_KIND=time_lost ERRORS=9"
          " FAULT=overflow\n"
        + _feed(fresh)
        + "ASSERT_FLOW SAMPLES=2 POSITION=0.3890 ERROR_KIND=lost_messages"
          " ERRORS=0 FAULT=none\n"
        # the first read of the new query follows a gap of unknown length
        + "ASSERT_FLOW SAMPLES=2 POSITION=0.3890 ERROR_KIND=discontinuity"
          " ERRORS=1 FAULT=none\n", config=HERE / "flow_sensor.cfg")
    log = run_file(test, Harnessed(klipper_build), klippy_venv, short_tmp)
    assert "fell 255 reads behind and lost count of them" in log


def test_subscribers_get_every_window_with_flow_and_temperature(
        klipper_build, klippy_venv, short_tmp):
    # Phases, each ended by a QUERY_FLOW_SENSOR answer in the log: 5 mm^3/s,
    # 20 mm^3/s (the twin melts 10 at 200 C), a missing sensor, back again
    _, test = write_test(
        short_tmp, "subscribe",
        "SET_HEATER_TEMPERATURE HEATER=extruder TARGET=200\nM83\n"
        "G1 E20 F125\nM400\nQUERY_FLOW_SENSOR\n"
        "G1 E40 F500\nM400\nQUERY_FLOW_SENSOR\n"
        "SET_FLOW_SENSOR_SIMULATION FAULT=missing\n"
        "G1 E10 F300\nM400\nG1 E10 F300\nM400\nQUERY_FLOW_SENSOR\n"
        "SET_FLOW_SENSOR_SIMULATION FAULT=none\n"
        "G1 E10 F125\nM400\nQUERY_FLOW_SENSOR\n",
        config=HERE / "flow_sensor_sim.cfg")
    log = run_file(test, Harnessed(klipper_build), klippy_venv, short_tmp)
    phases = [[]]
    for line in log.splitlines():
        if "GRIP_WINDOW " in line:
            phases[-1].append(json.loads(line.split("GRIP_WINDOW ", 1)[1]))
        elif line.startswith("flow_sensor sim: grip"):
            phases.append([])
    slow, fast, faulted, back = phases[:4]
    assert all(w["sensor"] == "sim" and w["reactor_thread"]
               for w in slow + fast + faulted + back)
    # 20 mm in windows of 1.25 mm; the first one holds the acceleration
    assert len(slow) == 15 and all(w["reason"] == "judged" for w in slow)
    for w in slow[1:]:
        assert w["grip"] == pytest.approx(1.0, abs=0.03)
        assert w["flow_mm3_s"] == pytest.approx(5.0, rel=0.03)
        assert len(w["commanded_flows"]) == round(
            (w["end_time"] - w["start_time"]) / FLOW_PIECE_S)
        assert w["commanded_flows"] == pytest.approx(
            [5.0] * len(w["commanded_flows"]), rel=0.01)
        assert w["temp_c"] == 200.0
        assert w["end_time"] > w["start_time"]
    # settled (the twin's melt lag is 50 ms): half slips, 10 mm^3/s measured;
    # a slip closes windows at 0.5 mm, whose ends the sensor's noise moves
    # by about 2 % of it each
    assert len(fast) >= 60
    for w in fast[3:]:
        assert w["reason"] == "judged"
        assert w["grip"] == pytest.approx(0.5, abs=0.05)
        assert w["commanded_mm"] == pytest.approx(0.5, abs=0.02)
        # what was planned over it, from the extruder's trapq: 20 mm^3/s
        assert w["commanded_flows"] == pytest.approx(
            [20.0] * len(w["commanded_flows"]), rel=0.01)
        assert w["flow_mm3_s"] == pytest.approx(10.0, rel=0.1)
    assert sum(w["flow_mm3_s"] for w in fast[3:]) / len(fast[3:]) == \
        pytest.approx(10.0, rel=0.02)
    # while the sensor is faulted nothing is judged; then it is again
    assert [w for w in faulted if w["grip"] is not None] == []
    assert len(back) >= 6 and all(w["grip"] == pytest.approx(1.0, abs=0.03)
                                  for w in back[1:])
