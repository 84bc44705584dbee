"""The klippy tier proves itself on Klipper's own regression files."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys

import pytest

from devtools import stack
from devtools.klippy_test import KlippyTestFailure, parse, run_file, write_test


def test_klippers_own_commands_test_runs_in_place(klipper_build, klippy_venv,
                                                  short_tmp):
    # commands.test deliberately sends M206, unknown to its config: Klipper's
    # own harness judges it on exit code alone, and so do we here.
    log = run_file(klipper_build.tree / "test" / "klippy" / "commands.test",
                   klipper_build, klippy_venv, short_tmp, allow_unknown=True)
    assert "Exiting (print time" in log


def test_import_test_passes_in_the_patched_tree(klipper_build, klippy_venv):
    proc = subprocess.run([str(klippy_venv.python), str(klipper_build.klippy),
                           "--import-test"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_an_unknown_command_fails_the_run(klipper_build, klippy_venv, short_tmp):
    _, test = write_test(short_tmp, "unknown", "NO_SUCH_COMMAND_X\n",
                         config=klipper_build.tree / "config" / "example-cartesian.cfg")
    with pytest.raises(KlippyTestFailure, match="Unknown command"):
        run_file(test, klipper_build, klippy_venv, short_tmp)


def test_several_config_lines_make_several_runs(tmp_path):
    test = tmp_path / "multi.test"
    test.write_text("DICTIONARY a.dict\nCONFIG one.cfg\nG28\nCONFIG two.cfg\n"
                    "SHOULD_FAIL\n")
    runs = parse(test, tmp_path)
    assert [r.config.name for r in runs] == ["one.cfg", "two.cfg"]
    assert runs[1].gcode == ["G28"]


def test_installing_flowloop_moved_no_pinned_klippy_package(klippy_venv):
    assert klippy_venv.moved_by_flowloop() == {}
    assert "klipper-flowloop" in klippy_venv.freeze("flowloop")


def test_expect_log_lines_are_read_from_comments(tmp_path):
    _, test = write_test(tmp_path, "why", "# EXPECT_LOG: must be above 0\n"
                         "# EXPECT_NO_LOG: save_config: set\nG28\n",
                         config=tmp_path / "a.cfg", dictionary="a.dict",
                         should_fail=True)
    (run,) = parse(test, tmp_path)
    assert run.expect_log == ["must be above 0"]
    assert run.expect_no_log == ["save_config: set"]
    assert run.gcode == ["G28"]


def test_a_failure_for_another_reason_fails_the_test(klipper_build, klippy_venv,
                                                     short_tmp):
    _, test = write_test(short_tmp, "wrong_reason",
                         "# EXPECT_LOG: a reason that never appears\n"
                         "G28\nG1 X9999\n",  # fails, but for another reason
                         config=klipper_build.tree / "config" / "example-cartesian.cfg",
                         should_fail=True)
    with pytest.raises(KlippyTestFailure, match="log lacks"):
        run_file(test, klipper_build, klippy_venv, short_tmp)


def test_a_log_line_said_to_be_absent_fails_the_test(klipper_build, klippy_venv,
                                                     short_tmp):
    _, test = write_test(short_tmp, "unwanted",
                         "# EXPECT_NO_LOG: Starting Klippy\nG4 P1\n",
                         config=klipper_build.tree / "config" / "example-cartesian.cfg")
    with pytest.raises(KlippyTestFailure, match="log has 'Starting Klippy"):
        run_file(test, klipper_build, klippy_venv, short_tmp)


def test_the_build_cache_follows_the_patch_not_the_module_text(tmp_path):
    """A second run reuses the build; a changed patch input rebuilds it."""
    source = tmp_path / "source"
    for folder in ("klippy_extras", "mcu_sensor", "flowloop"):
        shutil.copytree(stack.PROJECT / folder, source / folder)
    key = stack.klipper_key(source)
    assert stack.klipper_key(source) == key
    module = source / "klippy_extras" / "flowloop.py"
    module.write_text(module.read_text() + "\n# edited\n")
    assert stack.klipper_key(source) == key  # a link: klippy reads it live
    sensor = source / "mcu_sensor" / "sensor_ems22.c"
    sensor.write_text(sensor.read_text() + "\n// edited\n")
    assert stack.klipper_key(source) != key  # compiled into the dictionaries


def test_without_klipper_the_tier_is_skipped_with_one_loud_line():
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
         "tests/klippy/test_harness.py::test_import_test_passes_in_the_patched_tree"],
        cwd=stack.PROJECT, capture_output=True, text=True,
        env={**os.environ, "KLIPPER_PATH": "/nonexistent/klipper"})
    assert proc.returncode == 0, proc.stdout
    lines = proc.stdout.splitlines()
    loud = [ln for ln in lines if ln.startswith("!!! no Klipper")]
    assert len(loud) == 1 and "git clone" in loud[0]  # how to get one
    assert sum("git clone" in ln for ln in lines) == 1  # not repeated per test
    assert "1 skipped" in proc.stdout


def test_without_kalico_its_runs_are_skipped_with_one_loud_line():
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
         "tests/klippy/test_harness.py::test_import_test_passes_in_the_patched_tree"
         "[kalico]"],
        cwd=stack.PROJECT, capture_output=True, text=True,
        env={**os.environ, "KALICO_PATH": "/nonexistent/kalico"})
    assert proc.returncode == 0, proc.stdout
    lines = proc.stdout.splitlines()
    loud = [ln for ln in lines if ln.startswith("!!! no Kalico")]
    assert len(loud) == 1 and "KALICO_PATH" in loud[0]
    assert "git clone https://github.com/KalicoCrew/kalico" in loud[0]
    assert "1 skipped" in proc.stdout


def test_each_klippy_test_runs_on_each_host_unless_listed_with_a_reason():
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "--collect-only", "-p",
         "no:cacheprovider", "tests/klippy/flowrate_limiter.test",
         "tests/klippy/test_harness.py::test_import_test_passes_in_the_patched_tree"],
        cwd=stack.PROJECT, capture_output=True, text=True)
    ids = [ln for ln in proc.stdout.splitlines() if "::" in ln]
    assert sorted(ids) == sorted([
        "tests/klippy/flowrate_limiter.test::flowrate_limiter.test",
        "tests/klippy/flowrate_limiter.test::flowrate_limiter.test[kalico]",
        "tests/klippy/test_harness.py::test_import_test_passes_in_the_patched_tree"
        "[klipper]",
        "tests/klippy/test_harness.py::test_import_test_passes_in_the_patched_tree"
        "[kalico]"]), proc.stdout
    # tests/conftest.py by its package name: a bare `import conftest` gets
    # whichever conftest.py pytest loaded last (tests/c, tests/moonraker, ...)
    from tests import conftest as root_conftest
    for host, reasons in root_conftest.NOT_ON_HOST.items():
        assert host in stack.HOSTS
        for key, reason in reasons.items():
            assert key.endswith(".test") or "::" in key, key
            assert len(reason) > 40, key  # says why, not just "broken"


def test_the_kalico_build_has_flowloop_as_plugins_and_a_firmware_extra(
        host, klipper_build):
    if host != "kalico":
        pytest.skip("Kalico's layout")
    tree = klipper_build.tree
    assert (tree / "klippy" / "plugins" / "flowrate_limiter.py").is_symlink()
    assert not (tree / "klippy" / "extras" / "flowrate_limiter.py").exists()
    assert (tree / "src" / "extras" / "flowloop" / "Kconfig").is_file()
    config = (klipper_build.dict_dir / "atmega2560.config").read_text()
    assert "CONFIG_WANT_SENSOR_EMS22=y" in config
    assert "query_ems22" in klipper_build.dictionary("atmega2560").read_text()


def test_flowloop_sees_the_sensor_command_in_either_hosts_firmware(
        klipper_build, klippy_venv, short_tmp):
    """[flowloop] asks the MCU dictionary for query_ems22 (Kalico's MCU has
    no check_valid_response); the patched build's firmware has it."""
    _, test = write_test(
        short_tmp, "firmware", "CHECK_FIRMWARE\n", cfg=(
            f"[include {klipper_build.tree / 'config' / 'example-cartesian.cfg'}]\n"
            "[flowloop]\n"
            "[gcode_macro CHECK_FIRMWARE]\ngcode:\n"
            "  {% set fw = printer.flowloop.sensor_firmware %}\n"
            "  {% if fw != {'mcu': true} %}\n"
            "    {action_raise_error('sensor_firmware is %s' % (fw,))}\n"
            "  {% endif %}\n"))
    run_file(test, klipper_build, klippy_venv, short_tmp)


