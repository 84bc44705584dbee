"""[autotemp] in batch mode: a real slicer excerpt, annotated, printed on the
simulated sensor whose twin is a hotend (tests/klippy/autotemp.cfg), with a
weak profile whose peak need lies above its max_temp_c."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from devtools import stack
from devtools.demo_autotemp import PROFILE, annotated, print_with_autotemp
from flowloop.control.autotemp import TemperaturePlan, TempLimits
from flowloop.gcode.bulk_planner import plan_batches
from flowloop.gcode.melt import CELL_S, MELT_TIME_S, Cells, melt_events
from flowloop.gcode.reference_planner import Segment, limits_from_config, plan_file
from flowloop.host.klipper_config import read_config
from flowloop.material.profile import profile_from_dict, profile_line
from tests.klippy.flowrate_limiter_steps import stepper_steps
from tests.klippy.test_flowrate_limiter import (
    AREA,
    CLOCK_HZ,
    GCODE,
    MM_PER_STEP,
    gcode_extrusion,
    run,
)
from tests.klippy.test_harness import check_host_status

LIMITS = TempLimits.of(profile_from_dict(PROFILE), 260.0)   # heater max_temp
LINE = profile_line(profile_from_dict(PROFILE), 0.5)


@pytest.fixture(scope="module")
def runs(host, klipper_build, klippy_venv):
    text = annotated(GCODE)
    return (print_with_autotemp(1, klipper_build, klippy_venv, text=text),
            print_with_autotemp(0, klipper_build, klippy_venv, text=text))


def test_no_unknown_command_and_the_annotations_are_the_source(runs):
    (on, _, log_on), (_, _, log_off) = runs
    assert "Unknown command" not in log_on + log_off
    announced = [r for r in on if any(x.startswith("AUTOTEMP_FLOW")
                                      for x in r["lines"])]
    assert len(announced) >= 5
    assert all(r["autotemp"]["source"] == "annotation" for r in announced)
    assert on[-1]["autotemp"]["profile"] == "weak"


def test_targets_follow_the_annotations_within_the_clamps(runs):
    (on, _, _), _ = runs
    statuses = [r["autotemp"] for r in on if r["autotemp"]["target"] is not None]
    targets = [s["target"] for s in statuses]
    # the heater is driven by autotemp's target
    assert [r["heater_target"] for r in on if r["autotemp"]["target"]
            is not None][10:] == targets[10:]
    # never outside the profile's bounds (the heater's 260 C is above them)
    assert min(targets) >= LIMITS.min_temp_c and max(targets) <= 225.0
    # the file's peak (6.7 mm^3/s) needs more than 225 C: clamped, counted
    assert LINE.temp_c(6.7) > 225.0
    assert max(targets) == 225.0
    assert statuses[-1]["capped_windows"] > 0
    # the second layer's announcements are low-flow stretches: it cools
    assert min(targets[len(targets) // 2:]) < 215.0
    # each planned flow comes with a target at least its need
    plan = TemperaturePlan(LINE, LIMITS)
    for s in statuses:
        if s["planned_flow"]:
            assert s["target"] >= plan.need_c(s["planned_flow"]) - 0.01


def test_the_slicers_m104_is_overridden(runs):
    (on, _, log_on), (off, _, _) = runs
    # line 346 of the excerpt: M104 S215 in layer 2
    assert "M104 S215 overridden" in log_on
    assert 215.0 in [r["heater_target"] for r in off]
    after = [r for r in on if any(x.startswith("M104 S215") for x in r["lines"])]
    assert after and after[0]["autotemp"]["source"] == "annotation"


def test_the_hotend_keeps_up_where_the_files_temperatures_do_not(runs):
    (_, moved_on, _), (_, moved_off, _) = runs
    commanded = gcode_extrusion(GCODE)
    lost_on, lost_off = commanded - moved_on, commanded - moved_off
    print(f"filament lost: autotemp {lost_on:.1f} mm, the file's own"
          f" temperatures {lost_off:.1f} mm of {commanded:.1f}")
    # at the file's 200/215 C the weak hotend slips on the infill
    assert lost_off > 0.05 * commanded
    # autotemp loses what the clamp at 225 C and the first rise cost
    assert lost_on < 0.5 * lost_off


def test_a_file_without_annotations_is_followed_reactively(klipper_build,
                                                           klippy_venv):
    text = GCODE.read_text()
    records, moved, log = print_with_autotemp(1, klipper_build, klippy_venv,
                                              text=text)
    _, moved_off, _ = print_with_autotemp(0, klipper_build, klippy_venv,
                                          text=text)
    assert "Unknown command" not in log
    statuses = [r["autotemp"] for r in records]
    assert {s["source"] for s in statuses} - {None} == {"lookahead"}
    assert "reactive" in statuses[-1]["why"] or statuses[-1]["source"] is None
    targets = [s["target"] for s in statuses if s["target"] is not None]
    assert targets and max(targets) <= 225.0
    # the infill's flow raises the heater while the moves run (the records
    # are taken after each chunk's M400, when nothing is queued and the
    # target has fallen back: no window is known there): it slips less
    commanded = gcode_extrusion(GCODE)
    lost_on, lost_off = commanded - moved, commanded - moved_off
    print(f"filament lost: reactive autotemp {lost_on:.1f} mm, the file's own"
          f" temperatures {lost_off:.1f} mm of {commanded:.1f}")
    assert lost_on < 0.8 * lost_off


def test_the_status_says_which_host_it_runs_on(host, klipper_build, klippy_venv,
                                               short_tmp):
    """[autotemp] status 'host': the facts its timing rests on (Klipper or
    Kalico, how far ahead the toolhead reads G-code, the heater's control),
    the same record the flowrate limiter reports."""
    check_host_status(
        host, klipper_build, klippy_venv, short_tmp,
        f"[include {stack.PROJECT / 'tests' / 'klippy' / 'autotemp_plain.cfg'}]\n",
        "autotemp")


def test_a_start_macro_waits_at_its_temperature_then_the_plan_takes_over(
        tmp_path, klipper_build, klippy_venv):
    """docs/autotemp.md, "Your start G-code": a PRINT_START macro heats and
    waits inside Klipper, then autotemp sets the heater to its plan as the
    first moves run."""
    src = tmp_path / "macro_start.gcode"
    body = GCODE.read_text().split("M82 ; use absolute distances for extrusion\n",
                                   1)[1]
    src.write_text("PRINT_START EXTRUDER=200 BED=60\nG90\nM82\n" + body)
    config = stack.PROJECT / "tests" / "klippy" / "autotemp_print_start.cfg"
    records, _, log = print_with_autotemp(1, klipper_build, klippy_venv,
                                          text=annotated(src), config=config)
    assert "Unknown command" not in log
    start = next(i for i, r in enumerate(records)
                 if any(x.startswith("PRINT_START") for x in r["lines"]))
    # within the first chunks of moves after the macro autotemp drives the
    # heater at the plan's need for the first layer's 6.6 mm^3/s (226 C,
    # clamped at the profile's 225 C), not at the macro's 200 C
    # (Kalico sets it at its step generators' next call: a chunk later)
    after = [r for r in records[start:start + 8]
             if r["autotemp"]["target"] is not None
             and r["heater_target"] == r["autotemp"]["target"]]
    assert after, "autotemp drove the heater in none of the first chunks"
    assert after[0]["autotemp"]["source"] == "annotation"
    assert after[0]["heater_target"] >= 220.0


HERE = Path(__file__).resolve().parent
SHORT_SEGMENTS = HERE.parent / "data" / "gcode" / "curves_0.6mm_layers_1_8.gcode"


def _move_plastic(s: Segment, u: float) -> float:
    """Plastic a move has left u s after its start: its flow trapezoid
    integrated (none for a move that adds no plastic)."""
    if s.filament_mm <= 0.0:
        return 0.0
    a, d, top = s.accel_s, s.decel_s, s.flow_mm3_s
    c = max(0.0, s.duration_s - a - d)
    u = min(max(u, 0.0), s.duration_s)
    ua, uc, ud = min(u, a), min(max(u - a, 0.0), c), max(u - a - c, 0.0)
    rise = (top - s.start_flow_mm3_s) * ua * ua / (2 * a) if a > 0 else 0.0
    fall = (top - s.end_flow_mm3_s) * ud * ud / (2 * d) if d > 0 else 0.0
    return s.start_flow_mm3_s * ua + rise + top * (uc + ud) - fall


def _planned_plastic(segs, times: np.ndarray) -> np.ndarray:
    """Plastic left by each of times (increasing)."""
    start = np.array([s.start_s for s in segs])
    before = np.concatenate(([0.0], np.cumsum([_move_plastic(s, s.duration_s)
                                               for s in segs])))
    k = np.searchsorted(start, times, "right") - 1
    return np.array([before[j] + _move_plastic(segs[j], t - segs[j].start_s)
                     if j >= 0 else 0.0 for t, j in zip(times.tolist(), k.tolist())])


def test_the_planners_half_second_mean_is_the_one_klippers_steps_give(
        klipper_build, klippy_venv, tmp_path):
    """The flow to melt the annotation announces (the planner's trapezoids,
    averaged over MELT_TIME_S) against the same mean rebuilt from the steps
    Klipper sends the extruder, on the file of short segments and bursts."""
    config = HERE / "autotemp_steps.cfg"
    _, lines = run(klipper_build, klippy_venv, tmp_path, "G28\n",
                   SHORT_SEGMENTS, config)
    clocks, dirs = stepper_steps(lines, "PA4")
    step_s = clocks / CLOCK_HZ
    # plastic: filament beyond the furthest it has been (an unretraction
    # refills the nozzle, as the planner counts it)
    plastic = np.maximum.accumulate(np.cumsum(dirs) * MM_PER_STEP) * AREA

    limits = limits_from_config(read_config(config))
    # the file as klippy printed it (run() wrote it there)
    with open(tmp_path / "print.gcode", "rb") as f:
        segs = [e for e in plan_file(f, limits) if isinstance(e, Segment)]
    # Klipper's print time starts elsewhere: the offset that puts the
    # planner's plastic on the steps' at each tenth of the print
    share = np.arange(1, 10) / 10
    at_steps = np.interp(share * plastic[-1], plastic, step_s)
    grid = np.arange(0.0, segs[-1].start_s + segs[-1].duration_s, 0.001)
    planned_volume = _planned_plastic(segs, grid)
    offsets = at_steps - np.interp(share * planned_volume[-1], planned_volume, grid)
    offset = float(np.median(offsets))
    with open(tmp_path / "print.gcode", "rb") as f:
        cells = [e for e in melt_events(plan_batches(f, limits))
                 if isinstance(e, Cells)]
    start = np.concatenate([c.start_s for c in cells])
    planned = np.concatenate([c.flow_mm3_s for c in cells])

    def steps_mean(t):
        h = MELT_TIME_S / 2
        at = np.searchsorted(step_s, [t + offset + h, t + offset - h], "right") - 1
        v = np.where(at >= 0, plastic[np.maximum(at, 0)], 0.0)
        return (v[0] - v[1]) / MELT_TIME_S

    stepped = np.maximum(steps_mean(start), steps_mean(start + CELL_S))
    window = np.floor(start).astype(int)           # 1 s windows of print time
    peaks_planned = np.zeros(window[-1] + 1)
    peaks_stepped = np.zeros(window[-1] + 1)
    np.maximum.at(peaks_planned, window, planned)
    np.maximum.at(peaks_stepped, window, stepped)
    flowing = peaks_planned > 0.5
    difference = np.abs(peaks_planned - peaks_stepped)[flowing]
    # the steps' short bursts: the plastic of the print's highest 20 ms
    edges = np.arange(step_s[0], step_s[-1], 0.02)
    burst = np.diff(plastic[np.searchsorted(step_s, edges, "right") - 1]).max()
    print(f"1 s windows {flowing.sum()}: planner's 0.5 s mean peak"
          f" {peaks_planned.max():.2f}, from Klipper's steps {peaks_stepped.max():.2f}"
          f" mm^3/s; per window |difference| median {np.median(difference):.3f},"
          f" max {difference.max():.3f}; the steps' highest 20 ms"
          f" {burst / 0.02:.1f} mm^3/s;"
          f" time offset {offset:.3f} s, spread {np.ptp(offsets) * 1000:.1f} ms")
    # one timeline: the planner's print time is Klipper's, to a millisecond
    assert np.ptp(offsets) < 0.001
    assert flowing.sum() > 100
    assert peaks_stepped.max() == pytest.approx(peaks_planned.max(), rel=0.01)
    # to a step's volume over the mean (0.012 mm^3/s), far below FLOW's 0.1
    assert difference.max() < 0.03
