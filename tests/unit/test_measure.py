"""The decisions of MEASURE_MATERIAL_PROFILE (flowloop.material.measure) and
the fixed-power hotend the twin simulates it with."""

from __future__ import annotations

import dataclasses

import pytest

from flowloop.control.hotend import HotendModel, HotendParams
from flowloop.errors import FlowloopError
from flowloop.material import measure
from flowloop.window import Window

pytestmark = pytest.mark.unit


def plan(**kw):
    args = dict(temps=(200.0, 230.0), powers=None, start_flow=2.0, step=0.5,
                max_flow=20.0, min_grip=0.9, min_temp_c=190.0, max_temp_c=260.0)
    args.update(kw)
    return measure.make_plan(**args)


def test_a_plan_runs_its_levels_in_order_and_flows_up_to_max_flow():
    p = plan(temps=(240.0, 200.0, 220.0), start_flow=2.0, step=0.5, max_flow=3.0)
    assert p.by == "temperature"
    assert p.levels == (200.0, 220.0, 240.0)
    assert list(p.flows()) == [2.0, 2.5, 3.0]
    assert plan(temps=None, powers=(0.3, 0.4)).describe_level(0.3) == "power 30%"


@pytest.mark.parametrize("kw, message", [
    ({"temps": None}, "give TEMPS= or POWERS="),
    ({"powers": (0.3, 0.4)}, "give TEMPS= or POWERS="),
    ({"temps": (200.0,)}, "TEMPS: needs 2 to 10 levels, got 1"),
    ({"temps": (200.0, 200.0)}, "TEMPS: each level once"),
    ({"temps": (180.0, 220.0)}, "TEMPS: 180 degC is outside the profile's 190..260"),
    ({"temps": (200.0, 270.0)}, "outside"),
    ({"temps": (205.0, 212.0)}, "TEMPS: the levels span 7 degC; at least 10"
                                " is needed"),
    ({"temps": (200.0, 209.9, 205.0)}, "TEMPS: the levels span 9.9 degC"),
    ({"temps": None, "powers": (0.30, 0.34)}, "POWERS: the levels span 0.04 of"
                                              " max_power 1; at least 5% of full"
                                              " power is needed"),
    ({"temps": None, "powers": (0.30, 0.38), "max_power": 0.5},
     "POWERS: the levels span 0.08 of max_power 0.5"),
    ({"temps": None, "powers": (0.3, 1.2)}, "POWERS: 1.2 must be in 0..1"),
    ({"temps": None, "powers": (0.0, 0.5)}, "POWERS: 0 must be in 0..1"),
    ({"start_flow": 0.0}, "START_FLOW: must be a number above 0"),
    ({"step": -1.0}, "STEP: must be a number above 0"),
    ({"max_flow": 1.0}, "MAX_FLOW: 1 is below START_FLOW 2"),
    ({"step": 0.01}, "more than 200 steps"),
    ({"min_grip": 1.0}, "MIN_GRIP: must be in 0..1"),
    ({"min_grip": 0.0}, "MIN_GRIP"),
])
def test_a_bad_plan_is_refused_naming_the_parameter(kw, message):
    with pytest.raises(FlowloopError, match=message.replace(".", r"\.")):
        plan(**kw)


@pytest.mark.parametrize("kw", [
    {"temps": (200.1, 210.1)},                       # 9.99999... apart
    {"temps": (200.0, 210.0)},
    {"temps": None, "powers": (0.30, 0.35)},         # 0.04999... apart
    {"temps": None, "powers": (0.30, 0.40), "max_power": 0.5},
])
def test_levels_just_far_enough_apart_are_planned(kw):
    assert len(plan(**kw).levels) == 2


def test_settled_needs_the_whole_hold_time_within_the_band():
    steady = [(float(t), 200.0 + 0.1 * (t % 2)) for t in range(12)]
    assert measure.settled(steady, hold_s=10.0)
    assert not measure.settled(steady[:5], hold_s=10.0)
    rising = [(float(t), 180.0 + t) for t in range(12)]
    assert not measure.settled(rising, hold_s=10.0)
    assert not measure.settled([], hold_s=10.0)


def window(start, end, grip, flow=5.0, temp=210.0):
    return Window(start_time=start, end_time=end, commanded_mm=1.0,
                  measured_mm=grip or 0.0, grip=grip,
                  reason="judged" if grip is not None else "retraction",
                  flow_mm3_s=flow, temp_c=temp)


