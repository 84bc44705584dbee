"""The fixed-power heater's watchdog rules (flowloop.control.watchdog)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from flowloop.control import watchdog
from flowloop.errors import FlowloopError
from flowloop.host.fixed_power import FixedPowerControl
from flowloop.material.profile import Bounds

pytestmark = pytest.mark.unit

LIMITS = watchdog.WatchdogLimits(min_temp_c=190.0, max_temp_c=260.0)


@given(st.floats(190.0, 260.0))
def test_a_temperature_within_the_limits_goes_on(temp):
    assert watchdog.stop_reason(LIMITS, temp_c=temp, now_s=0.0) is None


@given(st.floats(260.001, 1000.0))
def test_a_temperature_above_the_limit_ends_the_level(temp):
    reason = watchdog.stop_reason(LIMITS, temp_c=temp, now_s=0.0)
    assert "above the limit 260" in reason


@given(st.floats(-50.0, 189.999))
def test_a_temperature_below_the_profile_minimum_ends_the_level(temp):
    reason = watchdog.stop_reason(LIMITS, temp_c=temp, now_s=0.0)
    assert "below the profile's minimum 190" in reason


def test_a_reading_that_is_not_a_number_ends_the_level():
    assert "not a number" in watchdog.stop_reason(LIMITS, temp_c=math.nan,
                                                  now_s=0.0)


def test_rising_at_fixed_power_ends_the_level():
    ok = watchdog.stop_reason(LIMITS, temp_c=219.0, now_s=10.0, settled_c=210.0,
                              previous=(9.0, 218.0))
    assert ok is None
    reason = watchdog.stop_reason(LIMITS, temp_c=221.0, now_s=10.0,
                                  settled_c=210.0, previous=(9.0, 220.0))
    assert "rose to 221.0" in reason


def test_falling_faster_than_a_hotend_cools_ends_the_level():
    # sagging 2 degC/s under a rising flow is what a held heater does
    assert watchdog.stop_reason(LIMITS, temp_c=206.0, now_s=10.0,
                                settled_c=210.0, previous=(8.0, 210.0)) is None
    reason = watchdog.stop_reason(LIMITS, temp_c=200.0, now_s=10.0,
                                  settled_c=210.0, previous=(9.0, 210.0))
    assert "fell 10.0 degC/s" in reason


def test_a_sensor_fault_ends_the_level():
    assert "flow sensor fault 'missing'" in watchdog.stop_reason(
        LIMITS, temp_c=210.0, now_s=0.0, sensor_fault="missing")
    assert watchdog.stop_reason(LIMITS, temp_c=210.0, now_s=0.0,
                                sensor_fault=None) is None


def test_a_lost_host_ends_the_level():
    assert watchdog.stop_reason(LIMITS, temp_c=210.0, now_s=104.9,
                                heartbeat_s=100.0) is None
    reason = watchdog.stop_reason(LIMITS, temp_c=210.0, now_s=105.1,
                                  heartbeat_s=100.0)
    assert "has not answered for 5.1 s" in reason


def test_the_temperature_rule_comes_first():
    reason = watchdog.stop_reason(LIMITS, temp_c=300.0, now_s=100.0,
                                  sensor_fault="missing", heartbeat_s=0.0)
    assert "above the limit" in reason


@pytest.mark.parametrize("kwargs, message", [
    ({"min_temp_c": 200.0, "max_temp_c": 200.0}, "must be below"),
    ({"min_temp_c": 200.0, "max_temp_c": math.nan}, "finite"),
    ({"min_temp_c": 180.0, "max_temp_c": 200.0, "host_timeout_s": 0.0},
     "host_timeout_s must be above 0"),
])
def test_bad_limits_are_refused(kwargs, message):
    with pytest.raises(FlowloopError, match=message):
        watchdog.WatchdogLimits(**kwargs)


def test_the_fixed_power_cutoff_holds_the_power_until_a_rule_says_stop():
    cutoff = watchdog.FixedPowerCutoff(LIMITS, 0.6)
    assert cutoff.power_at(10.0, 215.0) == 0.6     # no heartbeat yet: no host rule
    cutoff.heartbeat_s = 10.0
    assert cutoff.power_at(14.0, 215.0) == 0.6 and cutoff.stopped is None
    # the host went quiet: cut, and cut for good (a late heartbeat or a good
    # reading does not bring the power back)
    assert cutoff.power_at(15.5, 215.0) == 0.0
    assert cutoff.stopped.startswith("the host has not answered for 5.5 s")
    cutoff.heartbeat_s = 15.5
    assert cutoff.power_at(16.0, 215.0) == 0.0


@given(st.floats(allow_nan=True, allow_infinity=True))
def test_the_fixed_power_cutoff_never_heats_outside_the_limits(temp):
    cutoff = watchdog.FixedPowerCutoff(LIMITS, 1.0)
    power = cutoff.power_at(0.0, temp)
    inside = math.isfinite(temp) and LIMITS.min_temp_c <= temp <= LIMITS.max_temp_c
    assert power == (1.0 if inside else 0.0)
    assert (cutoff.stopped is None) == inside


def test_a_measurements_watchdog_is_built_from_its_bounds_in_one_place():
    bounds = Bounds(min_temp_c=190.0, max_temp_c=240.0, recommended_temp_c=215.0)
    limits, rules = watchdog.for_measurement(bounds, host_timeout_s=7.0)
    assert (limits.min_temp_c, limits.max_temp_c, limits.host_timeout_s) == (
        190.0, 240.0, 7.0)
    assert rules(temp_c=215.0, now_s=0.0) is None
    assert rules(temp_c=241.0, now_s=0.0) == watchdog.temperature_stop(
        limits, 241.0)
    assert watchdog.for_measurement(bounds)[0].host_timeout_s == \
        watchdog.DEFAULT_HOST_TIMEOUT_S


class Heater:
    """What a heater control is given: set_pwm."""

    def __init__(self):
        self.pwm = []

    def set_pwm(self, read_time, value):
        self.pwm.append((read_time, value))


def test_the_fixed_power_control_holds_its_power_until_a_rule_cuts_it():
    heater = Heater()
    control = FixedPowerControl(heater, 0.4, LIMITS)
    control.heartbeat(10.0)
    control.temperature_update(10.5, 210.0, 190.0)
    assert heater.pwm == [(10.5, 0.4)] and control.stopped is None
    # the host silent too long: cut, and for good
    control.temperature_update(10.5 + LIMITS.host_timeout_s + 1, 210.0, 190.0)
    control.heartbeat(20.0)
    control.temperature_update(20.5, 210.0, 190.0)
    assert [p for _, p in heater.pwm] == [0.4, 0.0, 0.0]
    assert control.stopped.startswith("the host has not answered")
    assert control.check_busy(0.0, 210.0, 190.0) is False
    # what Kalico's heaters ask of it
    assert control.get_profile() == {'name': 'fixed_power',
                                     'control': 'fixed_power'}
    assert control.get_type() == 'fixed_power'
    control.check_valid()
    control.update_smooth_time(1.0)
    control.temperature_update(21.0, 210.0, 190.0, 205.0)
    assert heater.pwm[-1] == (21.0, 0.0)
