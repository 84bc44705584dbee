"""The planner's moves against Klipper's own toolhead code.

Klipper's `Move`, `LookAheadQueue` (klippy/toolhead.py) and the extruder's
`check_move` / `calc_junction` (klippy/kinematics/extruder.py) are loaded from
the Klipper checkout (KLIPPER_PATH, read only; their host imports stubbed) and
driven the way `ToolHead.move` drives them. Every move must get the same
accel, cruise and decel times from both, from the reference planner and
from the bulk one (bulk_planner). Skipped without a checkout.
"""

from __future__ import annotations

import importlib.util
import io
import math
import sys
import types
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from devtools import stack
from flowloop.gcode import bulk_planner
from flowloop.gcode.reference_planner import PrinterLimits, Segment, plan_text

pytestmark = pytest.mark.unit

DATA = Path(__file__).resolve().parents[1] / "data" / "gcode"


def load_klipper(name: str, relative: str, stub_names):
    saved = {n: sys.modules.get(n) for n in stub_names}
    sys.modules.update({n: types.ModuleType(n) for n in stub_names})
    try:
        spec = importlib.util.spec_from_file_location(
            name, stack.klipper_path() / "klippy" / relative)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    finally:
        for n, old in saved.items():
            if old is None:
                sys.modules.pop(n, None)
            else:
                sys.modules[n] = old


@pytest.fixture(scope="module")
def klipper():
    reason = stack.missing_klipper_reason()
    if reason:
        pytest.skip(f"no Klipper checkout at {stack.klipper_path()}")
    toolhead = load_klipper("klipper_toolhead", "toolhead.py",
                            ("mcu", "chelper", "kinematics", "kinematics.extruder"))
    extruder = load_klipper("klipper_extruder", "kinematics/extruder.py",
                            ("stepper", "chelper"))
    return toolhead, extruder


class KlipperExtruder:
    """What PrinterExtruder's check_move and calc_junction read of self."""

    def __init__(self, extruder_module, limits: PrinterLimits):
        self.module = extruder_module
        self.heater = types.SimpleNamespace(can_extrude=True)
        self.nozzle_diameter = limits.nozzle_diameter
        self.filament_area = limits.filament_area_mm2
        self.max_extrude_ratio = (limits.derived("max_extrude_cross_section")
                                  / self.filament_area)
        self.max_e_velocity = limits.derived("max_extrude_only_velocity")
        self.max_e_accel = limits.derived("max_extrude_only_accel")
        self.max_e_dist = limits.max_extrude_only_distance
        self.instant_corner_v = limits.instantaneous_corner_velocity

    def check_move(self, move, index):
        self.module.PrinterExtruder.check_move(self, move, index)

    def calc_junction(self, prev_move, move, index):
        return self.module.PrinterExtruder.calc_junction(self, prev_move, move, index)


def klipper_moves(klipper, limits: PrinterLimits, moves):
    """(accel_t, cruise_t, decel_t, cruise_v) of each move, as klippy plans it;
    moves are (x, y, e, speed) in absolute machine coordinates."""
    toolhead_module, extruder_module = klipper
    toolhead = types.SimpleNamespace(
        max_accel=limits.max_accel, max_velocity=limits.max_velocity,
        junction_deviation=limits.square_corner_velocity ** 2
        * (math.sqrt(2.0) - 1.0) / limits.max_accel,
        mcr_pseudo_accel=limits.max_accel * (1.0 - limits.minimum_cruise_ratio),
        extra_axes=[KlipperExtruder(extruder_module, limits)])
    lookahead = toolhead_module.LookAheadQueue()
    lookahead.set_flush_time(toolhead_module.BUFFER_TIME_HIGH)
    out = []
    pos = [0.0, 0.0, 0.0, 0.0]

    def process(flushed):
        out.extend((m.accel_t, m.cruise_t, m.decel_t, m.cruise_v) for m in flushed)

    for x, y, e, speed in moves:
        move = toolhead_module.Move(toolhead, pos, [x, y, 0.0, e], speed)
        if not move.move_d:
            continue
        if move.axes_d[3]:
            toolhead.extra_axes[0].check_move(move, 3)
        pos = list(move.end_pos)
        if lookahead.add_move(move):
            process(lookahead.flush(lazy=True))
    process(lookahead.flush())
    return out


def planner_moves(limits: PrinterLimits, moves, in_bulk: bool = False):
    text = "\n".join(["G90", "M82"] + [f"G1 X{x!r} Y{y!r} E{e!r} F{speed * 60!r}"
                                       for x, y, e, speed in moves])
    events = bulk_planner.plan_file(io.BytesIO(text.encode()), limits) if in_bulk \
        else plan_text(text, limits)
    return [(s.accel_s, s.duration_s - s.accel_s - s.decel_s, s.decel_s, s.speed_mm_s)
            for s in events if isinstance(s, Segment)]


def assert_same_plan(klipper, limits, moves):
    theirs = klipper_moves(klipper, limits, moves)
    for in_bulk in (False, True):       # the reference and the bulk planner
        ours = planner_moves(limits, moves, in_bulk)
        assert len(ours) == len(theirs)
        for i, (a, b) in enumerate(zip(ours, theirs)):
            assert a == pytest.approx(b, rel=1e-9, abs=1e-12), f"move {i}"


def excerpt_moves(name: str):
    """XY moves of a real slicer excerpt, E made cumulative across G92."""
    moves, x, y, e_base, e, feed = [], 0.0, 0.0, 0.0, 0.0, 25.0
    for line in (DATA / name).read_text().splitlines():
        code = line.split(";")[0].split()
        if code[:1] == ["G92"]:
            e_base = e - float(code[1][1:])
        if code[:1] != ["G1"]:
            continue
        words = {w[0]: float(w[1:]) for w in code[1:]}
        if "Z" in words:
            continue
        x, y = words.get("X", x), words.get("Y", y)
        e = e_base + words["E"] if "E" in words else e
        feed = words.get("F", feed * 60) / 60
        moves.append((x, y, e, feed))
    return moves


@pytest.mark.parametrize("limits", [
    PrinterLimits(),
    PrinterLimits(max_velocity=500, max_accel=20000, minimum_cruise_ratio=0.0,
                  square_corner_velocity=8),
    PrinterLimits(max_velocity=150, max_accel=800, minimum_cruise_ratio=0.8,
                  square_corner_velocity=2, instantaneous_corner_velocity=3),
])
@pytest.mark.parametrize("name", ["block_layers_1_2.gcode", "box_bridge_layer.gcode"])
def test_a_real_file_is_planned_as_klipper_plans_it(klipper, limits, name):
    moves = excerpt_moves(name)
    assert len(moves) > 500
    assert_same_plan(klipper, limits, moves)


position = st.floats(min_value=-50, max_value=50, allow_nan=False).map(
    lambda v: round(v, 3))


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(position, position,
                          st.floats(min_value=-1.0, max_value=1.0).map(
                              lambda v: round(v, 4)),
                          st.sampled_from([5.0, 30.0, 100.0, 400.0])),
                min_size=1, max_size=60),
       st.sampled_from([0.0, 0.5, 0.9]))
def test_any_moves_are_planned_as_klipper_plans_them(klipper, steps, mcr):
    limits = PrinterLimits(max_velocity=300, max_accel=3000,
                           minimum_cruise_ratio=mcr, max_extrude_cross_section=50.0,
                           max_extrude_only_distance=100)
    moves, e = [], 0.0
    for x, y, de, speed in steps:
        e = round(e + de, 4)
        moves.append((x, y, e, speed))
    assert_same_plan(klipper, limits, moves)
