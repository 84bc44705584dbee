"""`make demo` starts the stack, reports what flowloop loaded, and stops."""

from __future__ import annotations

import re
import subprocess
import sys

from devtools import stack


def test_demo_runs_its_steps_and_stops_every_process(moonraker_venv):
    proc = subprocess.run([sys.executable, "-m", "devtools.demo", "--once"],
                          cwd=stack.PROJECT, capture_output=True, text=True,
                          timeout=600)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-5000:]
    assert "Moonraker: http://127.0.0.1:" in out
    assert "/server/flowloop/info" in out
    if stack.missing_klipper_reason() is None:
        assert "klippy: flowloop" in out
    else:
        assert "SKIPPED" in out
    data_dir = re.search(r"\(data: (\S+)\)", out).group(1)
    leftover = subprocess.run(["pgrep", "-f", data_dir], capture_output=True,
                              text=True).stdout.split()
    assert not leftover
