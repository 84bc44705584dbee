"""Grip windows: judged, not judged across retractions or with too little motion."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from flowloop.calibrate.flow_sensor import (
    ReversedSensor,
    fit_calibration,
    parse_speeds,
    rotation_distance_correction,
)
from flowloop.errors import FlowloopError
from flowloop.sensor.grip import (
    SLIP_CHECK_MM,
    SLIP_GRIP,
    SLIP_STEP_MM,
    GripEstimator,
    SampleRate,
    positions_at,
    trapq_positions,
    window_flows,
)


def _run(est, t, measured, commanded):
    return est.add(list(t), list(measured), list(commanded))


def test_a_feeder_that_keeps_up_reads_grip_one_through_the_calibration():
    t = np.arange(0, 2, 0.001)
    commanded = 3.0 * t                       # 3 mm/s of filament
    sensor = 0.97 * commanded                 # sensor reads 3 % short
    est = GripEstimator(window_mm=1.25, calibration=0.97)
    windows = _run(est, t, sensor, commanded)
    assert len(windows) == 4
    assert all(w.reason == "judged" for w in windows)
    assert est.grip == pytest.approx(1.0, abs=1e-3)


@given(st.floats(0.3, 1.0), st.floats(0.5, 10.0), st.floats(0.8, 1.2))
def test_grip_is_the_measured_share_of_commanded_filament(grip, speed, cal):
    t = np.arange(0, 3.0, 0.002)
    commanded = speed * t
    est = GripEstimator(window_mm=1.0, calibration=cal)
    windows = _run(est, t, grip * cal * commanded, commanded)
    judged = [w for w in windows if w.reason == "judged"]
    assert judged
    for w in judged:
        assert w.grip == pytest.approx(grip, rel=1e-6)
        if grip > SLIP_GRIP + 1e-3:
            assert w.commanded_mm >= 1.0
        elif grip < SLIP_GRIP - 1e-3:   # closes once SLIP_CHECK_MM shows it
            assert w.commanded_mm <= SLIP_CHECK_MM + 2 * speed * 0.002


@given(st.floats(0.5, 3.0), st.floats(0.3, 0.8))
def test_a_slip_closes_the_window_as_soon_as_it_shows(step_at_s, grip):
    # 3 mm/s of filament (7.2 mm^3/s), the feeder slipping from step_at_s on
    t = np.arange(0, 4.0, 0.004)
    commanded = 3.0 * t
    measured = np.where(t < step_at_s, commanded,
                        3.0 * step_at_s + grip * 3.0 * (t - step_at_s))
    windows = _run(GripEstimator(window_mm=1.25), t, measured, commanded)
    # the first window the limiter counts as a slip (below its default
    # min_grip, 0.9): one closed whole holds at most half a stretch of good
    # grip before the stretch that read below SLIP_GRIP
    first = next(w for w in windows if w.grip <= 0.9)
    # as soon as the checked stretch reads below SLIP_GRIP, give or take a
    # step of filament, and half a stretch if a window closed in between (a
    # whole window took up to two windows, 1.25 mm each)
    shows_mm = SLIP_CHECK_MM * min(1.0, (1.0 - SLIP_GRIP) / (1.0 - grip))
    assert all(w.reason == "judged" for w in windows)
    assert first.end_time - step_at_s <= (
        shows_mm + SLIP_CHECK_MM / 2 + SLIP_STEP_MM) / 3.0 + 0.01
    # the windows before it did not show the slip; they tile the path
    assert all(w.grip > 0.9 for w in windows[:windows.index(first)])
    assert all(a.end_time == b.start_time for a, b in zip(windows, windows[1:]))
    assert sum(w.commanded_mm for w in windows) == pytest.approx(
        commanded[-1] - commanded[0], abs=SLIP_CHECK_MM + 1.25)


def test_no_slip_is_looked_for_while_the_filament_goes_back_in():
    # 3 mm/s, a 2 mm retraction at 1 s, an unretract at 30 mm/s that the
    # sensor sees slip (half of it), then printing at 3 mm/s that slips too
    t = np.arange(0, 3.0, 0.002)
    back = np.clip((t - 1.0) * 30.0, 0.0, 2.0)          # retraction
    refill = np.clip((t - 1.2) * 30.0, 0.0, 2.0)        # the unretract
    commanded = 3.0 * np.minimum(t, 1.0) - back + refill \
        + 3.0 * np.clip(t - 1.5, 0.0, None)
    measured = commanded - 0.5 * refill - 0.5 * 3.0 * np.clip(t - 1.5, 0.0, None)
    # (windows long enough to hold the unretract whole: a window that fills
    # judges it, as before)
    windows = GripEstimator(window_mm=2.5).add(t, measured, commanded)
    judged = [w for w in windows if w.grip is not None]
    # no stretch of the unretract alone closes a window: the one that holds
    # it ends where the filament is back (at 1.267 s)
    assert judged[1].start_time == pytest.approx(1.067, abs=0.005)
    assert judged[2].start_time == pytest.approx(1.267, abs=0.01)
    # printing again, the slip shows as soon as a stretch reads it (the
    # commanded filament grows 3 mm/s)
    slipped = judged[2]
    assert slipped.grip == pytest.approx(0.5)
    assert slipped.end_time < 1.5 + (SLIP_CHECK_MM + SLIP_STEP_MM) / 3.0 + 0.01


def test_a_feeder_that_keeps_up_never_closes_a_window_early():
    # noise, and pressure advance's few tens of micrometres of lag at speed
    # changes, do not read as a slip over SLIP_CHECK_MM
    t = np.arange(0, 6.0, 0.004)
    commanded = 3.0 * t + 0.04 * (np.sin(3 * t) > 0)
    rng = np.random.default_rng(1)
    measured = 3.0 * t + rng.normal(0.0, 0.34 / 103.0, len(t))
    windows = GripEstimator(window_mm=1.25).add(t, measured, commanded,
                                                nominal_mm=3.0 * t)
    assert len(windows) == 14
    assert all(w.reason == "judged" and w.commanded_mm >= 1.25 for w in windows)
    assert min(w.grip for w in windows) > 0.95


def test_grip_is_not_judged_across_a_retraction():
    t = np.arange(0, 1.0, 0.001)
    commanded = np.where(t < 0.3, 5 * t, 5 * 0.3 - 0.8)   # a 0.8 mm retraction
    commanded = np.where(t > 0.5, commanded + 8 * (t - 0.5), commanded)
    est = GripEstimator(window_mm=1.25)
    windows = _run(est, t, commanded, commanded)
    reasons = [w.reason for w in windows]
    assert "retraction" in reasons
    retraction = windows[reasons.index("retraction")]
    assert retraction.grip is None
    # judging resumes once the filament moves forward for a whole window again
    assert reasons[-1] == "judged"


def test_pressure_advance_wobble_below_the_tolerance_is_not_a_retraction():
    t = np.arange(0, 1.0, 0.001)
    commanded = 3 * t - 0.01 * np.sin(40 * t) ** 2
    windows = _run(GripEstimator(), t, commanded, commanded)
    assert windows and all(w.reason == "judged" for w in windows)


def test_too_little_motion_is_not_judged():
    t = np.arange(0, 5.0, 0.01)
    commanded = 0.1 * t                       # 0.1 mm/s: 1.25 mm takes 12.5 s
    est = GripEstimator(window_mm=1.25, max_window_s=2.0)
    windows = _run(est, t, 0.2 * commanded, commanded)
    assert windows and all(w.reason == "too_little_motion" for w in windows)
    assert est.grip is None


def test_a_sensor_that_does_not_move_is_stuck_not_grip_zero():
    t = np.arange(0, 1.0, 0.001)
    est = GripEstimator()
    windows = _run(est, t, np.zeros_like(t), 4 * t)
    assert windows and all(w.reason == "stuck" and w.grip is None for w in windows)


def test_flows_are_volumetric():
    t = np.arange(0, 1.0, 0.001)
    est = GripEstimator(filament_area_mm2=2.0)
    _run(est, t, 2.5 * t, 5 * t)
    measured, commanded = est.flows()
    assert commanded == pytest.approx(10.0, rel=1e-3)
    assert measured == pytest.approx(5.0, rel=1e-3)
    assert est.filament_position == pytest.approx(2.5 * t[-1])


def test_sample_rate_counts_good_samples_over_the_last_second():
    rate = SampleRate()
    assert rate.per_second() == 0.0
    t = np.arange(0, 3.0, 0.001)
    for start in range(0, len(t), 12):      # batches as the MCU sends them
        rate.add(t[start:start + 12])
    assert rate.total == len(t)
    assert rate.per_second() == pytest.approx(1000, rel=1e-6)
    slow = np.arange(3.0, 5.0, 0.004)       # three of four samples bad
    for start in range(0, len(slow), 3):
        rate.add(slow[start:start + 3])
    assert rate.per_second() == pytest.approx(250, rel=1e-6)
    rate.add([])
    assert rate.total == len(t) + len(slow)


def test_bad_settings_are_refused():
    with pytest.raises(FlowloopError, match="grip_window"):
        GripEstimator(window_mm=0)
    with pytest.raises(FlowloopError, match="calibration"):
        GripEstimator(calibration=-1)


# --- calibration fits ---------------------------------------------------------


def test_calibration_speeds_are_parsed_and_bounded():
    assert parse_speeds("0.5, 1,2,") == [0.5, 1.0, 2.0]
    for text, message in (("1;2", "SPEEDS: '1;2' is not a number"),
                          ("1", "SPEEDS: needs at least 2 speeds, got 1"),
                          ("0,1", "SPEEDS: speed 0 must be positive"),
                          ("1,12", "SPEEDS: speed 12 is above 10 mm/s"),
                          ("1,nan", "SPEEDS: 'nan' is not a finite number")):
        with pytest.raises(FlowloopError, match=message):
            parse_speeds(text)


@given(st.floats(0.7, 1.4), st.lists(st.floats(0.2, 5.0), min_size=2, max_size=6,
                                     unique=True),
       st.floats(5.0, 100.0))
def test_fit_recovers_the_sensor_ratio_from_any_speeds(ratio, speeds, length):
    commanded = [length] * len(speeds)
    fit = fit_calibration(speeds, commanded, [ratio * c for c in commanded])
    assert fit.calibration == pytest.approx(ratio)
    assert fit.spread == pytest.approx(0, abs=1e-9)


@given(st.floats(0.03, 0.3))
def test_fit_is_refused_when_speeds_disagree_beyond_the_bound(slip):
    with pytest.raises(FlowloopError, match="disagree by more than 2.00%"):
        fit_calibration([0.5, 1, 4], [20, 20, 20], [20, 20, 20 * (1 - slip)])


def test_fit_within_the_bound_is_the_least_squares_ratio():
    fit = fit_calibration([1, 2], [10, 30], [10.1, 30.0])
    assert fit.calibration == pytest.approx((10 * 10.1 + 30 * 30) / (100 + 900))
    assert "1 mm/s: 1.01000" in fit.describe()


@given(st.floats(0.85, 1.15), st.floats(1.0, 40.0))
def test_rotation_distance_scales_by_what_the_sensor_measured(ratio, rd):
    change = rotation_distance_correction(rd, 50.0, 50.0 * ratio)
    assert change.rotation_distance == pytest.approx(rd * ratio)
    assert change.calibration == 1.0


def test_an_implausible_rotation_distance_change_is_refused():
    with pytest.raises(FlowloopError, match="more than 20% off"):
        rotation_distance_correction(7.7, 50.0, 30.0)


@given(st.floats(0.6, 1.5))
def test_a_sensor_counting_backwards_is_told_apart_from_no_filament(ratio):
    with pytest.raises(ReversedSensor, match="counts backwards"):
        fit_calibration([0.5, 1, 2], [20, 20, 20], [-20 * ratio] * 3)
    with pytest.raises(ReversedSensor, match="counts backwards"):
        rotation_distance_correction(7.7, 50.0, -50.0 * ratio)
    with pytest.raises(FlowloopError, match="saw almost no filament"):
        fit_calibration([0.5, 1], [20, 20], [0.1, -0.1])


def _pressure_advance_corner(t):
    """Nominal E at 3 mm/s with a slow stretch (a corner) at 0.4..0.6 s; the
    stepper, with pressure advance 0.05 s, leads by 0.05 x velocity and so
    steps back 0.1 mm where the print slows."""
    velocity = np.where((t > 0.4) & (t < 0.6), 1.0, 3.0)
    nominal = np.concatenate([[0.0], np.cumsum(velocity[1:] * np.diff(t))])
    return nominal, nominal + 0.05 * velocity


def test_pressure_advance_at_a_corner_is_not_a_retraction():
    t = np.arange(0, 1.5, 0.001)
    nominal, stepper = _pressure_advance_corner(t)
    assert np.diff(stepper).min() < -0.09        # the stepper goes back
    est = GripEstimator(window_mm=1.0)
    windows = est.add(t, stepper, stepper, nominal_mm=nominal)
    assert len(windows) >= 3 and all(w.reason == "judged" for w in windows)
    # measured against the stepper position: what the feeder was asked to move
    at = {round(x, 6): e for x, e in zip(t, stepper)}
    for w in windows:
        assert w.commanded_mm == pytest.approx(
            at[round(w.end_time, 6)] - at[round(w.start_time, 6)])
    # without the nominal motion the same samples close as a retraction
    plain = GripEstimator(window_mm=1.0).add(t, stepper, stepper)
    assert "retraction" in [w.reason for w in plain]


def test_a_nominal_retraction_still_closes_the_window():
    t = np.arange(0, 1.0, 0.001)
    nominal = np.where(t < 0.3, 5 * t, 5 * 0.3 - 0.8)
    windows = GripEstimator().add(t, nominal, nominal + 0.05, nominal_mm=nominal)
    assert "retraction" in [w.reason for w in windows]


@given(st.lists(st.tuples(st.floats(0.01, 0.5), st.floats(0.0, 50.0),
                          st.floats(-2000.0, 2000.0), st.sampled_from([1.0, -1.0])),
                min_size=1, max_size=6), st.floats(-10.0, 10.0))
def test_trapq_positions_follow_the_moves_as_klipper_plans_them(segments, e0):
    moves, start, position = [], 1.0, e0
    for move_t, start_v, accel, axis_r in segments:
        accel = max(accel, -start_v / move_t)    # never reverses in a move
        moves.append((start, move_t, start_v, accel, position, axis_r))
        position += axis_r * (start_v + 0.5 * accel * move_t) * move_t
        start += move_t
    times = np.linspace(0.5, start + 0.5, 200)
    got = trapq_positions(list(reversed(moves)), times)
    for t, p in zip(times, got):
        if t <= 1.0:
            assert p == pytest.approx(e0)
        elif t >= start:
            assert p == pytest.approx(position, abs=1e-6)
        else:
            m = max(m for m in moves if m[0] <= t)
            dt = t - m[0]
            assert p == pytest.approx(m[4] + m[5] * (m[2] + 0.5 * m[3] * dt) * dt,
                                      abs=1e-6)
    assert trapq_positions([], times) is None


def test_window_flows_are_the_planned_flow_in_pieces():
    # 0.2 s at 2 mm/s of filament, a 0.1 s stop, 0.2 s at 1 mm/s (trapq rows)
    moves = [(1.0, 0.2, 2.0, 0.0, 0.0, 1.0), (1.3, 0.2, 1.0, 0.0, 0.4, 1.0)]
    flows = window_flows(moves, 1.0, 1.5, 2.0)
    assert len(flows) == 10                    # 0.05 s pieces
    assert flows == pytest.approx([4.0] * 4 + [0.0] * 2 + [2.0] * 4)
    # the pieces average to the planned volume over the window
    assert sum(flows) / len(flows) * 0.5 == pytest.approx(2.0 * (0.4 + 0.2))
    assert window_flows([], 1.0, 1.5, 2.0) == ()
    assert window_flows(moves, 1.5, 1.5, 2.0) == ()


def test_a_break_drops_the_open_window_and_starts_a_new_one():
    t = np.arange(0, 1.0, 0.001)
    commanded = 3.0 * t
    sensor = commanded.copy()
    sensor[500:] += 9.96                  # a whole turn lost across a gap
    breaks = np.zeros(len(t), dtype=bool)
    breaks[500] = True
    windows = GripEstimator(window_mm=1.0).add(t, sensor, commanded,
                                               breaks=breaks)
    assert windows and all(w.grip == pytest.approx(1.0) for w in windows)
    assert not any(w.start_time < 0.5 < w.end_time for w in windows)
    # unmarked, the lost turn would be judged as grip
    plain = GripEstimator(window_mm=1.0).add(t, sensor, commanded)
    assert max(w.grip for w in plain) > 5


@given(st.floats(0.0002, 0.01), st.integers(1, 400), st.floats(0.001, 0.05))
def test_positions_are_read_about_every_spacing_and_interpolated(period, n,
                                                                 spacing):
    times = 3.0 + period * np.arange(n)
    calls = []

    def position_at(t):
        calls.append(t)
        return 2.0 * t + 0.5 * 40.0 * t * t      # accelerating filament

    got = positions_at(times, position_at, spacing)
    assert calls[0] == times[0] and calls[-1] == times[-1]
    assert len(calls) <= (times[-1] - times[0]) / spacing + 2
    assert np.all(np.diff(calls) > 0)
    # linear between reads at most `spacing` (plus a period) apart
    gap = spacing + period
    assert np.abs(got - position_at(times)).max() <= 40.0 * gap * gap / 8 + 1e-9
