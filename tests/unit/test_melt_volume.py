"""flowloop.gcode.melt.volume_on_grid: the plastic through the nozzle at the
grid's times, against each move's trapezoid integrated here on its own."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from flowloop.gcode.bulk_planner import Segments
from flowloop.gcode.melt import _pieces, grid_time, volume_on_grid

# a phase lasts none or at least a nanosecond, as the planner's do
seconds = st.one_of(st.just(0.0), st.floats(1e-9, 2.0))
move = st.tuples(
    st.sampled_from([0.0, 0.0, 0.3, 1e-4]),   # gap before it (mostly none)
    seconds,                                 # accel s
    seconds,                                 # cruise s
    seconds,                                 # decel s
    st.floats(0.0, 20.0),                    # start flow
    st.floats(0.0, 30.0),                    # cruise flow
    st.floats(0.0, 20.0),                    # end flow
    st.booleans())                           # extrudes (else travel)


def batch(moves) -> Segments:
    rows, t = [], 5.0
    for gap, a, c, d, f0, fc, f1, extrudes in moves:
        t += gap
        rows.append((t, a + c + d, fc, a, d, f0, f1, 50.0, 1.0,
                     1.0 if extrudes else 0.0, len(rows)))
        t += a + c + d
    cols = list(zip(*rows))
    return Segments(*[np.array(c, dtype=np.int64 if k == 10 else float)
                      for k, c in enumerate(cols)])


def trapezoid_volume(b: Segments, before: float, t: float) -> float:
    """The volume at t, each move integrated on its own."""
    v = before
    for k in range(len(b)):
        if not b.filament_mm[k] > 0.0:
            continue
        s, a, d = b.start_s[k], b.accel_s[k], b.decel_s[k]
        c = max(b.duration_s[k] - a - d, 0.0)
        f0, fc, f1 = b.start_flow_mm3_s[k], b.flow_mm3_s[k], b.end_flow_mm3_s[k]
        for p0, length, fa, fb in ((s, a, f0, fc), (s + a, c, fc, fc),
                                   (s + a + c, d, fc, f1)):
            u = min(max(t - p0, 0.0), length)
            if length > 0.0:
                v += u * (fa + 0.5 * (fb - fa) / length * u)
    return v


@settings(max_examples=150, deadline=None)
@given(st.lists(move, min_size=1, max_size=8), st.floats(0.0, 1e5),
       st.sampled_from([0.01, 0.037, 0.25]))
def test_the_volume_at_each_time_is_the_moves_integral(moves, before, step):
    b = batch(moves)
    pieces = _pieces(b, before)
    end = float(b.start_s[-1] + b.duration_s[-1])
    # from before the batch (counted as at its start) to after it
    count = int((end + 1.0 - 4.0) / step)
    times = grid_time(4.0, np.arange(count), step)
    got = volume_on_grid(pieces, 4.0, 0, count, step)
    want = np.array([trapezoid_volume(b, before, float(t)) for t in times])
    assert np.allclose(got, want, rtol=1e-12, atol=1e-9 * (1.0 + before)), \
        np.max(np.abs(got - want))
    assert abs(pieces.end_volume_mm3 - trapezoid_volume(b, before, end + 1.0)) \
        <= 1e-9 * (1.0 + before)