HOST_NAMES = {"klipper": "Klipper", "kalico": "Kalico"}


def host_buffer_time(build) -> float:
    """BUFFER_TIME_HIGH as the host's own toolhead.py sets it (flowloop's
    table, klipper_config.HOST_BUFFER_TIME_S, must say the same)."""
    text = (build.tree / "klippy" / "toolhead.py").read_text()
    return float(re.search(r"^BUFFER_TIME_HIGH = ([0-9.]+)$", text, re.M)[1])


def check_host_status(host, build, venv, tmp, config: str, section: str) -> None:
    """Run klippy on `config` (printer.cfg text) and raise unless
    printer[section].host names the host, its toolhead's read-ahead and a
    PID heater control."""
    name, buffer_time = HOST_NAMES[host], host_buffer_time(build)
    _, test = write_test(
        tmp, "host", "CHECK_HOST\n", cfg=(
            config + "[gcode_macro CHECK_HOST]\ngcode:\n"
            f"  {{% set h = printer.{section}.host %}}\n"
            f"  {{% if h != {{'name': '{name}', 'buffer_time_s': {buffer_time},"
            " 'heater_control': 'pid'} %}\n"
            "    {action_raise_error('host is %s' % (h,))}\n"
            "  {% endif %}\n"))
    run_file(test, build, venv, tmp)


