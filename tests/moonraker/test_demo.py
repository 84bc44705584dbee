"""`make demo` starts the stack, reports what flowloop loaded, and stops;
without a Klipper checkout it says so and runs every step offline."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from devtools import stack
from tests.samples import make


def run_demo(env_extra, *args):
    env = {**os.environ, **env_extra}
    proc = subprocess.run([sys.executable, "-m", "devtools.demo", "--once", *args],
                          cwd=stack.PROJECT, capture_output=True, text=True,
                          timeout=600, env=env)
    return proc.returncode, proc.stdout + proc.stderr


def assert_all_stopped(out):
    data_dir = re.search(r"\(data: (\S+)\)", out).group(1)
    leftover = subprocess.run(["pgrep", "-f", data_dir], capture_output=True,
                              text=True).stdout.split()
    assert not leftover


def url_of(out):
    return re.search(r"Moonraker: (http://127\.0\.0\.1:\d+)", out)[1]


def test_demo_runs_its_steps_with_klippy_and_stops_every_process(moonraker_venv):
    if stack.missing_klipper_reason():
        pytest.skip("no Klipper checkout")
    # the live step's report: two lines of it, not the 30 s a user watches
    code, out = run_demo({"FLOWLOOP_DEMO_LIVE_S": "6"})
    assert code == 0, out[-5000:]
    assert "Moonraker: http://127.0.0.1:" in out
    assert "klippy: flowloop" in out and "demo step" not in out
    # one file, one peak flow in every step that names it (was 6.4 and 6.7)
    peaks = set(re.findall(r"asks for up to ([0-9.]+) mm\^3/s", out))
    assert len(peaks) == 1, peaks
    # the demo printer's DIFF_AB_CALIBRATE says what it changed, not "ok"
    assert re.search(r"stepper_x: rotation_distance [0-9.]+ -> [0-9.]+", out)
    # the flow report step stored its report where Moonraker serves it; the
    # flows past what the twin melts at 200 C under-extruded
    under = re.search(r"recorded: under-extruded ([0-9.]+) mm", out)
    assert under and float(under[1]) > 0, out[out.find("=== flow_report ==="):][:800]
    assert f"{url_of(out)}/server/flowloop/report?job_id=0DE300" in out
    assert not re.search(r"^ok$", out, re.M)
    # the doctor command for this run's port, and the live page again at the end
    url = re.search(r"Moonraker: (http://127\.0\.0\.1:\d+)", out)[1]
    assert f"flowloop doctor --moonraker {url}" in out
    # (the first stack's info names its own page; the live step's comes last)
    live = re.findall(r"  live page: (http://\S+)", out)
    if "=== live ===" in out and "No klippy" not in out:
        assert out.index(f"Live page: {live[-1]}") > out.index("flowloop doctor")
        assert "printing it through Moonraker; a line every 3 s for 6 s" in out
    assert_all_stopped(out)


def test_demo_without_klipper_says_so_and_runs_every_step_offline(moonraker_venv):
    code, out = run_demo({"KLIPPER_PATH": "/nonexistent/klipper"})
    assert code == 0, out[-5000:]  # a failing step makes the exit code 1
    assert "SKIPPED" in out and "klippy: not connected" in out
    steps = re.findall(r"^=== (.+) ===$", out, re.MULTILINE)
    assert len(steps) == len(list(stack.PROJECT.glob("devtools/demo_*.py")))
    assert "/server/flowloop/report?job_id=0DE300" in out
    assert_all_stopped(out)


def test_a_second_stack_on_the_same_data_directory_starts_and_keeps_profiles(
        moonraker_venv):
    data_dir = stack.short_tempdir("fl-keep-")
    try:
        with stack.printer_stack(with_klippy=False, data_dir=data_dir) as first:
            status, _ = first.moonraker.request(
                "POST", "/server/flowloop/profile", {"profile": make(name="kept")})
            assert status == 200
            first_port = first.moonraker.port
        with stack.printer_stack(with_klippy=False, data_dir=data_dir) as second:
            assert second.moonraker.port != first_port  # a new port, still ready
            status, body = second.moonraker.request(
                "GET", "/server/flowloop/profile?name=kept")
            assert status == 200, body
    finally:
        shutil.rmtree(data_dir, ignore_errors=True)


def test_the_demo_keeps_its_data_directory_when_asked_and_starts_on_it_again(
        moonraker_venv):
    data_dir = stack.short_tempdir("fl-demo-keep-")
    try:
        with stack.printer_stack(with_klippy=False, data_dir=data_dir) as before:
            assert before.moonraker.request("POST", "/server/flowloop/profile", {
                "profile": make(name="from an earlier demo")})[0] == 200
        offline = {"KLIPPER_PATH": "/nonexistent/klipper"}
        for _ in range(2):  # the second start is the one that used to fail
            code, out = run_demo({**offline, "FLOWLOOP_DEMO_DATA": str(data_dir)},
                                 "--step", "material_profiles")
            assert code == 0, out[-5000:]
            assert f"(data: {data_dir})" in out
            assert "kept when the demo stops" in out
            assert_all_stopped(out)
        with stack.printer_stack(with_klippy=False, data_dir=data_dir) as after:
            status, body = after.moonraker.request(
                "GET", "/server/flowloop/profile?name=from%20an%20earlier%20demo")
            assert status == 200, body
    finally:
        shutil.rmtree(data_dir, ignore_errors=True)


def test_the_demo_says_it_removes_its_data_directory_and_does(moonraker_venv):
    code, out = run_demo({"KLIPPER_PATH": "/nonexistent/klipper"},
                         "--step", "material_profiles")
    assert code == 0, out[-5000:]
    assert "removed when the demo stops (set FLOWLOOP_DEMO_DATA=DIR" in out
    data_dir = re.search(r"\(data: (\S+)\)", out).group(1)
    assert not Path(data_dir).exists()
