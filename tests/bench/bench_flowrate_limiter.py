"""Flowrate limiter: what it saves, what it costs, on a real slicer file.

- Under-extrusion and print time: the block excerpt (tests/data/gcode) on the
  simulated sensor and hotend, limiter off, reactive, predictive, and the
  slip-free bound (a limiter told the twin's true capacity), on ten
  hotends (HOTENDS): the bench's own (a twin melting 70 % of what its
  optimistic profile says, as tests/klippy/flowrate_limiter_bench.cfg),
  four the limiter was not tuned on, fixed before any tuning (issue 41): a
  high-flow hotend, a worn nozzle, a noisy sensor, a slow high-mass one
  (heater time constant, heat capacity and melt lag twice the bench's),
  and one true to its profile (added with the first print's climb, to show
  what the climb costs where nothing needs it); and a second held-out set
  of the same four kinds (FRESH_HOTENDS), fixed before the model's fit was
  tuned again on the first (which had by then been looked at). The same
  runs again on the print's first ten layers (make bench only), where a
  first print's climb is a smaller share and a model that drifts over a
  print drifts further. Goals (issue 41):
  predictive prevents >= 98 % of the under-extrusion the uncapped run has
  (asserted on every hotend) at a print time within the slip-free bound's
  (printed; guarded at TIME_GUARD), and on the bench's hotend at a
  print-time cost below the reactive mode's (not met). Each hotend's next
  print, the profile activated with the ratio carried from the predictive
  run (what Moonraker sends after a restart): the same goals, asserted and
  guarded the same way. The same run gives the same figures (the twin is
  seeded and devtools.demo_flowrate_limiter.print_closed_loop syncs the
  sensor at each chunk, about a second of print time), to within one
  sensor count (0.01 mm) and 0.05 s with two klippy side by side; besides the goals'
  ratios, the time each mode adds per mm of under-extrusion it prevents
  (reactive is faster partly because it lets the
  feeder slip, and a slipping print runs at full speed). The table of
  docs/flowrate_limiter.md is printed at the end.
- The reactive rule against ddPrint's (linear in grip, no hysteresis) on the
  scenario of docs/flowrate_limiter.md (flowloop.control.rule_plot): a model,
  not a klippy run.
- klippy host time with the limiter on (checking every move, slowing none)
  vs no limiter, on the same file (batch mode, each config's start-up time
  with an empty file taken off): klippy's CPU time, the best of five runs of
  each, taken in turn. Goal: <= 1.10x. And on a printer, where the limiter
  queues a long extruding move in pieces (batch mode does not): the same
  file cut as it cuts them, the limiter on, against neither. Goal: <= 1.10x.

- Reaction time from a step drop in grip to the first slowed move
  executing, on a klippy paced to the clock (devtools/realtime_klippy.py):
  a steady print at 7 mm^3/s on a hotend at its temperature, the twin's
  melt stepped down at a known print time, the first slowed extruder step
  found in klippy's MCU output; on 5 mm segments, and on 3 s lines (queued
  in pieces). Goal: <= 1.2 s.
"""

from __future__ import annotations

import math
import os
import resource
import shutil
import subprocess
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Tuple

import numpy as np
import pytest

from devtools import stack
from devtools.demo_flowrate_limiter import (
    GCODE,
    OPTIMISTIC_PROFILE,
    cut_as_on_a_printer,
    print_closed_loop,
)
from devtools.klippy_api import KlippyApi
from flowloop.control import nozzle_health as nh
from flowloop.control import rule_plot
from flowloop.control.hotend import HotendParams
from flowloop.material.profile import min_grip_of, profile_from_dict
from flowloop.sensor.twin import DEFAULT_MELT_TIME_S, DEFAULT_NOISE_COUNTS
from tests.bench.size import FULL, pick
from tests.klippy.flowrate_limiter_steps import parsedump, stepper_steps
from tests.klippy.test_flowrate_limiter import AREA, CLOCK_HZ, HERE, gcode_extrusion
from tests.samples import STRONG_PROFILE


