"""flowloop.gcode.melt's grid without its times: grid_search against
np.searchsorted on the grid's times, the cells' places (Cells.search) and
each grid point's piece (_segment_of_each against np.repeat)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from flowloop.gcode.melt import (
    CELL_S,
    Cells,
    _segment_of_each,
    grid_search,
    grid_time,
    melt_events,
)
from flowloop.gcode.reference_planner import Segment

origins = st.one_of(st.just(0.0), st.floats(0.0, 2e5))
cells = st.sampled_from([CELL_S, 0.001, 0.037, 0.25])


@settings(max_examples=200, deadline=None)
@given(origins, st.integers(0, 5_000_000), st.integers(0, 300), cells,
       st.lists(st.floats(-5.0, 400.0), max_size=20), st.booleans(),
       st.sampled_from(["left", "right"]))
def test_grid_search_is_searchsorted_on_the_grid(origin, first, count, cell,
                                                 offsets, on_points, side):
    times = grid_time(origin, np.arange(first, first + count), cell)
    base = grid_time(origin, first, cell)
    keys = np.array([base + o * cell for o in offsets])
    if on_points and count:
        # keys on the grid's own times: where left and right differ
        keys = np.concatenate((keys, times[::7]))
    got = grid_search(keys, origin, first, first + count, cell, side)
    assert got.tolist() == np.searchsorted(times, keys, side).tolist()


@settings(max_examples=100, deadline=None)
@given(st.lists(st.integers(0, 6), min_size=1, max_size=60))
def test_each_points_segment_is_np_repeat(counts):
    counts = np.array(counts)
    seg_first = np.concatenate(([0], np.cumsum(counts)[:-1]))
    got = _segment_of_each(seg_first, counts, int(counts.sum()))
    assert got.tolist() == np.repeat(np.arange(len(counts)), counts).tolist()


def test_cells_find_places_as_their_start_times_do():
    moves = [Segment(start_s=t, duration_s=0.3, flow_mm3_s=f, accel_s=0.05,
                     decel_s=0.05, start_flow_mm3_s=0.0, end_flow_mm3_s=0.0,
                     speed_mm_s=50.0, distance_mm=15.0, filament_mm=1.0,
                     offset=k)
             for k, (t, f) in enumerate([(0.0, 5.0), (0.3, 9.0), (0.6, 2.0),
                                         (1.7, 7.0)])]
    found = [e for e in melt_events(moves) if isinstance(e, Cells)]
    assert found
    for c in found:
        start = c.start_s
        assert len(start) == len(c.flow_mm3_s) and start[0] == c.begin_s
        keys = np.concatenate((start[::3], start[::5] + 1e-3, [-1.0, 1e3]))
        for side in ("left", "right"):
            assert c.search(keys, side).tolist() == \
                np.searchsorted(start, keys, side).tolist()
