"""The hotend thermal model: a first-order lag after a dead time within the
heater's power, a sag when extrusion needs more heat than the heater has."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flowloop.control.hotend import (
    READING_PERIOD_S,
    STEP_S,
    HotendModel,
    HotendParams,
    NozzleEstimate,
    heater_reads,
    nozzle_estimate_for,
)
from flowloop.errors import FlowloopError
from flowloop.material.profile import Line
from flowloop.sensor.twin import SimulatedEms22

PARAMS = HotendParams(time_constant_s=4.0, dead_time_s=1.0)


def test_nothing_happens_before_the_dead_time():
    model = HotendModel(PARAMS, temp_c=25.0)
    model.set_target(0.0, 210.0)
    assert model.advance(0.95) == pytest.approx(25.0)


def test_within_power_it_follows_as_a_first_order_lag():
    # Start hot, a 2 degC step (about 21 W, within the heater's 40)
    model = HotendModel(PARAMS, temp_c=200.0, target_c=200.0)
    model.advance(5.0)
    model.set_target(5.0, 202.0)
    assert model.advance(6.0) == pytest.approx(200.0)
    temp = model.advance(6.0 + PARAMS.time_constant_s)
    assert 0.0 < model.power_w < PARAMS.max_power_w
    assert temp == pytest.approx(202.0 - 2.0 / math.e, abs=0.01)


def test_heating_from_cold_is_limited_by_the_heater_power():
    model = HotendModel(PARAMS, temp_c=25.0)
    model.set_target(0.0, 210.0)
    model.advance(1.0)
    # 40 W into 16.7 J/K can raise at most 2.4 degC/s
    temp = model.advance(3.0)
    assert model.power_w == PARAMS.max_power_w
    assert 25.0 < temp <= 25.0 + 2.0 * 40.0 / 16.7 + 1e-6


def test_extrusion_cools_and_a_high_flow_sags_the_nozzle():
    p = PARAMS
    limit = p.max_steady_flow_mm3_s(230.0)
    # 40 W minus 0.07 W/K * 205 K, over 0.00233 J/K/mm^3 * 205 K
    assert limit == pytest.approx((40 - 0.07 * 205) / (0.00233 * 205))
    for flow, sags in ((0.8 * limit, False), (1.5 * limit, True)):
        model = HotendModel(p, temp_c=230.0, target_c=230.0)
        temp = model.advance(600.0, flow_mm3_s=flow)
        assert (temp < 229.0) is sags
    # the sag settles where the heater's full power holds the block
    k = p.loss_w_per_c + p.filament_j_per_mm3_c * 1.5 * limit
    assert temp == pytest.approx(p.ambient_c + p.max_power_w / k, abs=0.5)


def test_a_heater_turned_off_cools_toward_ambient():
    model = HotendModel(PARAMS, temp_c=200.0)
    temp = model.advance(600.0)
    assert model.power_w == 0.0 and 25.0 < temp < 60.0


@given(st.floats(0, 300), st.floats(0, 300), st.floats(0, 60), st.floats(0, 50))
def test_the_nozzle_never_overshoots_a_target_it_approaches(start, target, t, flow):
    model = HotendModel(PARAMS, temp_c=max(start, PARAMS.ambient_c))
    model.set_target(0.0, target)
    temp = model.advance(t, flow)
    lo = min(model.params.ambient_c, target, start)
    hi = max(target, start, model.params.ambient_c)
    assert lo - 1e-6 <= temp <= hi + 1e-6


def _single_steps(model, until_s, flow):
    """The model as it is defined: one closed-form step of STEP_S at a time."""
    p = model.params
    k = p.loss_w_per_c + p.filament_j_per_mm3_c * flow
    while model.time_s < until_s:
        dt = min(STEP_S, until_s - model.time_s)
        target = model.target_seen_at(model.time_s)
        if model.fixed_power_w is not None:
            power = model.fixed_power_w
        elif target <= 0.0:
            power = 0.0
        else:
            power = k * (model.temp_c - p.ambient_c) + (
                p.heat_capacity_j_per_c / p.time_constant_s) * (target - model.temp_c)
        power = min(p.max_power_w, max(0.0, power))
        if 0 < power < p.max_power_w and target > 0 and model.fixed_power_w is None:
            end, rate = target, 1.0 / p.time_constant_s
        else:
            end, rate = p.ambient_c + power / k, k / p.heat_capacity_j_per_c
        model.temp_c = end + (model.temp_c - end) * math.exp(-dt * rate)
        model.time_s += dt
    return model.temp_c


@settings(deadline=None)  # a run of minutes of single steps: no timing here
@given(st.floats(25, 280), st.lists(st.tuples(
    st.floats(0.0, 60.0), st.sampled_from([0.0, 180.0, 210.0, 260.0, 300.0]),
    st.floats(0.1, 40), st.sampled_from([None, None, 5.0, 30.0])), max_size=12))
def test_runs_of_steps_taken_at_once_end_where_single_steps_do(start, spans):
    # advance() takes a run of steps in one closed form where the heater
    # stays on one side of its limits
    params = HotendParams(max_power_w=30.0, dead_time_s=0.37)
    model, reference = (HotendModel(params, temp_c=start) for _ in range(2))
    for seconds, target, flow, fixed in spans:
        for m in (model, reference):
            m.set_target(m.time_s, target)
            m.fixed_power_w = fixed
        temp = model.advance(model.time_s + seconds, flow)
        assert temp == pytest.approx(
            _single_steps(reference, reference.time_s + seconds, flow), abs=1e-6)
        assert model.time_s == reference.time_s


def test_a_nozzle_estimate_reads_as_often_as_a_thermistor_reports():
    estimate = NozzleEstimate(HotendModel(PARAMS, temp_c=200.0, target_c=200.0))
    reference = HotendModel(PARAMS, temp_c=200.0, target_c=200.0)
    # moves of 0.1 s, extruding 1 mm^3 each (10 mm^3/s), then 0.1 s of travel
    due = [estimate.add_move(0.1, 1.0 if i % 2 == 0 else 0.0) for i in range(3)]
    assert due == [False, False, True]  # 0.3 s: READING_PERIOD_S
    temp = estimate.read(230.0)
    # the model ran once over the three moves at their mean flow, the new
    # target from then on
    reference.set_target(0.0, 230.0)
    assert temp == reference.advance(0.3, 2.0 / 0.3)
    assert READING_PERIOD_S == 0.3
    assert estimate.add_move(0.2, 0.0) is False
    assert estimate.read(230.0) == reference.advance(0.5, 0.0)


def test_bad_parameters_are_one_line():
    with pytest.raises(FlowloopError, match="max_power_w must be above 0"):
        HotendParams(max_power_w=0)
    with pytest.raises(FlowloopError, match="dead_time_s must be >= 0"):
        HotendParams(dead_time_s=-1)


# --- the simulated twin's hotend ---------------------------------------------

def _twin_grip(twin, target_c, seconds, demand_mm3_s, start=0.0):
    """Share of commanded filament that moved over `seconds` of steady demand."""
    times = start + np.arange(0.0, seconds, 0.001)
    commanded = demand_mm3_s / twin.filament_area_mm2 * (times - start)
    moved = twin.advance(times, commanded, target_c)
    if demand_mm3_s == 0:
        return None
    return (moved[-1] - moved[0]) / (commanded[-1] - commanded[0])


def test_the_twin_slips_while_its_hotend_heats_and_keeps_up_once_hot():
    melt = Line(0.2, -30.0)                     # 10 mm^3/s at 200 C
    twin = SimulatedEms22(melt, noise_counts=0,
                          hotend=HotendModel(PARAMS, temp_c=25.0))
    assert _twin_grip(twin, 200.0, 5.0, 5.0) < 0.2     # cold: nothing melts
    _twin_grip(twin, 200.0, 120.0, 0.0, start=5.0)     # heats up, idle
    assert twin.temp_c(200.0) == pytest.approx(200.0, abs=0.5)
    assert _twin_grip(twin, 200.0, 5.0, 5.0, start=125.0) == pytest.approx(1.0)


def test_a_long_high_flow_sags_the_twin_s_nozzle():
    weak = HotendParams(max_power_w=20.0, time_constant_s=4.0, dead_time_s=1.0)
    # a line that melts all of it at 230 C, if the heater could hold 230 C
    twin = SimulatedEms22(Line(1.0, -200.0), noise_counts=0,
                          hotend=HotendModel(weak, temp_c=230.0, target_c=230.0))
    assert weak.max_steady_flow_mm3_s(230.0) < 20.0
    first = _twin_grip(twin, 230.0, 2.0, 25.0)
    later = _twin_grip(twin, 230.0, 60.0, 25.0, start=2.0)
    assert first == pytest.approx(1.0)
    assert twin.temp_c(230.0) < 220.0 and later < 0.9


def test_a_scaled_twin_melts_that_share_of_its_line():
    from flowloop.sensor.twin import scaled_line
    line = Line(0.2, -30.0, ceiling=Line(0.1, -5.0))
    weak = scaled_line(line, 0.7)
    for temp in (180.0, 220.0, 300.0):
        assert weak.flow_mm3_s(temp) == pytest.approx(0.7 * line.flow_mm3_s(temp))


def test_only_a_batch_mode_klippy_reads_the_nozzle_from_the_model():
    # batch mode: output to a file, the MCU clock never started
    assert not heater_reads(True, 0.0)                  # batch mode
    assert heater_reads(True, 12.5) and heater_reads(False, 0.0)
    assert isinstance(nozzle_estimate_for(True, 0.0), NozzleEstimate)
    assert nozzle_estimate_for(True, 12.5) is None     # paced to the clock
    assert nozzle_estimate_for(False, 0.0) is None     # a printer, connecting
    assert nozzle_estimate_for(False, 12.5) is None


def test_batch_mode_s_estimate_heats_as_the_hotend_it_is_given():
    # A simulated hotend slower than the default (its twin's heater): the
    # estimate must follow it, not the default hotend, or the caps are set
    # at a temperature the nozzle has not reached
    slow = HotendParams(time_constant_s=10.0, heat_capacity_j_per_c=41.75)
    estimates = {name: nozzle_estimate_for(True, 0.0, params)
                 for name, params in (("default", None), ("slow", slow))}
    assert estimates["slow"].model.params == slow
    assert estimates["default"].model.params == HotendParams()
    temps = {}
    for name, estimate in estimates.items():
        estimate.model = HotendModel(estimate.model.params, temp_c=200.0,
                                     target_c=200.0)
        for _ in range(20):           # 200 -> 215 C, 6 s of moves
            estimate.add_move(READING_PERIOD_S, 0.0)
            temps[name] = estimate.read(215.0)
    twin = HotendModel(slow, temp_c=200.0, target_c=200.0)
    twin.set_target(0.0, 215.0)
    assert temps["slow"] == pytest.approx(twin.advance(6.0), abs=0.01)
    assert temps["default"] > temps["slow"] + 2.0


@settings(deadline=None)
@given(st.lists(st.floats(190.0, 260.0), min_size=1, max_size=80),
       st.sampled_from([0.1, 0.2, 0.25, 0.5]))
def test_a_target_acts_at_the_same_step_however_the_model_is_advanced(
        targets, step_s):
    """Targets set every step_s, one model advanced to each next setting (as
    a hotend is), the other a dead time ahead of them (as autotemp's plan
    runs its own): the same temperatures. Before SAME_INSTANT_S the summed
    clock put a target change a step (STEP_S) apart in the two, 0.06 C on a
    ramp, which Hypothesis found in the plan's tests."""
    hotend, ahead = (HotendModel(PARAMS, temp_c=200.0, target_c=200.0)
                     for _ in range(2))
    ahead.advance(PARAMS.dead_time_s)
    seen = {}
    for k, target in enumerate(targets):
        t = k * step_s
        for m in (hotend, ahead):
            m.set_target(t, target)
        ahead.advance(t + step_s + PARAMS.dead_time_s)
        seen[k + 1] = ahead.temp_c
    lag = round(PARAMS.dead_time_s / step_s)   # steps (a whole number here)
    for k in range(1, len(targets) + lag + 1):
        temp = hotend.advance(k * step_s)
        if k - lag in seen:
            assert temp == pytest.approx(seen[k - lag], abs=1e-9)
