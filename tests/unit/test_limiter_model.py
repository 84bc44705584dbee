"""The predictive grip model: seeded from the profile's one melt line,
fitted online to the windows the sensor closes."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from flowloop.control.grip_model import (
    CLIMB_FROM,
    CLIMB_STEP,
    DEFAULT_FILAMENT_AREA_MM2,
    SLIP_TOLERANCE,
    CapacityLine,
    GripModel,
    WindowFlow,
    fit_capacity,
    melted_capacity,
    predicted_grip,
)
from flowloop.control.limiter import LimiterSettings
from flowloop.errors import FlowloopError
from flowloop.material.profile import Line, profile_from_dict, profile_line
from flowloop.window import FAULT, JUDGED, TOO_LITTLE_MOTION, Window
from tests.samples import make

PROFILE = profile_from_dict(make())          # herz-pla-red 0.8 mm (ddPrint)
LINE = profile_line(PROFILE, 0.5)


def seen(flow_mm3_s, grip, temp_c, flows=(), reason=None):
    """A one-second grip window at a mean commanded flow, as the model
    learns from it."""
    if reason is None:
        reason = TOO_LITTLE_MOTION if grip is None else JUDGED
    commanded_mm = flow_mm3_s / DEFAULT_FILAMENT_AREA_MM2
    return Window(0.0, 1.0, commanded_mm,
                  0.0 if grip is None else grip * commanded_mm, grip, reason,
                  temp_c=temp_c, commanded_flows=tuple(flows))


def test_the_seed_is_the_profile_line_at_its_grip():
    seed = CapacityLine.from_profile_line(LINE, 0.9, 210.0)
    for temp in (200.0, 210.0, 230.0):
        assert seed.at(temp) == pytest.approx(0.9 * LINE.flow_mm3_s(temp))
    model = GripModel(seed)
    # the cap is where the slip starts: below the line, where grip is 0.9
    assert model.cap_mm3_s(220.0) == pytest.approx(0.9 * LINE.flow_mm3_s(220.0))


def test_predicted_grip_is_capacity_over_demand():
    seed = CapacityLine(210.0, 10.0, 0.15)
    assert predicted_grip(seed, 8.0, 210.0) == 1.0
    assert predicted_grip(seed, 20.0, 210.0) == pytest.approx(0.5)
    assert predicted_grip(seed, 0.0, 210.0) == 1.0


def test_slipping_windows_pull_the_fit_to_the_true_capacity():
    seed = CapacityLine(210.0, 10.0, 0.15)
    true = CapacityLine(210.0, 7.0, 0.12)      # a hotend 30 % weaker than seeded
    model = GripModel(seed)
    for i in range(60):
        temp = 200.0 + (i % 5) * 10.0
        demand = 1.6 * true.at(temp)
        model.learn(seen(demand, true.at(temp) / demand, temp))
    # 60 windows against a prior worth 5: over 90 % of the seed's error gone
    assert abs(model.fitted.capacity_mm3_s - 7.0) < 0.1 * 3.0
    assert model.fitted.slope_mm3_s_per_c == pytest.approx(0.12, rel=0.1)
    assert model.status()["windows"] == 60


def test_a_window_that_kept_up_above_the_model_raises_it():
    model = GripModel(CapacityLine(210.0, 10.0, 0.15))
    for _ in range(20):
        model.learn(seen(14.0, 1.0, 210.0))
    assert model.fitted.at(210.0) > 13.0


def test_windows_that_say_nothing_change_nothing():
    model = GripModel(CapacityLine(210.0, 10.0, 0.15))
    assert not model.learn(seen(5.0, 1.0, 210.0))     # kept up below capacity
    assert not model.learn(seen(15.0, None, 210.0))   # not judged
    assert not model.learn(seen(15.0, 0.5, None))     # no temperature
    assert not model.learn(seen(15.0, 0.5, 210.0, reason=FAULT))  # faulted
    assert model.fitted == model.seed


@given(st.lists(st.tuples(st.floats(180, 260), st.floats(0, 40)), max_size=30))
def test_with_one_temperature_the_slope_stays_near_the_seed(points):
    seed = CapacityLine(210.0, 10.0, 0.15)
    same_temp = [(215.0, flow) for _, flow in points]
    fit = fit_capacity(seed, same_temp)
    # all at one temperature: the data pins C(215) (the seed's capacity is
    # worth half a window), the prior the slope
    if points:
        mean = sum(f for _, f in same_temp) / len(same_temp)
        n = len(same_temp)
        assert fit.at(215.0) == pytest.approx(
            (n * mean + 0.5 * seed.at(215.0)) / (n + 0.5), rel=0.05, abs=0.05)
        assert abs(fit.slope_mm3_s_per_c - 0.15) \
            <= 0.002 * abs(mean - seed.at(215.0)) + 1e-9


def test_one_slipped_window_moves_the_capacity_most_of_the_way():
    # the profile's capacity is a guess, a slip a measurement of this hotend
    model = GripModel(CapacityLine(210.0, 10.0, 0.15))
    model.learn(seen(12.0, 7.0 / 12.0, 210.0))
    assert 7.0 < model.cap_mm3_s(210.0) < 8.1


def test_the_seed_does_not_hold_the_fit_above_what_the_windows_measure():
    # a profile 40 % optimistic, a hundred windows that slipped at 7 mm^3/s:
    # a cap even 1 % above 7 slips every capped move by 1 %
    model = GripModel(CapacityLine(210.0, 10.0, 0.15))
    for _ in range(100):
        model.learn(seen(12.0, 7.0 / 12.0, 200.0))
    assert model.cap_mm3_s(200.0) == pytest.approx(7.0, rel=0.005)


def test_the_line_it_is_seeded_from_is_the_material_line():
    # one melt line: the model asks flowloop.material's Line, never its own
    line = Line(0.2, -30.0)
    assert CapacityLine.from_profile_line(line, 1.0, 200.0).at(210.0) == \
        pytest.approx(line.flow_mm3_s(210.0))


# --- what a window that mixes flows says -------------------------------------

@given(st.lists(st.floats(0.0, 30.0), min_size=1, max_size=40),
       st.floats(0.5, 25.0))
def test_melted_capacity_inverts_a_hotend_that_passes_min_flow_capacity(
        flows, capacity):
    melted = sum(min(f, capacity) for f in flows) / len(flows)
    got = melted_capacity(flows, melted)
    if capacity < max(flows):
        assert got == pytest.approx(capacity, rel=1e-9, abs=1e-9)
    else:  # it kept up with every piece: only the peak is known
        assert got == pytest.approx(max(flows))


def test_a_mixed_window_reads_the_capacity_its_mean_would_hide():
    # half the window at 12 mm^3/s against a capacity of 8, half at 2
    flows = [12.0] * 5 + [2.0] * 5
    mean = sum(flows) / len(flows)
    grip = (5 * 8.0 + 5 * 2.0) / (mean * len(flows))
    window = WindowFlow.of(mean, grip, flows)
    assert grip * mean == pytest.approx(5.0)       # what the old rule took
    assert window.melted_mm3_s == pytest.approx(8.0)
    assert window.peak_mm3_s == pytest.approx(12.0)
    # the planned flow leaves out pressure advance: scaled to the mean
    scaled = WindowFlow.of(mean, grip, [f * 1.02 for f in flows])
    assert scaled.melted_mm3_s == pytest.approx(8.0)
    # without the flow over time: a window at one flow
    assert WindowFlow.of(10.0, 0.7).melted_mm3_s == pytest.approx(7.0)


def test_a_window_that_reads_over_1_mirrors_one_that_reads_as_much_under():
    # half the window at the peak, 12 mm^3/s, half at 2: a grip 3 % under 1
    # puts the capacity below the peak by what the peak's pieces lost, 3 %
    # over puts it as far above
    flows = [12.0] * 5 + [2.0] * 5
    under, over = WindowFlow.of(7.0, 0.97, flows), WindowFlow.of(7.0, 1.03, flows)
    assert under.over_mm3_s == under.melted_mm3_s == pytest.approx(12.0 - 0.42)
    assert over.melted_mm3_s == pytest.approx(12.0)     # kept up: its peak
    assert over.over_mm3_s == pytest.approx(12.0 + 0.42)
    # a window at one flow: the flow times its grip
    assert WindowFlow.of(10.0, 1.04).over_mm3_s == pytest.approx(10.4)


def test_noise_at_the_cap_pulls_the_fit_both_ways():
    # The hotend melts more than the cap: every window at the cap kept up,
    # and only the sensor's noise makes one read under or over the band. As
    # many read 3 % over as under: the fit stays at the cap, where counting
    # only those read under walked it down window by window.
    def fed(grips):
        model = GripModel(CapacityLine(210.0, 10.0, 0.15), climb_from=1.0)
        for grip in grips:
            model.learn(seen(model.cap_mm3_s(210.0), grip, 210.0))
        return model.cap_mm3_s(210.0)
    for noisy in ([0.97, 1.03] * 40, [1.03, 0.97] * 40):
        assert fed(noisy) == pytest.approx(10.0, rel=0.015)
    # within the band a window at the cap says nothing, either way
    assert fed([1.0 + SLIP_TOLERANCE / 2, 1.0 - SLIP_TOLERANCE / 2] * 40) == 10.0
    # the reads under alone (all that counted before): 10 % down in 40
    assert fed([0.97] * 40) < 0.92 * 10.0


def test_a_window_read_over_1_below_the_cap_teaches_nothing():
    model = GripModel(CapacityLine(210.0, 10.0, 0.15), climb_from=1.0)
    assert not model.learn(seen(8.0, 1.05, 210.0))
    assert model.fitted == model.seed


def test_mixed_windows_teach_the_true_capacity_not_their_mean():
    true = CapacityLine(210.0, 7.0, 0.12)
    model = GripModel(CapacityLine(210.0, 10.0, 0.15))
    for i in range(60):
        temp = 200.0 + (i % 5) * 10.0
        c = true.at(temp)
        # fast infill above the capacity, slow perimeters and a pause
        flows = [1.5 * c] * 4 + [0.5 * c] * 4 + [0.0] * 2
        mean = sum(flows) / len(flows)
        grip = sum(min(f, c) for f in flows) / len(flows) / mean
        model.learn(seen(mean, grip, temp, flows))
    # as with windows at one flow: over 90 % of the seed's error gone (their
    # mean flow, 0.6 of the capacity, would have fitted about 4.6)
    assert abs(model.fitted.capacity_mm3_s - 7.0) < 0.1 * 3.0
    # a window that kept up while peaking above the model raises it to the peak
    kept = GripModel(CapacityLine(210.0, 7.0, 0.12))
    assert kept.learn(seen(4.0, 1.0, 210.0, [9.0, 9.0, 0.0, 0.0, 2.0]))
    assert kept.observations[-1] == (210.0, pytest.approx(9.0))
    # one that nearly kept up (a slip within sensor noise, under 2 %) says
    # the capacity its slip gives: 9.8 under a peak of 10
    flows = [10.0] * 5 + [2.0] * 5
    grip = (5 * 9.8 + 5 * 2.0) / sum(flows)
    assert grip > 0.98
    assert kept.learn(seen(6.0, grip, 210.0, flows))
    assert kept.observations[-1] == (210.0, pytest.approx(9.8))


def test_a_first_print_climbs_from_below_the_profile_to_its_line():
    # a hotend that melts what the profile says: each window that kept up
    # at the cap raises it CLIMB_STEP times what the window asked for, up
    # to the profile's line, where the climb ends; no window it kept up in
    # is taken for a measurement
    seed = CapacityLine(210.0, 10.0, 0.15)
    model = GripModel(seed, climb_from=CLIMB_FROM)
    assert model.cap_mm3_s(210.0) == pytest.approx(CLIMB_FROM * 10.0)
    assert model.cap_mm3_s(230.0) == pytest.approx(CLIMB_FROM * seed.at(230.0))
    caps = [model.cap_mm3_s(210.0)]
    while model.climb_ratio is not None:
        cap = caps[-1]
        assert model.learn(seen(cap, 1.0, 210.0, flows=(cap,) * 10))
        caps.append(model.cap_mm3_s(210.0))
        assert len(caps) < 20
    for before, after in zip(caps[:-2], caps[1:-1]):
        assert after == pytest.approx(before * CLIMB_STEP)
    assert caps[-1] == pytest.approx(10.0)
    assert model.status()["windows"] == 0 and model.status()["climb_ratio"] is None


def test_a_climb_ends_at_the_first_slip_and_the_fit_takes_it_from_there():
    seed = CapacityLine(210.0, 10.0, 0.15)
    model = GripModel(seed, climb_from=0.7)
    # kept up at 7: the climb steps to 7.35, where a hotend melting 7.2 slips
    model.learn(seen(7.0, 1.0, 210.0, flows=(7.0,) * 10))
    assert model.cap_mm3_s(210.0) == pytest.approx(7.0 * CLIMB_STEP)
    # a window far below the cap that kept up does not raise it
    assert not model.learn(seen(3.0, 1.0, 210.0, flows=(3.0,) * 10))
    model.learn(seen(7.35, 7.2 / 7.35, 210.0, flows=(7.35,) * 10))
    assert model.climb_ratio is None and model.status()["windows"] == 1
    # the fit: the measurement (7.2) against the seed where the climb left
    # it (7.35, worth half a window), not the profile's 10
    assert model.cap_mm3_s(210.0) == pytest.approx((0.5 * 7.35 + 7.2) / 1.5)
    # after the climb, a window that kept up is no step any more
    model.learn(seen(7.0, 1.0, 210.0, flows=(7.0,) * 10))
    assert model.cap_mm3_s(210.0) == pytest.approx((0.5 * 7.35 + 7.2) / 1.5)


@pytest.mark.parametrize("bad", [0.0, -0.5, 1.5, float("nan")])
def test_a_climb_from_outside_0_to_1_is_refused(bad):
    with pytest.raises(FlowloopError, match="climb_from"):
        GripModel(CapacityLine(210.0, 10.0, 0.15), climb_from=bad)
    with pytest.raises(FlowloopError, match="climb_from must be in"):
        LimiterSettings(climb_from=bad)


def test_climbing_from_1_is_no_climb():
    model = GripModel(CapacityLine(210.0, 10.0, 0.15), climb_from=1.0)
    assert model.climb_ratio is None and model.cap_mm3_s(210.0) == 10.0