def test_a_step_is_judged_on_its_windows_after_the_transient():
    windows = [window(10.0, 10.5, 0.5),            # transient: not used
               window(11.0, 11.5, 0.95, 6.0, 211.0),
               window(11.5, 12.0, None),            # unjudged: not used
               window(12.0, 12.5, 0.85, 5.0, 209.0),
               window(12.5, 13.5, 0.2)]             # past the step's end
    step = measure.judge_step(windows, 10.0, 13.0, 6.5)
    assert step.windows == 2
    assert step.grip == pytest.approx(0.9)
    assert step.measured_mm3_s == pytest.approx(5.5)
    assert step.temp_c == pytest.approx(210.0)
    assert measure.judge_step(windows[:1], 10.0, 13.0, 6.5) is None


def test_the_limit_point_is_the_melted_flow_at_the_step_temperature():
    step = measure.StepResult(commanded_mm3_s=7.0, grip=0.85, measured_mm3_s=5.95,
                              temp_c=205.3, windows=3)
    point = measure.limit_point(step, power=0.4, fallback_temp_c=0.0)
    assert (point.kind, point.temp_c, point.flow_mm3_s) == ("into_air", 205.3, 5.95)
    assert point.heater_pwm == pytest.approx(0.4 * 255)
    nameless = measure.StepResult(7.0, 0.85, 5.95, None, 3)
    assert measure.limit_point(nameless, 0.4, 199.0).temp_c == 199.0


@pytest.mark.parametrize("power", [5.0, 14.0, 35.0])
def test_a_hotend_at_fixed_power_settles_where_loss_meets_it(power):
    params = HotendParams()
    hotend = HotendModel(params, temp_c=200.0, target_c=200.0)
    hotend.fixed_power_w = power
    hotend.advance(2500.0)   # ten of the block's own time constants
    expected = params.ambient_c + power / params.loss_w_per_c
    assert hotend.temp_c == pytest.approx(expected, rel=1e-3)
    assert hotend.power_w == power


def test_a_hotend_at_fixed_power_sags_under_flow_where_its_controller_does_not():
    params = HotendParams()
    hold = params.steady_power_w(220.0, 0.0)
    fixed = HotendModel(params, temp_c=220.0, target_c=220.0)
    fixed.fixed_power_w = hold
    held = HotendModel(params, temp_c=220.0, target_c=220.0)
    fixed.advance(30.0, flow_mm3_s=10.0)
    held.advance(30.0, flow_mm3_s=10.0)
    assert fixed.temp_c < 215.0
    assert held.temp_c == pytest.approx(220.0, abs=0.5)


def test_a_low_flow_step_lasts_long_enough_for_its_windows():
    # 2 mm^3/s on 1.75 mm filament is 0.83 mm/s: 4 windows of 1.25 mm take 6 s
    assert measure.step_duration_s(3.0, 2.0, 2.405, 1.25) == pytest.approx(
        4 * 1.25 / (2.0 / 2.405))
    assert measure.step_duration_s(3.0, 10.0, 2.405, 1.25) == 3.0


def test_a_step_that_may_be_the_limit_lasts_more_windows():
    p = plan(start_flow=None, min_grip=0.9)
    # the base expects 10 mm^3/s: below 9 a step cannot be the limit
    assert p.step_windows(8.9, 10.0) == measure.MIN_STEP_WINDOWS
    assert p.step_windows(9.0, 10.0) == measure.LIMIT_STEP_WINDOWS
    assert p.step_windows(2.0, None) == measure.LIMIT_STEP_WINDOWS
    assert measure.LIMIT_STEP_WINDOWS > measure.MIN_STEP_WINDOWS
    assert measure.step_duration_s(2.0, 2.0, 2.405, 1.25, 5) == pytest.approx(
        5 * 1.25 / (2.0 / 2.405))


def test_the_console_line_of_a_step_says_how_long_it_extruded():
    step = measure.StepResult(6.0, 0.85, 5.1, 210.0, 3, duration_s=2.5)
    assert step.describe() == ("flow 6.00 mm^3/s for 2.5 s: grip 0.850,"
                               " measured 5.10 mm^3/s at 210.0 degC")


def test_without_start_flow_a_level_starts_near_its_expected_limit():
    p = plan(start_flow=None, step=0.5, max_flow=20.0)
    assert not p.start_given and p.start_flow_mm3_s == measure.DEFAULT_START_FLOW_MM3_S
    # 80 % of 9.6 is 7.68: there, not on a grid from 2 (7.5 would spend
    # filament below the limit for nothing)
    assert p.ramp_start(9.6) == pytest.approx(7.68)
    assert list(p.flows(p.ramp_start(9.6)))[:3] == pytest.approx([7.68, 8.18, 8.68])
    assert p.ramp_start(None) == 2.0
    assert p.ramp_start(1.0) == 2.0        # never below START_FLOW
    assert p.ramp_start(100.0) == 20.0     # never above MAX_FLOW
    assert list(p.flows(19.0)) == [19.0, 19.5, 20.0]
    given = plan(start_flow=3.0)
    assert given.start_given and given.ramp_start(9.6) == 3.0