def _scaled_profile(profile, scale, name="truthful"):
    """The profile of a hotend melting `scale` of what `profile` says."""
    lines = {name: {**line, "flow_mm3_s": scale * line["flow_mm3_s"],
                    "slope_mm3_s_per_c": scale * line["slope_mm3_s_per_c"]}
             for name, line in profile["lines"].items()}
    return {**profile, "identity": {**profile["identity"], "name": name},
            "lines": lines}


@dataclass(frozen=True)
class Hotend:
    """One simulated hotend of the bench print: the profile the limiter is
    given (OPTIMISTIC_PROFILE times profile_scale), what the twin really
    melts of it (melt_scale), the twin's other options, and the speed
    factor (M220) the file is printed at."""
    name: str
    profile_scale: float = 1.0
    melt_scale: float = 0.7
    twin_options: Tuple[Tuple[str, str], ...] = ()
    speed_percent: int = 100

    @property
    def profile(self):
        return _scaled_profile(OPTIMISTIC_PROFILE, self.profile_scale,
                               f"{self.name} profile")

    @property
    def true_profile(self):
        """A profile that says exactly what this twin melts."""
        return self.knowing_profile(1.0)

    def knowing_profile(self, share):
        """A profile that says `share` of what this twin melts."""
        return _scaled_profile(OPTIMISTIC_PROFILE,
                               share * self.profile_scale * self.melt_scale,
                               f"{self.name} truthful"
                               + ("" if share == 1.0 else f" x{share:g}"))

    def config(self, tmp_path, melt_scale):
        options = (("melt_scale", f"{melt_scale:g}"),) + self.twin_options
        path = tmp_path / f"{self.name}-{melt_scale:g}.cfg".replace(" ", "_")
        path.write_text(f"[include {HERE / 'flowrate_limiter_loop.cfg'}]\n"
                        "[flow_sensor_simulation sim]\n"
                        + "".join(f"{k}: {v}\n" for k, v in options))
        return path

    def gcode(self, gcode, tmp_path):
        if self.speed_percent == 100:
            return gcode
        path = tmp_path / f"{self.name}.gcode".replace(" ", "_")
        path.write_text(f"M220 S{self.speed_percent}\n" + gcode.read_text())
        return path


# The bench's own hotend (as tests/klippy/flowrate_limiter_bench.cfg: 40 W,
# melting 70 % of its optimistic profile, 4.2 mm^3/s at 200 C), and the
# hotends the limiter was not tuned on, fixed before any tuning (issue 41;
# the slow high-mass one was added once the twin took its options, with no
# tuning after it).
BENCH_HOTEND = Hotend("bench")
HOTENDS = (
    BENCH_HOTEND,
    # twice the bench's capacity (8.4 mm^3/s at 200 C) and heater, the
    # file printed at twice its speeds so that it still asks for more
    Hotend("high-flow", profile_scale=2.0,
           twin_options=(("heater_power", "80"),), speed_percent=200),
    # a worn nozzle: melts 15 % less than its profile says
    Hotend("worn nozzle", melt_scale=0.85),
    # the sensor's noise twice the datasheet's (twin.DEFAULT_NOISE_COUNTS)
    Hotend("noisy sensor",
           twin_options=(("noise_counts", f"{2 * DEFAULT_NOISE_COUNTS:g}"),)),
    # a slow high-mass hotend: its heater's time constant and heat capacity
    # and its melt lag twice the bench's (HotendParams', twin's defaults)
    Hotend("slow high-mass", twin_options=(
        ("heater_time_constant", f"{2 * HotendParams.time_constant_s:g}"),
        ("heater_heat_capacity", f"{2 * HotendParams.heat_capacity_j_per_c:g}"),
        ("melt_time", f"{2 * DEFAULT_MELT_TIME_S:g}"))),
    # added 2026-11-30, after the first print's climb (grip_model.CLIMB_FROM)
    # was chosen, to show what it costs where nothing needs it: a hotend
    # that melts exactly what its profile says (the model's seed, the line
    # at the profile's min_grip 0.9, is its capacity)
    Hotend("true to its profile", melt_scale=0.9),
)
# A second held-out set, fixed on 2026-11-30 before the model's fit was
# touched again, once tuning had looked at every hotend above (so those are
# a tuning set now): the same four kinds as the issue asks for, each set up
# differently from its first (capacity, heater, speed, the noise's seed).
FRESH_HOTENDS = (
    # 2.5 times the bench's capacity and heater, the file at 2.5 times its
    # speeds
    Hotend("high-flow B", profile_scale=2.5,
           twin_options=(("heater_power", "100"),), speed_percent=250),
    # a worn nozzle (15 % below its profile) on a profile 1.3 times the
    # bench's, a 52 W heater, the file at 1.3 times its speeds
    Hotend("worn nozzle B", profile_scale=1.3, melt_scale=0.85,
           twin_options=(("heater_power", "52"), ("seed", "3")),
           speed_percent=130),
    # twice the datasheet's noise, another noise draw, a hotend melting 65 %
    # of its profile
    Hotend("noisy sensor B", melt_scale=0.65, twin_options=(
        ("noise_counts", f"{2 * DEFAULT_NOISE_COUNTS:g}"), ("seed", "11"))),
    # time constant, heat capacity and melt lag 2.5 times the bench's, 75 %
    # of its profile
    Hotend("slow high-mass B", melt_scale=0.75, twin_options=(
        ("heater_time_constant", f"{2.5 * HotendParams.time_constant_s:g}"),
        ("heater_heat_capacity",
         f"{2.5 * HotendParams.heat_capacity_j_per_c:g}"),
        ("melt_time", f"{2.5 * DEFAULT_MELT_TIME_S:g}"))),
)

