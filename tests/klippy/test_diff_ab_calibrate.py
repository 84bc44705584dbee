"""DIFF_AB_CALIBRATE's refusals say why, and the pylon template renders under
Klipper's own Jinja2 (2.11.3) exactly as under Moonraker's 3.x."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from devtools.klippy_test import run_file
from flowloop.calibrate import pylons

HERE = Path(__file__).resolve().parent


@pytest.mark.parametrize("name,message", [
    ("delta", "kinematics 'delta' is not supported: differential A/B calibration "
              "needs corexy or cartesian"),
    ("fail_bad_reading", "A1: 'abc' is not a number"),
    ("fail_missing_b", "DIFF_AB_CALIBRATE: B2=<readings> is missing"),
    ("fail_scale", "A: scale 1.02857 is +2.86 % from 1, more than 2 %"),
    ("fail_order", "D2 (10 mm) must be greater than D1 (150 mm)"),
    ("fail_shrunk", "B: readings must grow with the nominal distance"),
    ("macro_skew", "Skew correction is configured: the pylons must be printed "
                   "without it."),
])
def test_refusals_name_their_reason_and_change_nothing(
        klipper_build, klippy_venv, short_tmp, name, message):
    log = run_file(HERE / f"diff_ab_calibrate_{name}.test", klipper_build,
                   klippy_venv, short_tmp)
    assert message in log
    assert "save_config: set" not in log


def test_pylon_template_renders_the_same_under_klippers_jinja2(klippy_venv, tmp_path):
    code = ("import jinja2, sys; from flowloop.calibrate import pylons; "
            "sys.stdout.write(jinja2.__version__ + '\\n' + "
            "pylons.render(pylons.PylonOptions(kinematics='cartesian')))")
    proc = subprocess.run([str(klippy_venv.python), "-c", code], capture_output=True,
                          text=True, check=True)
    version, _, gcode = proc.stdout.partition("\n")
    assert version.startswith("2.")
    assert gcode == pylons.render(pylons.PylonOptions(kinematics="cartesian"))


def test_values_from_an_included_file_are_printed_to_paste(
        klipper_build, klippy_venv, short_tmp):
    log = run_file(HERE / "diff_ab_calibrate_cartesian.test", klipper_build,
                   klippy_venv, short_tmp)
    included = str((HERE / "diff_ab_calibrate_cartesian_y.cfg").resolve())
    assert (f"{included} sets these, which SAVE_CONFIG cannot change; paste "
            "them there:") in log
    assert "  [stepper_y1]\n  rotation_distance: 32.250600" in log
    assert "save_config: set [stepper_y" not in log
    assert ("Run SAVE_CONFIG to store [stepper_x] rotation_distance (Klipper restarts)."
            in log)
    assert "X and Y are no longer homed: run G28 before moving." in log
