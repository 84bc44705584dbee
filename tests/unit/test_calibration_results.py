"""Every calibration result is checked finite and within its option's bounds
before it is applied (issue 36): a NaN or an overflow is refused in one line,
never handed to a stepper."""

from __future__ import annotations

import math

import pytest

from flowloop.calibrate import diff_ab
from flowloop.calibrate import flow_sensor as sensor_cal
from flowloop.control.autotemp import check_announcement
from flowloop.control.tools import check_heater_target
from flowloop.errors import FlowloopError


def _sets(readings_1, readings_2, d1=10.0, d2=150.0):
    return diff_ab.reading_sets([d1, d2], [readings_1, readings_2], "a")


def _calibrate(sets_a, force=False):
    sets_b = _sets("10.0", "149.8")
    return diff_ab.calibrate("corexy", 40.0, 40.0, sets_a, sets_b, force=force)


def test_a_huge_nominal_distance_is_refused_not_turned_into_nan():
    # DIFF_AB_CALIBRATE ... D2=1e308 set both rotation_distance to NaN
    with pytest.raises(FlowloopError, match="^A: scale: must be above 0, got "):
        _calibrate(_sets("10.01", "150.3", d2=1e308))


def test_a_huge_reading_is_refused_even_with_force():
    with pytest.raises(FlowloopError, match="must be above 0|rotation_distance"):
        _calibrate(_sets("10.01", "1e308"), force=True)


def test_a_sane_calibration_still_gives_finite_rotation_distances():
    result = _calibrate(_sets("10.01", "150.3"))
    for axis in result.axes():
        assert math.isfinite(axis.new_rotation_distance)
        assert axis.new_rotation_distance > 0


@pytest.mark.parametrize("commanded, measured", [
    (math.nan, 50.0), (50.0, math.nan), (math.inf, 50.0), (50.0, math.inf)])
def test_a_rotation_distance_from_a_broken_measurement_is_refused(commanded,
                                                                  measured):
    with pytest.raises(FlowloopError):
        sensor_cal.rotation_distance_correction(7.71, commanded, measured)


def test_a_sensor_calibration_from_a_broken_measurement_is_refused():
    with pytest.raises(FlowloopError):
        sensor_cal.fit_calibration([1.0, 2.0], [10.0, math.nan], [10.0, 10.0])


@pytest.mark.parametrize("speeds", ["1e-320,1", "0.01,1", "1,1e308"])
def test_calibration_speeds_a_toolhead_cannot_plan_are_refused(speeds):
    with pytest.raises(FlowloopError, match="^SPEEDS: "):
        sensor_cal.parse_speeds(speeds)


@pytest.mark.parametrize("flow, lead, duration, message", [
    (5.0, 1.0, math.nan, "DURATION: must be above 0 and at most 3600, got nan"),
    (5.0, 1e308, 1e308, "LEAD: must be a number from 0 to 3600, got 1e+308"),
    (math.inf, 1.0, 1.0, "FLOW: must be a number from 0 to 1000, got inf"),
])
def test_an_announcement_names_its_bound(flow, lead, duration, message):
    with pytest.raises(FlowloopError) as e:
        check_announcement(flow, lead, duration)
    assert str(e.value) == message


@pytest.mark.parametrize("temp_c", [1e308, 5.0, 301.0])
def test_an_m104_target_outside_the_heaters_range_is_refused(temp_c):
    with pytest.raises(FlowloopError, match="^S: must be 0 or from 10 to 300"):
        check_heater_target(temp_c, 10.0, 300.0)


def test_an_m104_off_or_within_range_passes():
    assert check_heater_target(0.0, 10.0, 300.0) == 0.0
    assert check_heater_target(210.0, 10.0, 300.0) == 210.0