# The smoke run's print: the excerpt's first lines (homing and the start of
# its first layer), on the held-out hotend whose set-up differs most from
# the bench's (its profile, heater and speed factor), so every path of a
# hotend's set-up runs: every run of a hotend takes 7 s however short the
# file, the warm-up included
SMOKE_LINES = 400
SMOKE_HOTENDS = HOTENDS[1:2]
RUN_NAMES = ("off", "reactive", "predictive", "knowing the capacity")
# predictive again, the profile activated with the melt ratio carried from
# the predictive run (nozzle_health.carried_ratio of what Moonraker stores
# of it: what Moonraker sends at the next activation, the same hotend's next
# print after a restart)
SEEDED = "predictive, seeded"
# The limiter that knows the capacity is not slip-free: capped at the
# capacity, a speed change still slips while the melt catches up (0.6-0.8 mm
# on this print). Told a share of it (KNOWING_SHARES) it trades that slip
# for time, so predictive's time is also judged against it at predictive's
# own under-extrusion (equal_slip_time: between the shares it was told).
KNOWING_SHARES = (0.99, 1.01)
KNOWING = {share: f"knowing {share:.0%} of the capacity"
           for share in KNOWING_SHARES}
# the hotends run side by side, one klippy each (each klippy is one process)
WORKERS = max(1, min(2, os.cpu_count() or 1))


def _print_hotend(hotend, gcode, build, venv, tmp_path):
    """(under-extruded mm, print time s) of each run on this hotend: the
    limiter off, reactive, predictive, and the slip-free bound: the same
    twin under the temperature cap alone on a profile that says exactly
    what it melts (a limiter that knows the capacity at every
    temperature)."""
    gcode = hotend.gcode(gcode, tmp_path)
    commanded = gcode_extrusion(gcode)
    given = hotend.config(tmp_path, hotend.melt_scale)
    runs = ((0, hotend.profile, given, "predictive"),
            (1, hotend.profile, given, "reactive"),
            (1, hotend.profile, given, "predictive"),
            (1, hotend.true_profile, hotend.config(tmp_path, 1.0), "temperature"))
    # the twin's melt against the model's seed (the profile's line at its
    # min_grip): what a carried ratio would be, were the model exact
    results = {"true_ratio": hotend.melt_scale / min_grip_of(
        profile_from_dict(hotend.profile))}
    for name, (enable, profile, cfg, mode) in zip(RUN_NAMES, runs):
        status, moved = print_closed_loop(enable, build, venv, profile, cfg,
                                          mode, gcode)
        results[name] = (commanded - moved, status["print_time"])
        if name == "predictive":
            results["model"] = status["model"]
            results["estimate"] = status["nozzle_health"]
    for share, name in KNOWING.items():
        # told `share` of what it melts: the twin melts 1/share of the line
        status, moved = print_closed_loop(
            1, build, venv, hotend.knowing_profile(share),
            hotend.config(tmp_path, 1.0 / share), "temperature", gcode)
        results[name] = (commanded - moved, status["print_time"])
    ratio = nh.carried_ratio([results["estimate"]])
    results["seed"] = ratio
    status, moved = print_closed_loop(1, build, venv, hotend.profile, given,
                                      "predictive", gcode, melt_ratio=ratio)
    # the seed stood (confirmed by the windows), or was dropped unconfirmed
    # (limiter.CONFIRM_SEED_S)
    assert ratio in (status["seed_melt_ratio"], status["dropped_melt_ratio"]), status
    results["dropped"] = status["dropped_melt_ratio"]
    results[SEEDED] = (commanded - moved, status["print_time"])
    return results


