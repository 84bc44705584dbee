"""Flowrate limiter: what it saves, what it costs, on a real slicer file.

- Under-extrusion and print time: the block excerpt (tests/data/gcode) on the
  simulated sensor and hotend (tests/klippy/flowrate_limiter_bench.cfg: a
  twin melting 70 % of what its optimistic profile says), limiter off,
  reactive and predictive. Goal: predictive prevents >= 90 % of the
  under-extrusion the uncapped run has, at a print-time cost below the
  reactive mode's.
- The reactive rule against ddPrint's (linear in grip, no hysteresis) on the
  scenario of docs/flowrate_limiter.md (flowloop.control.rule_plot): a model,
  not a klippy run.
- klippy host time with the limiter on (checking every move, slowing none)
  vs no limiter, on the same file (batch mode, each config's start-up time
  with an empty file taken off): klippy's CPU time, the best of five runs of
  each, taken in turn. Goal: <= 1.10x.

Not measured here: the reaction time from a step drop in grip to the first
slowed move (docs/flowrate_limiter.md states the buffer's latency).
"""

from __future__ import annotations

import resource
import subprocess

from devtools.demo_flowrate_limiter import GCODE, OPTIMISTIC_PROFILE, print_closed_loop
from flowloop.control import rule_plot
from tests.klippy.test_flowrate_limiter import HERE, gcode_extrusion


def test_under_extrusion_and_print_time(klipper_build, klippy_venv, bench):
    commanded = gcode_extrusion(GCODE)
    config = HERE / "flowrate_limiter_bench.cfg"
    results = {}
    for name, enable, mode in (("off", 0, "predictive"), ("reactive", 1, "reactive"),
                               ("predictive", 1, "predictive")):
        status, moved = print_closed_loop(enable, klipper_build, klippy_venv,
                                          OPTIMISTIC_PROFILE, config, mode)
        results[name] = (commanded - moved, status["print_time"])
        bench.figure(f"limiter {name}: under-extruded", commanded - moved, " mm")
        bench.figure(f"limiter {name}: print time", status["print_time"], " s")
    lost_off, time_off = results["off"]
    for name in ("reactive", "predictive"):
        lost, took = results[name]
        bench.ratio(f"{name}: under-extrusion left", lost, lost_off,
                    goal="<= 0.10x" if name == "predictive" else "")
        bench.ratio(f"{name}: print time", took, time_off)
    bench.ratio("predictive vs reactive: print time", results["predictive"][1],
                results["reactive"][1], goal="< 1.0x")


def test_reactive_rule_against_ddprint_s(bench):
    ours = rule_plot.under_extrusion(rule_plot.simulate("flowloop"))
    theirs = rule_plot.under_extrusion(rule_plot.simulate("ddprint"))
    bench.ratio("reactive rule: under-extrusion vs ddPrint's rule (model)",
                ours, theirs, " mm^3", goal="< 1.0x")


def _klippy_cpu_seconds(build, venv, config, gcode, tmp):
    """CPU time (user + system) of one batch klippy run: other work on the
    machine stretches wall time, much less the CPU time klippy itself uses."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([str(venv.python), str(build.klippy), str(config), "-i",
                    str(gcode), "-o", str(tmp / "out"), "-l", str(tmp / "log"),
                    "-d", str(build.dictionary("atmega2560"))],
                   cwd=build.tree, check=True, capture_output=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


RUNS = 5

BED = """
[heater_bed]
heater_pin: PH5
sensor_type: EPCOS 100K B57560G104F
sensor_pin: PK6
control: watermark
min_temp: 0
max_temp: 110
"""


def test_klippy_host_time_with_the_limiter(klipper_build, klippy_venv, bench,
                                           tmp_path):
    # The same motion both ways: a limiter that checks every move against a
    # cap no move reaches, against no limiter at all
    base = f"[include {HERE / 'flow_sensor_printer.cfg'}]\n{BED}"
    without = tmp_path / "without.cfg"
    without.write_text(base)
    with_limiter = tmp_path / "with.cfg"
    with_limiter.write_text(base + "\n[flowrate_limiter]\nmax_flow: 1000\n")
    empty = tmp_path / "empty.gcode"
    empty.write_text("")
    # The excerpt (it homes and resets E itself) eight times: enough motion
    # that the start-up's scatter does not swamp the difference
    gcode = tmp_path / "long.gcode"
    gcode.write_text(GCODE.read_text() * 8)
    # The best of RUNS each, the four kinds of run taken in turn so that a
    # busy spell on the machine hits all of them; start-up (importing
    # flowloop's numpy and msgspec included) taken off
    runs = {}
    for _ in range(RUNS):
        for cfg in (with_limiter, without):
            for file in (gcode, empty):
                runs.setdefault((cfg, file), []).append(_klippy_cpu_seconds(
                    klipper_build, klippy_venv, cfg, file, tmp_path))
    t_on, t_off = (min(runs[cfg, gcode]) - min(runs[cfg, empty])
                   for cfg in (with_limiter, without))
    bench.ratio("klippy host CPU time, limiter on vs none (start-up taken off)",
                t_on, t_off, " s", goal="<= 1.10x")
