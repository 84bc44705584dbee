"""Fitting a profile's lines to measured points (flowloop.material.fit)."""

from __future__ import annotations

import math

import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from flowloop.errors import FlowloopError
from flowloop.material import fit
from flowloop.material.profile import (
    Bounds,
    MeasuredPoint,
    check_profile,
    profile_from_dict,
)

pytestmark = pytest.mark.unit

BOUNDS = Bounds(min_temp_c=190.0, recommended_temp_c=210.0, max_temp_c=260.0)


def point(temp_c, flow, pwm=None, kind="into_air"):
    return MeasuredPoint(kind=kind, temp_c=temp_c, flow_mm3_s=flow, grip=0.85,
                         heater_pwm=pwm)


@settings(max_examples=200, deadline=None)
@given(slope=st.floats(0.02, 0.5), flow_at_200=st.floats(2.0, 30.0),
       temps=st.lists(st.floats(180.0, 290.0), min_size=3, max_size=8),
       noise=st.lists(st.floats(-1.0, 1.0), min_size=8, max_size=8),
       noise_mm3_s=st.floats(0.0, 0.3))
def test_a_line_is_recovered_from_noisy_points_within_its_stated_uncertainty(
        slope, flow_at_200, temps, noise, noise_mm3_s):
    assume(max(temps) - min(temps) >= 20.0)
    intercept = flow_at_200 - 200.0 * slope
    flows = [slope * t + intercept + noise_mm3_s * e
             for t, e in zip(temps, noise)]
    mean = sum(temps) / len(temps)
    sxx = sum((t - mean) ** 2 for t in temps)
    n = len(temps)
    # Points that support a line: the fit's SSE is at most the noise's
    # (n * noise^2), so its slope error stays under 20 % of the slope and
    # the 25 % refusal cannot apply (noisier points are refused, rightly).
    assume(noise_mm3_s * math.sqrt(n / ((n - 2) * sxx)) <= 0.2 * slope)
    result = fit.fit_line(temps, flows, "temperature", fit.MIN_TEMP_SPREAD_C)
    # The noise is bounded by noise_mm3_s, so the slope error is too: an
    # OLS slope moves at most sum|x - mean| * noise / Sxx.
    bound = sum(abs(t - mean) for t in temps) * noise_mm3_s / sxx
    assert abs(result.slope - slope) <= bound + 1e-9
    assert abs(result.flow_at(mean) - (slope * mean + intercept)) \
        <= noise_mm3_s + 1e-9
    assert result.slope_stderr is not None and result.slope_stderr >= 0
    assert result.n == len(temps)
    line = result.flow_line().line()
    assert math.isclose(line.flow_mm3_s(230.0), result.flow_at(230.0),
                        rel_tol=1e-9)


@given(temps=st.lists(st.floats(150.0, 300.0), min_size=3, max_size=6),
       slope=st.floats(0.05, 0.3))
def test_exact_points_give_the_line_and_zero_error(temps, slope):
    assume(max(temps) - min(temps) >= fit.MIN_TEMP_SPREAD_C)
    flows = [slope * t - 30.0 + 60.0 for t in temps]
    result = fit.fit_line(temps, flows, "temperature", fit.MIN_TEMP_SPREAD_C)
    assert math.isclose(result.slope, slope, rel_tol=1e-6)
    assert math.isclose(result.intercept, 30.0, abs_tol=1e-6)
    assert result.slope_stderr == pytest.approx(0.0, abs=1e-6)


def test_two_points_give_their_line_with_an_unknown_uncertainty():
    result = fit.fit_line([200.0, 240.0], [10.0, 18.0], "temperature", 5.0)
    assert result.slope == pytest.approx(0.2)
    assert result.intercept == pytest.approx(-30.0)
    assert result.slope_stderr is None
    assert "uncertainty unknown" in result.describe("degC")


@given(temp=st.floats(150.0, 300.0), n=st.integers(1, 6),
       flow=st.floats(1.0, 30.0))
def test_points_at_one_temperature_are_refused(temp, n, flow):
    with pytest.raises(FlowloopError, match="temperature fit"):
        fit.fit_line([temp] * n, [flow + i for i in range(n)], "temperature",
                     fit.MIN_TEMP_SPREAD_C)


@given(slope=st.floats(-0.5, 0.0))
def test_a_flow_that_does_not_rise_with_temperature_is_refused(slope):
    temps = [200.0, 220.0, 240.0]
    flows = [20.0 + slope * (t - 200.0) for t in temps]
    with pytest.raises(FlowloopError, match="does not rise"):
        fit.fit_line(temps, flows, "temperature", fit.MIN_TEMP_SPREAD_C)


def test_scattered_points_are_refused():
    # slope 0.1 from the ends, but the middle point is 5 mm^3/s off
    with pytest.raises(FlowloopError, match="scatter too much"):
        fit.fit_line([200.0, 210.0, 220.0], [10.0, 16.0, 12.0], "temperature",
                     fit.MIN_TEMP_SPREAD_C)