def test_under_extrusion_and_print_time(klipper_build, klippy_venv, bench,
                                        tmp_path):
    gcode = GCODE
    if not FULL:
        gcode = tmp_path / "smoke.gcode"
        gcode.write_text("\n".join(GCODE.read_text().splitlines()[:SMOKE_LINES]))
    table = _hotend_table(pick(HOTENDS + FRESH_HOTENDS, SMOKE_HOTENDS), gcode,
                          klipper_build, klippy_venv, bench, tmp_path)
    # (the smoke run has only the held-out hotend: its figures stand in)
    _bench_hotend_ratios(bench, table.get(BENCH_HOTEND.name,
                                          next(iter(table.values()))))
    if FULL:
        _assert_goals_met_today(table)


# The same print's first ten layers (block.gcode's first 4050 lines, of
# which the bench print is the first 755): 13-17 min where the two layers
# take 4-7, so what a first print's climb costs once is a smaller share,
# and a model that drifts over a print drifts further
TEN_LAYERS = GCODE.parent / "block_layers_1_10.gcode"


def test_under_extrusion_and_print_time_over_ten_layers(
        klipper_build, klippy_venv, bench, tmp_path):
    if not FULL:
        pytest.skip("make bench only: the same runs as the two layers' on a"
                    " longer file (its smoke run covers them)")
    table = _hotend_table(HOTENDS + FRESH_HOTENDS, TEN_LAYERS, klipper_build,
                          klippy_venv, bench, tmp_path, "ten layers: ")
    _assert_goals_met_today(table)


def _hotend_table(hotends, gcode, build, venv, bench, tmp_path, label=""):
    """Every hotend's runs on `gcode` (two at a time), their figures and
    ratios printed (names prefixed with `label`), and the docs' tables;
    the runs by hotend name."""
    with ThreadPoolExecutor(WORKERS) as pool:
        done = list(pool.map(lambda hotend: _print_hotend(
            hotend, gcode, build, venv, tmp_path), hotends))
    table = {}
    for hotend, results in zip(hotends, done):
        table[hotend.name] = results
        name = label + hotend.name
        estimate = results["estimate"]
        bench.figure(f"{name}: predictive's nozzle health estimate"
                     f" ({estimate.reason or 'known'})",
                     math.nan if estimate.ratio is None else estimate.ratio,
                     f" of the profile, the twin melts {results['true_ratio']:.3f}")
        bench.figure(f"{name}: carried to '{SEEDED}' (its model's ratio"
                     " at the end; dropped unconfirmed: "
                     f"{results['dropped'] is not None})", results["seed"], "")
        for run in RUN_NAMES + tuple(KNOWING.values()) + (SEEDED,):
            lost, took = results[run]
            bench.figure(f"{name}: limiter {run}: under-extruded", lost, " mm")
            bench.figure(f"{name}: limiter {run}: print time", took, " s")
        bench.figure(f"{name}: predictive's grip model at the end",
                     results["model"]["capacity_mm3_s"], " mm^3/s at"
                     f" {results['model']['ref_temp_c']:g} C")
    for hotend_name, r in table.items():
        name = label + hotend_name
        bench.ratio(f"{name}: predictive under-extrusion vs limiter off",
                    r["predictive"][0], r["off"][0], " mm", goal="<= 0.02x")
        bench.ratio(f"{name}: predictive print time vs the slip-free bound",
                    r["predictive"][1], r["knowing the capacity"][1], " s",
                    goal="<= 1.0x")
        bench.ratio(f"{name}: predictive print time vs the limiter knowing"
                    " the capacity at predictive's under-extrusion",
                    r["predictive"][1], equal_slip_time(r, r["predictive"][0]),
                    " s", goal="<= 1.0x")
        bench.ratio(f"{name}: predictive seeded by its last print, under-extrusion"
                    " vs limiter off", r[SEEDED][0], r["off"][0], " mm",
                    goal="<= 0.02x")
        bench.ratio(f"{name}: predictive seeded by its last print, print time vs"
                    " the slip-free bound", r[SEEDED][1],
                    r["knowing the capacity"][1], " s", goal="<= 1.0x")
        bench.ratio(f"{name}: predictive seeded by its last print, print time vs"
                    " the limiter knowing the capacity at its under-extrusion",
                    r[SEEDED][1], equal_slip_time(r, r[SEEDED][0]), " s",
                    goal="<= 1.0x")
    for line in _table(table):
        bench.terminal.write_line(line)
    return table


