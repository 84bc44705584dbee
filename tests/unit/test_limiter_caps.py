"""The cap arithmetic for one G-code move: only extruding moves slow down,
by exactly as much as the cap needs, and nothing else changes."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from flowloop.control.caps import (
    CUT_FROM_S,
    MIN_CAP_MM3_S,
    PIECE_S,
    MoveShape,
    capped_speed,
    check_max_flow,
    lowest_cap,
    move_shape,
    piece_count,
    piece_ends,
)
from flowloop.errors import FlowloopError

AREA = math.pi * 1.75 ** 2 / 4


def test_an_extruding_move_runs_at_the_cap_flow():
    # 0.05 mm of filament per mm of path at 200 mm/s is 24 mm^3/s
    shape = move_shape([0, 0, 0, 0], [30, 40, 0, 2.5])
    assert shape.distance_mm == 50
    assert shape.flow_mm3_s(200, AREA) == pytest.approx(200 * AREA * 0.05)
    speed = capped_speed(shape, 200, 12.0, AREA)
    assert shape.flow_mm3_s(speed, AREA) == pytest.approx(12.0)
    assert speed == pytest.approx(12.0 / (AREA * 0.05))


def test_a_move_under_the_cap_keeps_its_speed():
    shape = move_shape([0, 0, 0, 0], [10, 0, 0, 0.1])
    assert capped_speed(shape, 50, 20.0, AREA) == 50


def test_travel_is_never_touched():
    shape = move_shape([0, 0, 0, 5], [100, 100, 0.2, 5])
    assert capped_speed(shape, 300, 0.5, AREA) == 300


def test_a_retraction_is_never_slowed():
    retract = move_shape([0, 0, 0, 5], [0, 0, 0, 4.2])
    wipe = move_shape([0, 0, 0, 5], [3, 0, 0, 4.5])
    assert capped_speed(retract, 45, 0.5, AREA) == 45
    assert capped_speed(wipe, 150, 0.5, AREA) == 150


def test_an_extrude_only_move_is_capped_on_e_speed():
    shape = move_shape([0, 0, 0, 0], [0, 0, 0, 10])
    assert shape.distance_mm == 0
    speed = capped_speed(shape, 20, 9.0, AREA)
    assert speed == pytest.approx(9.0 / AREA)
    assert shape.duration_s(speed) == pytest.approx(10 / speed)


def test_an_arc_split_into_segments_is_capped_segment_by_segment():
    # G2 reaches the transform as short chords: each one gets the same speed
    r, n = 10.0, 16
    points = [[r * math.cos(a), r * math.sin(a), 0, 0.04 * r * a]
              for a in (2 * math.pi * i / n for i in range(n + 1))]
    speeds = [capped_speed(move_shape(p0, p1), 150, 8.0, AREA)
              for p0, p1 in zip(points, points[1:])]
    chord = move_shape(points[0], points[1])
    assert speeds == pytest.approx([speeds[0]] * n)
    assert chord.flow_mm3_s(speeds[0], AREA) == pytest.approx(8.0)


def test_the_floor_holds_but_never_raises_a_speed():
    shape = move_shape([0, 0, 0, 0], [10, 0, 0, 1])
    assert capped_speed(shape, 100, 1.0, AREA, floor_mm_s=30) == 30
    assert capped_speed(shape, 20, 1.0, AREA, floor_mm_s=30) == 20


def test_a_zero_cap_slows_to_the_least_cap_but_never_stops_a_move():
    # a cold hotend melts nothing: the move crawls, klippy is not asked for 0
    shape = move_shape([0, 0, 0, 0], [10, 0, 0, 1])
    speed = capped_speed(shape, 100, 0.0, AREA)
    assert speed > 0
    assert shape.flow_mm3_s(speed, AREA) == pytest.approx(MIN_CAP_MM3_S)


moves = st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(0, 1),
                  st.floats(-3, 3))


@given(moves, st.floats(0.1, 500), st.floats(0, 100), st.floats(0, 500))
def test_a_cap_never_raises_a_speed(end, speed, cap, floor):
    shape = move_shape([0, 0, 0, 0], list(end))
    new = capped_speed(shape, speed, cap, AREA, floor_mm_s=floor)
    assert 0 < new <= speed
    if floor == 0:
        assert shape.flow_mm3_s(new, AREA) <= max(cap, MIN_CAP_MM3_S) * (1 + 1e-9)


def test_the_lowest_cap_wins_and_says_which():
    assert lowest_cap(max_flow=20.0, temperature=11.5, grip=None) == (11.5,
                                                                       "temperature")
    assert lowest_cap() == (None, "none")
    assert lowest_cap(model=0.0).cap_mm3_s == MIN_CAP_MM3_S
    with pytest.raises(FlowloopError, match="unknown cap 'speed'"):
        lowest_cap(speed=3.0)


@pytest.mark.parametrize("bad", [0, -1, "abc", float("nan"), float("inf"), None])
def test_a_bad_max_flow_is_one_line(bad):
    with pytest.raises(FlowloopError) as e:
        check_max_flow(bad, "MAX_FLOW")
    assert str(e.value).startswith("MAX_FLOW must be") and "\n" not in str(e.value)


def test_move_shape_ignores_extra_axes():
    assert move_shape([0, 0, 0, 0, 9], [3, 4, 0, 1, 2]) == MoveShape(5.0, 1.0)


# --- a long move queued in pieces (on a printer) ----------------------------

def test_a_move_longer_than_klippy_s_buffer_is_cut_into_pieces_of_half_of_it():
    # 120 mm at 40 mm/s: 3 s, six pieces of 0.5 s
    shape = move_shape([40, 100, 0, 0], [160, 100, 0, 8.7])
    assert piece_count(shape, 40.0) == math.ceil(3.0 / PIECE_S) == 6
    # 1.2 s: three pieces of 0.4 s, none longer than PIECE_S
    assert piece_count(shape, 100.0) == 3


def test_a_move_within_the_buffer_travel_and_a_retraction_stay_whole():
    line = move_shape([0, 0, 0, 0], [40, 0, 0, 2.0])
    assert piece_count(line, 40.0 / CUT_FROM_S) == 1        # exactly 1 s
    # just over: 1.01 s in three pieces, none longer than PIECE_S
    assert piece_count(line, 40.0 / CUT_FROM_S * 0.99) == 3
    assert piece_count(move_shape([0, 0, 0, 0], [200, 0, 0, 0]), 10.0) == 1
    assert piece_count(move_shape([0, 0, 0, 5], [200, 0, 0, 4]), 10.0) == 1


def test_an_extrude_only_move_is_cut_on_its_e_time():
    # 20 mm of filament at 5 mm/s: 4 s
    assert piece_count(move_shape([0, 0, 0, 0], [0, 0, 0, 20]), 5.0) == 8


@given(st.lists(st.floats(-500, 500), min_size=4, max_size=6),
       st.lists(st.floats(-500, 500), min_size=4, max_size=6),
       st.integers(1, 40))
def test_the_pieces_add_up_to_the_move_exactly(start, end, count):
    n = min(len(start), len(end))
    start, end = start[:n], end[:n]
    ends = list(piece_ends(start, end, count))
    assert len(ends) == count
    assert ends[-1] == list(end)  # the G-code's own position, not a sum
    prev = start
    for p in ends:
        # each piece on the line from start to end, an equal share of it
        for a, b, s0, e0 in zip(prev, p, start, end):
            assert b - a == pytest.approx((e0 - s0) / count, abs=1e-9)
        prev = p
