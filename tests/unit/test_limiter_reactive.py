"""The reactive grip rule: it slows at once after a slip, to the flow the
hotend proved it melts, holds inside the hysteresis band, and comes back at
a limited rate."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from flowloop.control.grip_model import DEFAULT_FILAMENT_AREA_MM2 as AREA
from flowloop.control.reactive import (
    MAX_RECOVERY_HOLD_S,
    RECOVERY_HOLD_S,
    ReactiveRule,
    ReactiveSettings,
)
from flowloop.errors import FlowloopError
from flowloop.window import FAULT, JUDGED, TOO_LITTLE_MOTION, Window

SETTINGS = ReactiveSettings(min_grip=0.9, hysteresis=0.03, recovery_per_s=0.2)


def seen(grip, flow_mm3_s, duration_s, flows=(), reason=None):
    """A closed grip window at a mean commanded flow, as the rule gets it."""
    if reason is None:
        reason = TOO_LITTLE_MOTION if grip is None else JUDGED
    commanded_mm = flow_mm3_s * duration_s / AREA
    return Window(0.0, duration_s, commanded_mm,
                  0.0 if grip is None else grip * commanded_mm, grip, reason,
                  commanded_flows=tuple(flows))


def test_a_slip_caps_at_the_measured_flow():
    rule = ReactiveRule(SETTINGS)
    assert rule.on_window(seen(0.95, 20.0, 0.5)) is None
    assert rule.on_window(seen(0.7, 20.0, 0.5)) == pytest.approx(14.0)


def test_a_mixed_window_caps_at_what_melted_while_it_slipped():
    # half the window at 20 mm^3/s melting 12, half at 4: grip 0.67 of a
    # mean 12; grip times the mean (8) would slow far below what melted
    rule = ReactiveRule(SETTINGS)
    window = seen(16.0 / 24.0, 12.0, 0.5, [20.0] * 4 + [4.0] * 4)
    assert rule.on_window(window) == pytest.approx(12.0)
    # and it recovers toward the flow that slipped, the window's peak
    assert rule.slip_flow_mm3_s == pytest.approx(20.0)


def test_a_later_slip_lowers_but_never_raises_the_cap():
    rule = ReactiveRule(SETTINGS)
    rule.on_window(seen(0.7, 20.0, 0.5))
    assert rule.on_window(seen(0.85, 14.0, 0.5)) == pytest.approx(0.85 * 14.0)
    assert rule.on_window(seen(0.89, 20.0, 0.5)) == pytest.approx(0.85 * 14.0)


def test_inside_the_hysteresis_band_the_cap_holds():
    rule = ReactiveRule(SETTINGS)
    rule.on_window(seen(0.7, 20.0, 0.5))
    for _ in range(10):
        assert rule.on_window(seen(0.92, 14.0, 1.0)) == pytest.approx(14.0)


def test_recovery_waits_for_the_hold_then_is_limited_in_rate():
    rule = ReactiveRule(SETTINGS)
    rule.on_window(seen(0.5, 20.0, 0.5))
    # the first RECOVERY_HOLD_S (2 s) of good grip only hold the cap
    assert rule.on_window(seen(1.0, 10.0, 1.0)) == pytest.approx(10.0)
    assert rule.on_window(seen(1.0, 10.0, 1.0)) == pytest.approx(10.0)
    # then +0.2 of the slipped flow (20) per second of good window
    assert rule.on_window(seen(1.0, 10.0, 1.0)) == pytest.approx(14.0)
    # a long window counts for one second only
    assert rule.on_window(seen(1.0, 14.0, 5.0)) == pytest.approx(18.0)
    assert rule.on_window(seen(1.0, 18.0, 0.4)) == pytest.approx(19.6)
    # back at the flow that slipped: released
    assert rule.on_window(seen(1.0, 19.6, 0.1)) is None


def test_a_slip_on_the_way_back_doubles_the_hold():
    rule = ReactiveRule(SETTINGS)
    rule.on_window(seen(0.5, 20.0, 0.5))
    for _ in range(3):
        rule.on_window(seen(1.0, 10.0, 1.0))
    assert rule.cap_mm3_s == pytest.approx(14.0)
    rule.on_window(seen(0.8, 14.0, 0.5))          # slipped again while recovering
    assert rule.cap_mm3_s == pytest.approx(0.8 * 14.0)
    assert rule.hold_s == pytest.approx(2 * RECOVERY_HOLD_S)
    for _ in range(4):                      # 4 s of good grip: still held
        assert rule.on_window(seen(1.0, 11.2, 1.0)) == pytest.approx(11.2)
    assert rule.on_window(seen(1.0, 11.2, 1.0)) == pytest.approx(15.2)


def test_windows_not_judged_change_nothing():
    rule = ReactiveRule(SETTINGS)
    rule.on_window(seen(0.6, 10.0, 0.5))
    assert rule.on_window(seen(None, 10.0, 0.5)) == pytest.approx(6.0)
    # a faulted sensor's windows: whatever they carry, the reason says it
    assert rule.on_window(seen(0.1, 10.0, 0.5, reason=FAULT)) == pytest.approx(6.0)
    for _ in range(10):
        assert rule.on_window(seen(1.0, 10.0, 1.0, reason=FAULT)) \
            == pytest.approx(6.0)
    # nor does a window of no time or no forward flow
    assert rule.on_window(seen(0.1, 10.0, 0.0)) == pytest.approx(6.0)
    assert rule.on_window(seen(0.1, 0.0, 0.5)) == pytest.approx(6.0)


@pytest.mark.parametrize("kw, message", [
    ({"min_grip": 0.0}, "min_grip must be in (0, 1]"),
    ({"min_grip": 1.2}, "min_grip must be in (0, 1]"),
    ({"hysteresis": -0.1}, "hysteresis must be in 0..1"),
    ({"recovery_per_s": 0.0}, "recovery_rate must be above 0"),
])
def test_bad_settings_are_one_line(kw, message):
    with pytest.raises(FlowloopError, match=message.replace("(", r"\(")
                       .replace(")", r"\)")):
        ReactiveSettings(**kw)


windows = st.lists(st.tuples(st.one_of(st.none(), st.floats(0.0, 1.2)),
                             st.floats(0.5, 40.0), st.floats(0.05, 3.0)),
                   max_size=40)


@given(windows, st.floats(0.5, 40.0))
def test_the_cap_never_exceeds_the_flow_that_slipped(seq, _):
    # "never raises a speed": whatever it saw, the rule allows at most what
    # the G-code asked for when it slipped, and never less than nothing.
    rule = ReactiveRule(SETTINGS)
    for grip, flow, dt in seq:
        cap = rule.on_window(seen(grip, flow, dt))
        if cap is not None:
            assert 0 <= cap < rule.slip_flow_mm3_s


@given(windows, st.floats(0.0, 1.2), st.floats(0.0, 1.2), st.floats(0.5, 40.0),
       st.floats(0.05, 3.0))
def test_the_cap_is_monotone_in_grip(seq, g1, g2, flow, dt):
    low, high = sorted((g1, g2))
    caps = []
    for grip in (low, high):
        rule = ReactiveRule(SETTINGS)
        for window in seq:
            rule.on_window(seen(*window))
        cap = rule.on_window(seen(grip, flow, dt))
        caps.append(float("inf") if cap is None else cap)
    assert caps[0] <= caps[1]


@given(windows, st.floats(0.93, 1.2), st.floats(0.5, 40.0))
def test_good_windows_always_release_the_cap(seq, grip, flow):
    rule = ReactiveRule(SETTINGS)
    for window in seq:
        rule.on_window(seen(*window))
    rule.on_window(seen(0.0, 40.0, 1.0))  # the deepest slip there is
    # the longest hold, then back to the slipped flow at +0.2 of it per
    # second: 5 s (one more for rounding)
    for _ in range(int(MAX_RECOVERY_HOLD_S) + 6):
        rule.on_window(seen(grip, flow, 1.0))
    assert rule.cap_mm3_s is None