def equal_slip_time(results, lost_mm):
    """The print time of the limiter that knows the capacity were it told
    the share of it at which it under-extrudes lost_mm: interpolated between
    the shares it was told (KNOWING_SHARES and 1), their under-extrusion
    rising with the share; held at the end shares outside them; nan where
    the points do not rise (no share to read)."""
    names = [KNOWING[KNOWING_SHARES[0]], "knowing the capacity",
             KNOWING[KNOWING_SHARES[-1]]]
    lost = np.array([results[name][0] for name in names])
    took = np.array([results[name][1] for name in names])
    if not np.all(np.diff(lost) > 0.0):
        return math.nan
    return float(np.interp(lost_mm, lost, took))


def _bench_hotend_ratios(bench, results):
    """The bench hotend's figures against each other (issue 30's goals)."""
    lost_off, time_off = results["off"]
    for name in ("reactive", "predictive"):
        lost, took = results[name]
        bench.ratio(f"{name}: under-extrusion left", lost, lost_off,
                    goal="<= 0.10x" if name == "predictive" else "")
        bench.ratio(f"{name}: print time", took, time_off)
    bench.ratio("predictive vs reactive: print time", results["predictive"][1],
                results["reactive"][1], goal="< 1.0x")
    # What no slip costs at the least: predictive learns the capacity that
    # the bound is told
    bound = results["knowing the capacity"][1]
    bench.ratio("predictive vs the slip-free bound: print time",
                results["predictive"][1], bound, goal="<= 1.0x")
    bench.ratio("reactive vs the slip-free bound: print time",
                results["reactive"][1], bound)
    # Reactive lets the feeder slip, and a slipping print runs at full speed:
    # the time each adds per mm of under-extrusion it prevents
    cost = {name: (results[name][1] - time_off) / (lost_off - results[name][0])
            for name in ("reactive", "predictive")}
    bench.ratio("predictive vs reactive: print time added per mm of"
                " under-extrusion prevented", cost["predictive"], cost["reactive"],
                " s/mm")


def _table(table):
    """The markdown table of docs/flowrate_limiter.md: under-extruded mm per
    run, predictive's as a share of limiter-off (goal <= 0.02x), its print
    time against the slip-free bound (goal <= 1.0x)."""
    yield ("| hotend | off | reactive | predictive | knowing the capacity"
           " | predictive / off | predictive time / bound |")
    yield "| --- | --- | --- | --- | --- | --- | --- |"
    for name, r in table.items():
        lost = [r[run][0] for run in RUN_NAMES]
        share = lost[2] / lost[0] if lost[0] > 0 else math.nan
        time_share = r["predictive"][1] / r["knowing the capacity"][1]
        yield (f"| {name} | " + " | ".join(f"{v:.2f} mm" for v in lost)
               + f" | {share:.3f}x | {time_share:.3f}x |")
    yield ""
    yield ("| hotend | carried ratio (the twin's true one) | seeded: under-extruded"
           " | seeded / off | seeded time / bound |")
    yield "| --- | --- | --- | --- | --- |"
    for name, r in table.items():
        ratio = r["seed"]
        lost, took = r[SEEDED]
        yield (f"| {name} | {'none' if ratio is None else f'{ratio:.3f}'}"
               f" ({r['true_ratio']:.3f}) | {lost:.2f} mm"
               f" | {lost / r['off'][0]:.3f}x"
               f" | {took / r['knowing the capacity'][1]:.3f}x |")
    yield ""
    knowing = [KNOWING[KNOWING_SHARES[0]], "knowing the capacity",
               KNOWING[KNOWING_SHARES[-1]]]
    yield ("| hotend | " + " | ".join(knowing) + " | predictive"
           " | predictive time / knowing's at its under-extrusion"
           " | seeded | seeded time / knowing's at its under-extrusion |")
    yield "| --- |" + " --- |" * (len(knowing) + 4)
    for name, r in table.items():
        cells = [f"{r[run][0]:.2f} mm, {r[run][1]:.1f} s"
                 for run in knowing + ["predictive"]]
        first, seeded = r["predictive"], r[SEEDED]
        yield (f"| {name} | " + " | ".join(cells)
               + f" | {first[1] / equal_slip_time(r, first[0]):.3f}x"
               + f" | {seeded[0]:.2f} mm, {seeded[1]:.1f} s"
               + f" | {seeded[1] / equal_slip_time(r, seeded[0]):.3f}x |")