def test_a_step_counts_its_windows_by_filament_and_time():
    # a slip closes windows sooner: a short window's noisy ends count for
    # its short time, and the median grip is per mm of filament
    windows = [dataclasses.replace(window(11.0, 11.9, 0.8, 10.0), commanded_mm=2.0),
               dataclasses.replace(window(11.9, 12.0, 0.7, 12.0), commanded_mm=0.2),
               dataclasses.replace(window(12.0, 12.1, 0.7, 12.0), commanded_mm=0.2)]
    step = measure.judge_step(windows, 10.0, 12.5, 12.0)
    assert step.measured_mm3_s == pytest.approx((0.9 * 10.0 + 0.2 * 12.0) / 1.1)
    assert step.grip == pytest.approx(0.8)     # 2 mm at 0.8, 0.4 mm at 0.7


def test_the_melted_flow_of_a_print_uses_each_window_s_own_layer():
    layers = [(0.0, 5.0), (10.0, 6.0), (20.0, 7.0)]
    windows = [window(9.0, 10.5, 1.0),     # began in layer 1: 5.0
               window(12.0, 13.0, 0.95),   # layer 2: 5.7
               window(21.0, 22.0, 0.8),    # layer 3: 5.6
               window(22.0, 23.0, None)]   # unjudged: left out
    assert measure.melted_flow(windows, layers) == pytest.approx(
        (5.0 + 5.7 + 5.6) / 3)
    assert measure.melted_flow(windows, []) is None
    assert measure.melted_flow([window(-1.0, 0.5, 0.9)], layers) is None


def test_a_print_watch_ends_on_the_median_of_its_last_windows():
    watch = measure.PrintWatch(0.9, filament_mm=3.0)
    assert watch.add(window(0.0, 1.0, 0.95)) is None
    assert watch.add(window(1.0, 2.0, 0.8)) is None     # 2 of 3 windows
    assert watch.add(window(2.0, 3.0, None)) is None    # unjudged: ignored
    assert watch.add(window(3.0, 4.0, 0.85)) is not None
    assert [w.grip for w in watch.recent] == [0.95, 0.8, 0.85]
    # windows count by their filament: a slip closes them sooner
    short = measure.PrintWatch(0.9, filament_mm=3.0)
    assert short.add(window(0.0, 1.0, 0.95)) is None
    assert short.add(window(1.0, 2.0, 0.95)) is None
    for start in (2.0, 2.5, 2.75):      # 0.5 mm windows that slipped
        # (at most 1.5 mm of 0.8 in 3.5 mm: more than half kept up)
        assert short.add(dataclasses.replace(
            window(start, start + 0.25, 0.8), commanded_mm=0.5)) is None
    # the last 3 mm: 2 mm at 0.8, 1 mm at 0.95; the median per mm is 0.8
    assert short.add(dataclasses.replace(
        window(3.0, 3.25, 0.8), commanded_mm=0.5)).grip == pytest.approx(0.8)
    assert len(short.recent) == 5
    with pytest.raises(FlowloopError, match="MIN_GRIP"):
        measure.PrintWatch(1.5)


def test_a_power_level_heats_where_its_power_holds_on_the_loss_line():
    # 32.4 % held 210 degC: the loss is 0.324 / 185 per degC over ambient
    target = measure.power_level_target(0.30, [(0.324, 210.0)], 185.0, 250.0)
    assert target == pytest.approx(25.0 + 0.30 * 185.0 / 0.324)
    # there already (within the band): heat no more
    assert measure.power_level_target(
        0.30, [(0.324, 210.0), (0.30, target)], 185.0, 250.0) is None


def test_a_power_level_fits_every_heating_so_errors_of_both_signs_cancel():
    # the true loss is 0.00175 per degC: a heat-up read 10 % high, the
    # cool-down after it 7 % low; the last one alone would put 30 % at 211
    holds = [(0.356, 210.0), (0.2636, 186.5)]
    alone = 25.0 + 0.30 * 161.5 / 0.2636
    target = measure.power_level_target(0.30, holds, 150.0, 250.0)
    truth = 25.0 + 0.30 / 0.00175
    assert abs(target - truth) < abs(alone - truth) / 2


def test_a_power_level_beyond_the_bounds_tries_the_bound_then_stops():
    assert measure.power_level_target(0.25, [(0.324, 210.0)], 185.0,
                                      250.0) == 185.0
    with pytest.raises(FlowloopError, match="POWERS: 25.0% power holds about"
                       " 16[0-9] degC, outside the profile's 185..250 degC"):
        measure.power_level_target(0.25, [(0.324, 210.0), (0.28, 185.0)],
                                   185.0, 250.0)
    with pytest.raises(FlowloopError, match="no power level"):
        measure.power_level_target(0.25, [(0.0, 210.0)], 185.0, 250.0)