@pytest.mark.parametrize("xs, flows, message", [
    ([], [], "at least 2 points"),
    ([200.0], [10.0], "at least 2 points"),
    ([200.0, math.nan], [10.0, 12.0], "finite"),
    ([200.0, 220.0], [10.0, math.inf], "finite"),
    ([200.0, 220.0], [10.0], "2 temperatures but 1 flows"),
])
def test_degenerate_input_is_refused_in_one_line(xs, flows, message):
    with pytest.raises(FlowloopError, match=message) as err:
        fit.fit_line(xs, flows, "temperature", fit.MIN_TEMP_SPREAD_C)
    assert "\n" not in str(err.value)


def test_the_power_line_needs_every_points_power_and_is_optional():
    points = [point(200.0, 10.0), point(220.0, 12.0, 80.0),
              point(240.0, 14.0, 100.0)]
    lines = fit.fit_points("into_air", points)
    assert lines.power is None
    assert "no heater power" in lines.power_refused
    assert lines.temperature.slope == pytest.approx(0.1)


def test_fit_points_uses_only_its_kind():
    points = [point(200.0, 10.0, 70.0), point(220.0, 12.0, 90.0),
              point(240.0, 14.0, 110.0), point(210.0, 3.0, 80.0, "real_print")]
    lines = fit.fit_points("into_air", points)
    assert lines.temperature.n == 3
    assert lines.power.slope == pytest.approx(0.1)


def test_a_measured_profile_keeps_the_base_other_line_and_points():
    base = profile_from_dict({
        "identity": {"name": "base", "nozzle_diameter_mm": 0.6},
        "lines": {"into_air": {"slope_mm3_s_per_c": 0.1, "temp_c": 200.0,
                               "flow_mm3_s": 4.5},
                  "real_print": {"slope_mm3_s_per_c": 0.08, "temp_c": 200.0,
                                 "flow_mm3_s": 3.5}},
        "bounds": {"min_temp_c": 190.0, "recommended_temp_c": 210.0,
                   "max_temp_c": 260.0},
        "points": [{"kind": "real_print", "temp_c": 210.0, "flow_mm3_s": 4.0,
                    "grip": 0.9},
                   {"kind": "into_air", "temp_c": 210.0, "flow_mm3_s": 5.0,
                    "grip": 0.9}],
        "provenance": {"method": "manual"}})
    points = [point(200.0, 10.0, 70.0), point(220.0, 12.0, 90.0),
              point(240.0, 14.0, 110.0)]
    lines = fit.fit_points("into_air", points)
    profile = fit.measured_profile("new", base, lines, points, base.bounds,
                                   0.4, 1.75, 0.9, "test",
                                   measured_at="2026-11-23T07:00:00Z")
    check_profile(profile)
    assert profile.name == "new"
    assert profile.identity.nozzle_diameter_mm == 0.6
    assert profile.lines.real_print == base.lines.real_print
    assert profile.lines.into_air.slope_mm3_s_per_c == pytest.approx(0.1)
    assert profile.lines.into_air.line().flow_mm3_s(220.0) == pytest.approx(12.0)
    assert profile.lines.into_air_power.slope_mm3_s_per_pwm == pytest.approx(0.1)
    # the base's earlier into-air point is replaced, its real-print one kept
    assert [p.kind for p in profile.points] == ["real_print"] + ["into_air"] * 3
    assert profile.provenance.method == "into_air"
    assert profile.provenance.min_grip == 0.9
    assert "slope +/-" in profile.provenance.note


def test_a_measured_profile_without_a_base_says_its_other_line_is_a_copy():
    points = [point(200.0, 10.0), point(240.0, 14.0)]
    lines = fit.fit_points("into_air", points)
    profile = fit.measured_profile("fresh", None, lines, points, BOUNDS, 0.4,
                                   1.75, 0.85, "test")
    assert profile.lines.real_print == profile.lines.into_air
    assert "not measured" in profile.provenance.note
    assert "uncertainty unknown" in profile.provenance.note
    assert profile.provenance.measured_at.endswith("Z")


def test_one_point_gives_the_line_with_the_given_slope():
    real = point(210.0, 5.5, kind="real_print")
    lines = fit.one_point_lines("real_print", real, 0.12)
    line = lines.temperature.flow_line().line()
    assert line.slope_mm3_s_per_c == 0.12
    assert line.flow_mm3_s(210.0) == pytest.approx(5.5)
    assert lines.power is None and lines.temperature.n == 1
    with pytest.raises(FlowloopError, match="slope 0 must be above 0"):
        fit.one_point_lines("real_print", real, 0.0)
    base = profile_from_dict({
        "identity": {"name": "base", "nozzle_diameter_mm": 0.4},
        "lines": {"into_air": {"slope_mm3_s_per_c": 0.12, "temp_c": 210.0,
                               "flow_mm3_s": 6.0},
                  "real_print": {"slope_mm3_s_per_c": 0.1, "temp_c": 210.0,
                                 "flow_mm3_s": 4.0}},
        "bounds": {"min_temp_c": 190.0, "recommended_temp_c": 210.0,
                   "max_temp_c": 260.0},
        "provenance": {"method": "manual"}})
    profile = fit.measured_profile("printed", base, lines, [real], base.bounds,
                                   0.4, 1.75, 0.9, "test")
    assert profile.lines.into_air == base.lines.into_air
    assert profile.lines.real_print.line().flow_mm3_s(210.0) == pytest.approx(5.5)
    assert profile.provenance.method == "real_print"
    assert "one point" in profile.provenance.note