# Print time against the slip-free bound's, first print and seeded by the
# last: issue 41's goal is 1.0x. Measured 2026-11-30 on the ten hotends
# (the first print climbing from CLIMB_FROM, the G-code fed in a printer's
# pieces): first prints 0.994-1.007x, 0.999-1.003x at their own
# under-extrusion (equal_slip_time); seeded 0.995-1.005x and 0.999-1.000x;
# guarded at this
TIME_GUARD = 1.02


def _assert_goals_met_today(table):
    """Asserted where it was met on 2026-11-30: predictive's under-extrusion
    <= 0.02x of limiter-off (issue 41's goal) on a first print and seeded by
    the last, on every hotend; its print time within TIME_GUARD of the
    slip-free bound's, and of the limiter knowing the capacity at its own
    under-extrusion (the goal, 1.0x, is printed: the climb costs a first
    print up to 0.7 %, docs/flowrate_limiter.md)."""
    for name, r in table.items():
        bound = r["knowing the capacity"][1]
        for run in ("predictive", SEEDED):
            assert r[run][0] <= 0.02 * r["off"][0], (name, run, r)
            assert r[run][1] <= TIME_GUARD * bound, (name, run, r)
            assert r[run][1] <= TIME_GUARD * equal_slip_time(r, r[run][0]), \
                (name, run, r)


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


RUNS = pick(5, 1)


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
    # The excerpt (it homes and resets E itself) sixteen times: enough motion
    # that the start-up's scatter does not swamp the difference
    gcode = tmp_path / "long.gcode"
    gcode.write_text(GCODE.read_text() * pick(16, 1))
    # On a printer the limiter queues its long extruding moves in pieces
    # (batch mode does not): the same file cut as it cuts them
    cut = tmp_path / "cut.gcode"
    cut.write_text("\n".join(cut_as_on_a_printer(gcode.read_text().splitlines())))
    # The best of RUNS each, the kinds of run taken in turn so that a busy
    # spell on the machine hits all of them; start-up (importing flowloop's
    # numpy and msgspec included) taken off
    runs = {}
    kinds = [(cfg, file) for cfg in (with_limiter, without)
             for file in (gcode, cut, empty)]
    for _ in range(RUNS):
        for cfg, file in kinds:
            runs.setdefault((cfg, file), []).append(_klippy_cpu_seconds(
                klipper_build, klippy_venv, cfg, file, tmp_path))
    cpu = {(cfg, file): min(runs[cfg, file]) - min(runs[cfg, empty])
           for cfg, file in kinds if file is not empty}
    bench.ratio("klippy host CPU time, limiter on vs none (start-up taken off)",
                cpu[with_limiter, gcode], cpu[without, gcode], " s",
                goal="<= 1.10x")
    moves = [sum(line.startswith("G1") for line in f.read_text().splitlines())
             for f in (cut, gcode)]
    bench.ratio("G1 moves klippy queues, cut as on a printer vs as sliced",
                *moves, "")
    bench.ratio("klippy host CPU time, no limiter, the file cut as on a"
                " printer vs as sliced", cpu[without, cut], cpu[without, gcode],
                " s")
    bench.ratio("klippy host CPU time, limiter on and the file cut as on a"
                " printer vs neither", cpu[with_limiter, cut],
                cpu[without, gcode], " s", goal="<= 1.10x")


