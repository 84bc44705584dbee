"""Steps from klippy's batch output, decoded with Klipper's own parsedump.py:
one stepper's step times and directions, and flow over time from them."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np

CONFIG_STEPPER = re.compile(r"^config_stepper oid=(\d+) step_pin=(\S+)")
QUEUE_STEP = re.compile(r"^queue_step oid=(\d+) interval=(\d+) count=(\d+) add=(-?\d+)")
STEP_DIR = re.compile(r"^set_next_step_dir oid=(\d+) dir=(\d+)")
RESET_CLOCK = re.compile(r"^reset_step_clock oid=(\d+) clock=(\d+)")


def parsedump(build, venv, dictionary: Path, output: Path) -> List[str]:
    # Klipper's script imports msgproto by name (run it in klippy/); Kalico's
    # imports it relative to its klippy package (run it as a module).
    script = build.tree / "klippy" / "parsedump.py"
    if "from . import" in script.read_text():
        cmd, cwd = [str(venv.python), "-m", "klippy.parsedump"], build.tree
    else:
        cmd, cwd = [str(venv.python), "parsedump.py"], script.parent
    proc = subprocess.run(cmd + [str(dictionary), str(output)], cwd=cwd,
                          capture_output=True, text=True, check=True)
    return proc.stdout.splitlines()


def stepper_steps(lines: List[str], step_pin: str) -> Tuple[np.ndarray, np.ndarray]:
    """(clock of each step, +1/-1 direction of each step) of the stepper on
    step_pin, following stepper.c: a queue_step's first step comes interval
    ticks after the previous step, each next one interval + k * add later."""
    oid = None
    clocks: List[int] = []
    dirs: List[int] = []
    last = 0
    direction = 1
    for line in lines:
        m = CONFIG_STEPPER.match(line)
        if m and m.group(2) == step_pin:
            oid = m.group(1)
            continue
        if oid is None or f"oid={oid} " not in line + " ":
            continue
        m = QUEUE_STEP.match(line)
        if m:
            interval, count, add = (int(g) for g in m.groups()[1:])
            k = np.arange(count, dtype=np.int64)
            times = last + np.cumsum(interval + k * add)
            clocks.extend(times.tolist())
            dirs.extend([direction] * count)
            last = int(times[-1])
            continue
        m = STEP_DIR.match(line)
        if m:
            direction = 1 if m.group(2) == "1" else -1
            continue
        m = RESET_CLOCK.match(line)
        if m:
            last = int(m.group(2))
    if oid is None:
        raise AssertionError(f"no stepper on {step_pin} in the output")
    return np.array(clocks, dtype=np.int64), np.array(dirs, dtype=np.int64)


EXITING = re.compile(r"Exiting \(print time ([0-9.]+)s\)")


def output_is_whole(log: str, lines: List[str], step_pins: List[str],
                    clock_hz: float) -> bool:
    """Whether the MCU output holds the motion up to where klippy said it
    exited (the end of its last move, which every stepper on step_pins
    takes part in; within 10 ms: a step, not a move).
    In batch mode the output is written by the serial queue's own thread,
    and klippy's exit does not wait for it: on a busy machine the last
    messages were lost (on Kalico: 9 steps once, 3.5 s of steps once, every
    run beside six busy processes), until run_file's launcher made the exit
    wait (devtools/realtime_klippy.py, drain_on_disconnect)."""
    exits = EXITING.findall(log)
    if not exits:
        return True  # no exit line to judge by
    last = min(stepper_steps(lines, pin)[0][-1] / clock_hz for pin in step_pins)
    return last >= float(exits[-1]) - 0.01


def windowed_flow(clocks: np.ndarray, dirs: np.ndarray, clock_hz: float,
                  mm_per_step: float, area_mm2: float,
                  window_s: float) -> Dict[str, float]:
    """Forward filament per window as volumetric flow: the highest window,
    and the steps one window at the cap would allow."""
    forward = clocks[dirs > 0] / clock_hz
    if not len(forward):
        return {"max_flow": 0.0, "windows": 0}
    edges = np.arange(0.0, forward[-1] + window_s, window_s)
    counts = np.histogram(forward, edges)[0]
    # Two grids half a window apart, so no burst hides across an edge
    counts2 = np.histogram(forward, edges + window_s / 2)[0]
    most = max(counts.max(), counts2.max())
    return {"max_flow": most * mm_per_step * area_mm2 / window_s,
            "max_steps": int(most), "windows": len(counts)}
