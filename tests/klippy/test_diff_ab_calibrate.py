"""The pylon template renders under Klipper's own Jinja2 (2.11.3) exactly as
under Moonraker's 3.x, and values an included file sets are printed to paste.
(DIFF_AB_CALIBRATE's refusals say why and change nothing: the EXPECT_LOG and
EXPECT_NO_LOG lines of the diff_ab_calibrate_*.test files that SHOULD_FAIL.)"""

from __future__ import annotations

import subprocess
from pathlib import Path

from devtools.klippy_test import run_file
from flowloop.calibrate import pylons

HERE = Path(__file__).resolve().parent


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
