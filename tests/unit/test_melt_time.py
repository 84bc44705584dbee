"""What a burst shorter than MELT_TIME_S does on the simulated twin.

The annotation announces the flow averaged over MELT_TIME_S (0.5 s): a burst
above the hotend's capacity whose 0.5 s mean is within it is averaged away.
These tests measure what such a burst costs on the twin (flowloop.sensor.twin:
the feeder slips where the demand, smoothed over the twin's melt lag, exceeds
what the melt line gives) and whether the grip windows see it, so that the
limiter does. The figures are in docs/autotemp.md, "The flow to melt".

The pattern: 5 mm^3/s, a burst of 20 mm^3/s (twice the capacity of the twin's
default melt line at 200 C, 10 mm^3/s), then 5 mm^3/s again. Its 0.5 s mean
stays within capacity for bursts up to 1/6 s.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np
import pytest

from flowloop.gcode.melt import MELT_TIME_S
from flowloop.sensor.grip import SLIP_GRIP, GripEstimator
from flowloop.sensor.twin import DEFAULT_MELT_LINE, SimulatedEms22

AREA_MM2 = 2.405
SAMPLE_S = 0.001
TEMP_C = 200.0
BASE, BURST = 5.0, 20.0
CAPACITY = DEFAULT_MELT_LINE.flow_mm3_s(TEMP_C)
BURST_AT_S = 3.0


class Burst(NamedTuple):
    lost_mm: float            # filament commanded but not moved
    burst_mm: float           # the burst's own filament
    lowest_grip: float        # of the grip windows over the print
    mean_peak_mm3_s: float    # the highest 0.5 s mean of the flow


def burst_on_twin(burst_s: float, melt_lag_s: Optional[float] = None) -> Burst:
    """One burst, the twin fed the commanded position every millisecond."""
    t = np.arange(0.0, 6.0, SAMPLE_S)
    flow = np.where((t >= BURST_AT_S) & (t < BURST_AT_S + burst_s), BURST, BASE)
    commanded = np.concatenate(([0.0], np.cumsum(flow[:-1]) * SAMPLE_S / AREA_MM2))
    kwargs = {} if melt_lag_s is None else {"melt_time_s": melt_lag_s}
    twin = SimulatedEms22(noise_counts=0.0, **kwargs)
    moved = np.concatenate([twin.advance(t[k:k + 100], commanded[k:k + 100], TEMP_C)
                            for k in range(0, len(t), 100)])
    windows = GripEstimator(filament_area_mm2=AREA_MM2).add(t, moved, commanded)
    half = round(MELT_TIME_S / 2 / SAMPLE_S)
    volume = np.cumsum(flow) * SAMPLE_S
    mean = (volume[2 * half:] - volume[:-2 * half]) / MELT_TIME_S
    return Burst(float(commanded[-1] - moved[-1]), BURST * burst_s / AREA_MM2,
                 min(w.grip for w in windows if w.grip is not None),
                 float(mean.max()))


def test_the_pattern_is_within_capacity_over_half_a_second_up_to_a_sixth_of_one():
    assert BURST > CAPACITY > BASE
    assert burst_on_twin(0.16).mean_peak_mm3_s <= CAPACITY
    assert burst_on_twin(0.18).mean_peak_mm3_s > CAPACITY


@pytest.mark.parametrize("burst_s", [0.01, 0.02])
def test_a_burst_of_a_slicers_rounding_costs_no_filament(burst_s):
    lost, _, grip, mean = burst_on_twin(burst_s)
    assert lost == 0.0
    assert grip == pytest.approx(1.0)
    assert mean < 0.6 * CAPACITY


@pytest.mark.parametrize("burst_s", [0.1, 0.15])
def test_a_burst_longer_than_the_twins_melt_lag_slips_and_the_grip_windows_see_it(
        burst_s):
    # the twin's default melt lag (0.05 s) is shorter than MELT_TIME_S: such a
    # burst is averaged away by the annotation, and covered by the limiter
    lost, burst_mm, grip, mean = burst_on_twin(burst_s)
    assert mean <= CAPACITY
    assert 0.2 * burst_mm < lost < 0.4 * burst_mm
    assert grip < SLIP_GRIP


@pytest.mark.parametrize("burst_s", [0.01, 0.05, 0.1, 0.15, 0.165])
def test_with_a_melt_lag_near_the_residence_no_averaged_burst_costs_three_percent(
        burst_s):
    # a melt lag of 0.3 s (the fil tier's twin): the 0.5 s mean is what melts
    lost, burst_mm, grip, mean = burst_on_twin(burst_s, melt_lag_s=0.3)
    assert mean <= CAPACITY + 1e-9
    assert lost <= 0.03 * burst_mm
    assert grip > SLIP_GRIP


def onset_s(melt_lag_s: float) -> float:
    """The shortest burst (in 5 ms steps) that loses more than 0.5 % of its
    filament on a twin of this melt lag."""
    for ms in range(5, 1000, 5):
        r = burst_on_twin(ms / 1000, melt_lag_s)
        if r.lost_mm > 0.005 * r.burst_mm:
            return ms / 1000
    raise AssertionError("no burst slips")


@pytest.mark.parametrize("melt_lag_s", [0.05, 0.3])
def test_the_melt_window_a_twin_tolerates_is_its_melt_lag(melt_lag_s):
    """Under-extrusion starts at a burst of about half the melt lag (the lag
    smooths the demand as a first-order filter: this burst, three times the
    base's margin to capacity, overflows it from ln(1.5) = 0.41 lags on).
    A melt window no longer than the lag averages away only bursts that do
    not slip, whatever their height (the window's mean of a burst is at
    least its first-order peak); MELT_TIME_S (0.5 s) is that window for a
    hotend whose melt lags 0.5 s, and averages away slipping bursts on the
    twin's 0.05 s and the fil tier's 0.3 s (docs/autotemp.md)."""
    onset = onset_s(melt_lag_s)
    assert 0.4 * melt_lag_s <= onset <= 0.55 * melt_lag_s
    # the longest burst a window of the lag averages within capacity
    averaged = melt_lag_s * (CAPACITY - BASE) / (BURST - BASE)
    assert averaged < onset
    r = burst_on_twin(averaged, melt_lag_s)
    assert r.lost_mm <= 0.005 * r.burst_mm and r.lowest_grip > SLIP_GRIP
    # MELT_TIME_S averages away bursts up to a sixth of a second, which slip
    # on both twins
    assert MELT_TIME_S * (CAPACITY - BASE) / (BURST - BASE) > onset