def test_the_limiter_says_which_host_it_runs_on(host, klipper_build, klippy_venv,
                                                 short_tmp):
    """[flowrate_limiter] status 'host': the host's name, the motion it queues
    ahead (toolhead BUFFER_TIME_HIGH: a cap acts that much later) and the
    heater control, read from the host itself."""
    check_host_status(
        host, klipper_build, klippy_venv, short_tmp,
        f"[include {stack.PROJECT / 'tests' / 'klippy' / 'flow_sensor_printer.cfg'}]\n"
        "[flowrate_limiter]\nmax_flow: 8\n", "flowrate_limiter")


def test_ready_api_names_the_config_error_of_a_klippy_that_never_gets_ready(
        klipper_build, klippy_venv, short_tmp):
    """Klippy.ready_api (every klippy-tier start-up): a klippy stopped by its
    configuration raises, with klippy's own message, and hands out no
    connection to a klippy that is not ready."""
    config = short_tmp / "bad.cfg"
    config.write_text(
        f"[include {stack.PROJECT / 'tests' / 'klippy' / 'flow_sensor_printer.cfg'}]\n"
        "[flowrate_limiter]\nmax_flow: -1\n")
    klippy = stack.Klippy(klipper_build, klippy_venv, config, short_tmp,
                          {"mcu": "atmega2560"})
    try:
        with pytest.raises(RuntimeError) as raised:
            klippy.ready_api()
    finally:
        klippy.stop()
    first = str(raised.value).splitlines()[0]
    assert first.startswith("klippy is not ready (error):"), first
    assert "max_flow" in first, first


def test_status_now_is_what_a_query_answers_at_once(klipper_build, klippy_venv,
                                                    short_tmp):
    """KlippyApi.status_now (the macro of status_macro.cfg) gives the status
    objects/query gives, without the wait for klippy's status tick; a
    config that lacks the macro is named, not read as an empty status."""
    here = stack.PROJECT / "tests" / "klippy"
    objects = ("toolhead", "extruder", "autotemp", "flow_sensor sim")
    klippy = stack.Klippy(klipper_build, klippy_venv, here / "autotemp.cfg",
                          short_tmp, {"mcu": "atmega2560"})
    try:
        with klippy.ready_api() as api:
            api.gcode("G28\nSET_HEATER_TEMPERATURE HEATER=extruder TARGET=205\n"
                      "G1 X50 Y40 Z1 F6000\nM400")
            now = api.status_now(*objects)
            queried = api.query_many(*objects)
            assert now == queried
            assert now["toolhead"]["position"][:2] == [50.0, 40.0]
            assert now["extruder"]["target"] == 205.0
            for _ in range(3):
                api.status_now("toolhead")
            assert not api.remote  # each answer taken, none left behind
    finally:
        klippy.stop()
    (short_tmp / "plain").mkdir()
    klippy = stack.Klippy(klipper_build, klippy_venv, here / "autotemp_plain.cfg",
                          short_tmp / "plain", {"mcu": "atmega2560"})
    try:
        with klippy.ready_api() as api:
            with pytest.raises(RuntimeError, match="status_macro.cfg"):
                api.status_now("toolhead")
    finally:
        klippy.stop()
