"""A klippy whose Python lacks a requirement of flowloop's core (numpy) stops
with one config error naming the package and the pip that installs it into
that Python, as Klipper does for numpy, not with an internal error at the
first import of numpy (no_numpy_harness.py hides it)."""

from __future__ import annotations

from pathlib import Path

import pytest

from devtools.klippy_test import run_file, write_test
from flowloop.host import requirements

HERE = Path(__file__).resolve().parent


class WithoutNumpy:
    """The Klipper build, klippy started through no_numpy_harness.py."""

    def __init__(self, build):
        self.tree, self.dict_dir = build.tree, build.dict_dir
        self.klippy = HERE / "no_numpy_harness.py"


@pytest.mark.parametrize("config", ["flow_sensor_sim.cfg", "autotemp.cfg",
                                    "diff_ab_calibrate_corexy.cfg",
                                    "endstop_calibrate.cfg"])
def test_a_missing_numpy_is_one_config_error_naming_what_to_install(
        klipper_build, klippy_venv, short_tmp, config):
    _, test = write_test(short_tmp, "nonumpy", "G4 P1\n", config=HERE / config,
                         should_fail=True)
    log = run_file(test, WithoutNumpy(klipper_build), klippy_venv, short_tmp)
    line = requirements.missing_message("numpy", str(klippy_venv.python))
    assert line in log, log[-3000:]
    assert "Internal error" not in log
