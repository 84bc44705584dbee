"""`make demo` starts the stack, reports what flowloop loaded, and stops;
without a Klipper checkout it says so and runs every step offline."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

from devtools import stack


def run_demo(env_extra):
    env = {**os.environ, **env_extra}
    proc = subprocess.run([sys.executable, "-m", "devtools.demo", "--once"],
                          cwd=stack.PROJECT, capture_output=True, text=True,
                          timeout=600, env=env)
    return proc.returncode, proc.stdout + proc.stderr


def assert_all_stopped(out):
    data_dir = re.search(r"\(data: (\S+)\)", out).group(1)
    leftover = subprocess.run(["pgrep", "-f", data_dir], capture_output=True,
                              text=True).stdout.split()
    assert not leftover


def test_demo_runs_its_steps_with_klippy_and_stops_every_process(moonraker_venv):
    if stack.missing_klipper_reason():
        pytest.skip("no Klipper checkout")
    code, out = run_demo({})
    assert code == 0, out[-5000:]
    assert "Moonraker: http://127.0.0.1:" in out
    assert "klippy: flowloop" in out and "demo step" not in out
    assert_all_stopped(out)


def test_demo_without_klipper_says_so_and_runs_every_step_offline(moonraker_venv):
    code, out = run_demo({"KLIPPER_PATH": "/nonexistent/klipper"})
    assert code == 0, out[-5000:]  # a failing step makes the exit code 1
    assert "SKIPPED" in out and "klippy: not connected" in out
    steps = re.findall(r"^=== (.+) ===$", out, re.MULTILINE)
    assert len(steps) == len(list(stack.PROJECT.glob("devtools/demo_*.py")))
    assert_all_stopped(out)