# --- reaction time, in real time ---------------------------------------------

# A circle of 5 mm segments at 100 mm/s (every junction allows full speed)
# extruding 7 mm^3/s: the twin melts 0.7 x 12 = 8.4 of it under
# STRONG_PROFILE, and 0.7 x 8 = 5.6 (grip 0.8) under WEAKER, whose line (8)
# still lies above 7 so that the temperature cap does not act on the step
# itself.
WEAKER = {**STRONG_PROFILE, "identity": {"name": "weaker", "nozzle_diameter_mm": 0.4},
        "lines": {"into_air": {"slope_mm3_s_per_c": 0.1, "temp_c": 200.0,
                               "flow_mm3_s": 8.5},
                  "real_print": {"slope_mm3_s_per_c": 0.1, "temp_c": 200.0,
                                 "flow_mm3_s": 7.5}}}
SPEED_MM_S, FLOW_MM3_S, SEGMENT_MM = 100.0, 7.0, 5.0
LINE_MM, LINE_S = 120.0, 3.0  # the lines' variant: 40 mm/s
STEP_AT_S = 8.0      # the step, this long after the print starts
PRINT_S = 14.0


def _circle_gcode(seconds: float) -> str:
    radius = 60.0
    e_per_mm = FLOW_MM3_S / (AREA * SPEED_MM_S)
    count = int(seconds * SPEED_MM_S / SEGMENT_MM)
    per_turn = 2 * math.pi * radius / SEGMENT_MM
    lines = [f"G1 X{100 + radius:.3f} Y100 F6000", "M83"]
    for i in range(1, count + 1):
        angle = 2 * math.pi * i / per_turn
        lines.append(f"G1 X{100 + radius * math.cos(angle):.3f}"
                     f" Y{100 + radius * math.sin(angle):.3f}"
                     f" E{SEGMENT_MM * e_per_mm:.5f} F{SPEED_MM_S * 60:g}")
    return "\n".join(lines + ["M400"])


def _lines_gcode(seconds: float) -> str:
    """Straight lines of LINE_S each, back and forth, at the same flow: a
    slicer's infill (the bench print's lines run up to 3.3 s)."""
    speed = LINE_MM / LINE_S
    e_per_line = FLOW_MM3_S / AREA * LINE_S
    lines = ["G1 X40 Y100 F6000", "M83"]
    for i in range(math.ceil(seconds / LINE_S)):
        lines.append(f"G1 X{40 + LINE_MM * ((i + 1) % 2):g} Y100"
                     f" E{e_per_line:.5f} F{speed * 60:g}")
    return "\n".join(lines + ["M400"])


MOVES = {"5 mm segments": _circle_gcode, "3 s lines": _lines_gcode}


def _step_time(rows, near_s):
    """Print time at which the twin's filament starts to fall behind the
    commanded, from the sensor's own samples (flow_sensor/dump_flow: time,
    filament_mm, commanded_mm): the deficit's line after it leaves its level
    before near_s, followed back to that level."""
    t, filament, commanded = (np.array(c) for c in zip(*rows))
    deficit = commanded - filament
    level = np.median(deficit[(t > near_s - 1.0) & (t < near_s - 0.3)])
    behind = np.nonzero((t > near_s - 0.3) & (deficit > level + 0.02))[0][0]
    after = (t >= t[behind]) & (t < t[behind] + 0.5)
    slope, offset = np.polyfit(t[after], deficit[after], 1)
    return float((level - offset) / slope)


def _first_slowed_step(times, step_at_s):
    """Print time of the first extruder step after step_at_s from which the
    step interval stays 5 % longer than before the step (a slowed move, or
    the deceleration into one)."""
    intervals = np.diff(times)
    before = intervals[(times[1:] > step_at_s - 3.0) & (times[1:] < step_at_s)]
    steady = float(np.median(before))
    slow = intervals > 1.05 * steady
    for i in np.nonzero(slow & (times[1:] > step_at_s))[0]:
        if slow[i:i + 50].all():
            return float(times[i]), steady
    return None, steady


@pytest.mark.alone  # paced to the clock
@pytest.mark.parametrize("moves,grip_window_mm", pick(
    [("5 mm segments", 1.25), ("5 mm segments", 0.5), ("3 s lines", 1.25)],
    [("5 mm segments", 1.25), ("3 s lines", 1.25)]))
def test_reaction_time_to_a_step_drop_in_grip(klipper_build, klippy_venv, bench,
                                              moves, grip_window_mm):
    # 1.25 mm: [flow_sensor]'s default grip_window (0.43 s of filament at
    # 7 mm^3/s); 0.5 mm: what a shorter window saves. 5 mm segments of a
    # circle, or straight lines of 3 s each (a cap acts on a move when
    # klippy queues it, about a second before it runs). (When the limiter
    # decides is not split out: a status poll answers 0.25-0.75 s late while
    # klippy prints in real time.)
    workdir = stack.short_tempdir("fl-react-")
    config = workdir / "printer.cfg"
    config.write_text(f"[include {HERE / 'flowrate_limiter_reaction.cfg'}]\n"
                      f"[flow_sensor_simulation sim]\ngrip_window: {grip_window_mm}\n")
    klippy = stack.Klippy(klipper_build, klippy_venv, config, workdir,
                          {"mcu": "atmega2560"}, realtime=True)
    try:
        api = klippy.ready_api()
        printing = KlippyApi(klippy.api_socket)
        rows = []
        dump = threading.Thread(target=_collect_samples,
                                args=(klippy.api_socket, rows), daemon=True)
        dump.start()
        api.call("flowloop/set_active_profile", extruder="extruder",
                 profile=STRONG_PROFILE, working_point=0.5)
        api.gcode("SET_KINEMATIC_POSITION X=100 Y=100 Z=10\n"
                  "SET_HEATER_TEMPERATURE HEATER=extruder TARGET=200")
        # M109 does not wait here, and a move queued on a cold nozzle runs
        # at the temperature cap of then to its end
        stack.wait_until(lambda: api.query("extruder")["temperature"] > 199.0,
                         30)
        now = lambda: api.query("toolhead")["estimated_print_time"]  # noqa: E731
        started = now()
        printing.send("gcode/script", script=MOVES[moves](PRINT_S))
        stack.wait_until(lambda: now() >= started + STEP_AT_S, 30)
        before = now()
        api.call("flowloop/set_active_profile", extruder="extruder",
                 profile=WEAKER, working_point=0.5)
        after = now()
        stack.wait_until(lambda: now() >= started + PRINT_S + 3.0, 60)
        status = api.query("flowrate_limiter")
        api.close()
        printing.close()
        dump.join()
    finally:
        klippy.stop()
    try:
        lines = parsedump(klipper_build, klippy_venv,
                          klipper_build.dictionary("atmega2560"),
                          workdir / "mcu-output")
        clocks, dirs = stepper_steps(lines, "PA4")
        times = clocks[dirs > 0] / CLOCK_HZ
        step_s = _step_time(rows, before)
        slowed_at, steady = _first_slowed_step(times, step_s)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    assert status["reason"] == "grip" or status["slowed_moves"] > 0, status
    assert before - 0.05 <= step_s <= after + 0.05, (before, step_s, after)
    assert slowed_at is not None, "no slowed move after the step"
    what = f"grip_window {grip_window_mm:g} mm" + (
        "" if moves == "5 mm segments" else f", {moves}")
    bench.figure(f"reaction ({what}): steady extruder step interval before"
                 " the step", steady * 1e3, " ms")
    bench.figure(f"reaction time ({what}), step drop in grip to the first"
                 " slowed move executing (realtime klippy)", slowed_at - step_s,
                 " s", goal="<= 1.2 s")


def _collect_samples(api_socket, rows, seconds=PRINT_S + 4.0):
    with KlippyApi(api_socket, timeout=0.2) as dump:
        dump.send("flow_sensor/dump_flow", sensor="sim",
                  response_template={"key": "flow"})
        for msg in dump.messages(seconds):
            if "params" in msg:
                rows.extend(msg["params"].get("data", []))
