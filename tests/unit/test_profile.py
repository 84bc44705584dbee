"""Material profile schema, validation and the functions over the two lines."""

from __future__ import annotations

import math
import re
import unicodedata

import msgspec
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flowloop.errors import FlowloopError
from flowloop.material import profile as P
from tests.samples import make


@pytest.fixture
def herz():
    return P.profile_from_dict(make())


# --- hand-computed from the ddPrint file (ddprint-profile-format.md formulas):
# C1 = 7.5789 - 0.146*171.6312 = -17.4792552 (into air)
# C2 = 10.1356 - 0.146*210    = -20.5244    (real print)
# WP 0.5: C = -19.0018276; 12 mm^3/s needs (12 + 19.0018276)/0.146 degC


@pytest.mark.parametrize("wp, temp", [(0.0, 222.76986301369865),
                                      (0.5, 212.34128493150686),
                                      (1.0, 201.91270684931507)])
def test_temperature_for_12_mm3_s_on_herz_pla_red(herz, wp, temp):
    assert P.temp_for_flow(herz, 12.0, wp) == pytest.approx(temp, abs=1e-9)


def test_flow_at_230_degc_at_the_default_working_point(herz):
    assert P.flow_at(herz, 230.0) == pytest.approx(14.5781724, abs=1e-9)


def test_working_point_zero_is_the_real_print_line_and_one_is_into_air(herz):
    assert P.flow_at(herz, 210.0, 0.0) == pytest.approx(10.1356, abs=1e-12)
    assert P.flow_at(herz, 171.6312 + 30, 1.0) == pytest.approx(7.5789 + 0.146 * 30)


def test_kaisertech_pla_white_working_point_line():
    kaiser = P.profile_from_dict(make(air=(0.1691, 170.125, 8.0267),
                                      real=(0.1691, 224.7, 12.8127)))
    # C = (8.0267 - 0.1691*170.125 + 12.8127 - 0.1691*224.7) / 2 = -22.96275375
    assert P.temp_for_flow(kaiser, 12.0) == pytest.approx(206.75785777646365)
    assert P.flow_at(kaiser, 230.0) == pytest.approx(15.93024625)


def test_temperature_is_clamped_to_the_bounds(herz):
    assert P.temp_for_flow(herz, 30.0) == 260.0  # the line says 335.6 degC
    assert P.temp_for_flow(herz, 1.0) == 190.0  # the line says 137.0 degC
    assert P.temp_for_flow(herz, 0.0) == 190.0


def test_max_flow_at_a_measured_temperature_is_capped_at_max_temp(herz):
    at_max = 0.146 * 260 - 19.0018276
    assert P.max_flow_at(herz, 260.0) == pytest.approx(at_max)
    assert P.max_flow_at(herz, 300.0) == pytest.approx(at_max)
    assert P.max_flow_at(herz, 200.0, 0.0) == pytest.approx(0.146 * 200 - 20.5244)
    assert P.max_flow_at(herz, 100.0) == 0.0  # below the line's zero


@pytest.mark.parametrize("bad", [-0.1, 1.5, math.nan, "0.5", True])
def test_working_point_outside_0_1_is_refused(herz, bad):
    with pytest.raises(FlowloopError, match="working point"):
        P.flow_at(herz, 200.0, bad)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_inputs_are_refused(herz, bad):
    with pytest.raises(FlowloopError, match="finite"):
        P.temp_for_flow(herz, bad)
    with pytest.raises(FlowloopError, match="finite"):
        P.max_flow_at(herz, bad)


def test_negative_flow_is_refused(herz):
    with pytest.raises(FlowloopError, match=">= 0"):
        P.temp_for_flow(herz, -1.0)


def test_round_trip_through_json_keeps_every_field(herz):
    full = P.profile_from_dict(make(
        points=[{"kind": "into_air", "temp_c": 210.0, "flow_mm3_s": 9.0,
                 "grip": 0.9, "heater_pwm": 120.0}],
        ddprint={"top": {"bedTemp": 65, "kAdvance": 0.2}, "nozzle": {"slippage": 0.1}}))
    again = P.decode_profile(P.encode_profile(full))
    assert again == full
    assert P.profile_from_dict(P.profile_to_dict(full)) == full
    assert again.ddprint.top["bedTemp"] == 65 and isinstance(
        again.ddprint.top["bedTemp"], int)


@pytest.mark.parametrize("change, message", [
    (lambda d: d.update(colour="red"), "unknown field `colour`"),
    (lambda d: d["identity"].update(nozel=0.4), "unknown field `nozel`"),
    (lambda d: d["lines"]["into_air"].update(slope_mm3_s_per_c=0.0),
     "lines.into_air.slope_mm3_s_per_c must be > 0"),
    (lambda d: d["lines"]["real_print"].update(slope_mm3_s_per_c=-0.1),
     "lines.real_print.slope_mm3_s_per_c must be > 0"),
    (lambda d: d["lines"]["into_air"].update(flow_mm3_s=math.nan),
     "lines.into_air.flow_mm3_s must be a finite number"),
    (lambda d: d["bounds"].update(max_temp_c=math.inf), "bounds.max_temp_c must be"),
    (lambda d: d["bounds"].update(max_temp_c=520.0), "must be in 0..500"),
    (lambda d: d["lines"]["into_air"].update(temp_c=-5.0), "must be in 0..500"),
    (lambda d: d["bounds"].update(min_temp_c=270.0), "min_temp_c (270) must be below"),
    (lambda d: d["bounds"].update(recommended_temp_c=180.0), "recommended_temp_c"),
    (lambda d: d["identity"].update(name=""), "profile name is empty"),
    (lambda d: d["identity"].update(name="a\nb"), "control character"),
    (lambda d: d["identity"].update(printer="x\x00"), "identity.printer contains"),
    (lambda d: d.update(schema_version=2), "schema_version 2 is not supported"),
    (lambda d: d["provenance"].update(method="guess"), "Invalid enum value 'guess'"),
    (lambda d: d["identity"].update(spoolman_filament_id=0), "spoolman_filament_id"),
    (lambda d: d.update(points=[{"kind": "into_air", "temp_c": 200, "flow_mm3_s": 5,
                                 "grip": 3}]), "points[0].grip must be in 0..2"),
    (lambda d: d["lines"].update(into_air_power={
        "slope_mm3_s_per_pwm": 0.1, "pwm": 300, "flow_mm3_s": 5}),
     "lines.into_air_power.pwm must be in 0..255"),
    # U+FFFE/U+FFFF cannot be written in XML (SVG plots) even escaped
    (lambda d: d["identity"].update(name="PLA\ufffe"), "profile name contains"),
    (lambda d: d["identity"].update(filament_vendor="\uffff"), "filament_vendor"),
    (lambda d: d.update(ddprint={"top": {"bed\nTemp": 60}}), "ddprint.top key"),
    (lambda d: d.update(points=[{"kind": "into_air", "temp_c": 200, "flow_mm3_s": 5,
                                 "grip": 0.9}] * (P.MAX_POINTS + 1)),
     f"points has {P.MAX_POINTS + 1} entries, at most {P.MAX_POINTS}"),
    (lambda d: d.update(ddprint={"nozzle": {f"k{i}": i for i in range(
        P.MAX_DDPRINT_NUMBERS + 1)}}), "ddprint.nozzle has more than"),
])
def test_bad_profiles_are_refused_with_one_clear_line(change, message):
    data = make()
    change(data)
    with pytest.raises(FlowloopError) as err:
        P.profile_from_dict(data)
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_decode_reports_json_errors_in_one_line():
    with pytest.raises(FlowloopError, match="not a JSON profile"):
        P.decode_profile(b'{"identity": ')
    with pytest.raises(FlowloopError, match="must be a JSON object"):
        P.profile_from_dict([1, 2])


def test_direct_construction_is_validated_too(herz):
    with pytest.raises(FlowloopError, match="into_air.slope_mm3_s_per_c must be > 0"):
        P.Profile(identity=herz.identity, bounds=herz.bounds,
                  provenance=herz.provenance,
                  lines=P.Lines(into_air=P.FlowLine(slope_mm3_s_per_c=-1.0,
                                                    temp_c=200.0, flow_mm3_s=5.0),
                                real_print=herz.lines.real_print))


# --- real-print lines above the into-air line (real ddPrint files have them)
# JP-1/kaiser-pla-grey.json (+ pla.json bounds): Ktemp 0.1859, into air
# (180.9444 degC, 6.3317), real print (223.5 degC, 15.3515). Into air at
# 223.5 degC: 6.3317 + 0.1859 * 42.5556 = 14.2428, 1.1087 below real print;
# its intercept is 6.3317 - 0.1859 * 180.9444 = -27.30586396.


@pytest.fixture
def kaiser_grey():
    return P.profile_from_dict(make(air=(0.1859, 180.9444, 6.3317),
                                    real=(0.1859, 223.5, 15.3515)))


def test_a_real_print_line_above_into_air_is_kept_with_a_warning(kaiser_grey):
    (warning,) = P.line_warnings(kaiser_grey)
    assert "real-print line lies above the into-air line (by 1.11 mm^3/s" in warning
    assert "into-air line (the lower one)" in warning
    assert P.decode_profile(P.encode_profile(kaiser_grey)) == kaiser_grey


@pytest.mark.parametrize("wp", [0.0, 0.25, 0.5, 1.0])
def test_every_working_point_uses_the_lower_into_air_line(kaiser_grey, wp):
    # into air: flow = 0.1859 * T - 27.30586396
    assert P.flow_at(kaiser_grey, 230.0, wp) == pytest.approx(
        0.1859 * 230 - 27.30586396)
    assert P.temp_for_flow(kaiser_grey, 12.0, wp) == pytest.approx(
        (12.0 + 27.30586396) / 0.1859)
    assert P.max_flow_at(kaiser_grey, 300.0, wp) == pytest.approx(
        0.1859 * 260 - 27.30586396)


def test_crossing_lines_are_kept_and_follow_the_lower_line_past_the_crossing(herz):
    # real print with slope 0.3 through (210, 10.1356): crosses into air
    # (0.146 * T - 17.4792552) at (-17.4792552 - 10.1356 + 63) / 0.154 = 229.8 degC
    p = P.profile_from_dict(make(real=(0.3, 210.0, 10.1356)))
    (warning,) = P.line_warnings(p)
    assert "cross at 229.8 degC" in warning and "above it" in warning
    air = p.lines.into_air.line()
    assert P.flow_at(p, 250.0, 0.0) == pytest.approx(air.flow_mm3_s(250.0))
    assert P.flow_at(p, 250.0, 0.5) == pytest.approx(air.flow_mm3_s(250.0))
    assert P.flow_at(p, 200.0, 0.0) == pytest.approx(0.3 * 200 - 52.8644)
    knee = P.profile_line(p, 0.5).knee_temp_c()
    assert knee == pytest.approx(229.8, abs=0.05)
    # the knee is where temp_for_flow changes from one line to the other
    flow = air.flow_mm3_s(240.0)
    assert P.temp_for_flow(p, flow, 0.5) == pytest.approx(240.0)


def test_a_plausible_profile_has_no_warning_and_no_ceiling(herz):
    assert P.line_warnings(herz) == []
    assert all(P.profile_line(herz, wp).ceiling is None for wp in (0.0, 0.5, 1.0))


def test_line_through_a_point_and_its_inverse():
    line = P.Line.through(0.146, 210.0, 10.1356)
    assert line.flow_mm3_s(210.0) == pytest.approx(10.1356)
    assert line.temp_c(10.1356) == pytest.approx(210.0)
    assert line.flow_mm3_s(100.0) == 0.0  # below the zero: melts nothing
    assert line.knee_temp_c() is None


def test_lines_touching_at_a_bound_are_not_crossing():
    # into air - real print = 26 - 0.1*T: 7 at 190 degC, 0 at max_temp 260 degC
    air = (0.1, 200.0, 10.0)
    real = (0.2, 200.0, 4.0)
    p = P.profile_from_dict(make(air=air, real=real))
    assert P.flow_at(p, 260.0, 0.0) == pytest.approx(P.flow_at(p, 260.0, 1.0))


def test_capped_to_a_heater_never_asks_for_more_than_its_max_temp(herz):
    capped = P.capped_to_heater(herz, 235.0)
    assert capped.bounds.max_temp_c == 235.0 and capped.bounds.min_temp_c == 190.0
    assert P.temp_for_flow(capped, 30.0) == 235.0  # uncapped: 260
    assert P.max_flow_at(capped, 250.0) == pytest.approx(0.146 * 235 - 19.0018276)
    assert P.capped_to_heater(herz, 300.0) is herz
    low = P.capped_to_heater(herz, 200.0)
    assert low.bounds.recommended_temp_c == 200.0  # was 210
    with pytest.raises(FlowloopError, match="max_temp 185 degC is not above"):
        P.capped_to_heater(herz, 185.0)
    with pytest.raises(FlowloopError, match="finite"):
        P.capped_to_heater(herz, math.nan)


@settings(max_examples=150, deadline=None)
@given(st.floats(min_value=0.0, max_value=500.0), st.floats(min_value=0.0,
                                                             max_value=1e6))
def test_temperature_for_any_flow_never_exceeds_the_heater_cap(cap, flow):
    herz = P.profile_from_dict(make())
    try:
        capped = P.capped_to_heater(herz, cap)
    except FlowloopError:
        assert cap <= herz.bounds.min_temp_c
        return
    assert P.temp_for_flow(capped, flow) <= min(cap, herz.bounds.max_temp_c)


def test_active_status_is_small_and_json_able(herz):
    status = P.active_status(herz, 0.25)
    assert msgspec.json.decode(msgspec.json.encode(status)) == status
    assert status["name"] == "herz-pla-red_80" and status["working_point"] == 0.25
    line = P.Line.from_dict(status["working_line"])
    assert line.flow_mm3_s(230.0) == pytest.approx(P.flow_at(herz, 230.0, 0.25))
    assert status["working_line"]["ceiling"] is None and status["warnings"] == []


def test_active_status_carries_the_ceiling_and_the_warning(kaiser_grey):
    status = P.active_status(kaiser_grey, 0.25)
    assert msgspec.json.decode(msgspec.json.encode(status)) == status
    assert "lies above" in status["warnings"][0]
    line = P.Line.from_dict(status["working_line"])
    assert line.ceiling == kaiser_grey.lines.into_air.line()
    assert line.flow_mm3_s(230.0) == pytest.approx(P.flow_at(kaiser_grey, 230.0, 0.25))


def test_summary_lists_the_identity_fields(herz):
    s = P.summary(herz)
    assert s["name"] == "herz-pla-red_80" and s["printer"] == "UM2-1"
    assert s["nozzle_diameter_mm"] == 0.8 and s["method"] == "manual"
    assert s["warnings"] == []


def test_summary_carries_the_plausibility_warning(kaiser_grey):
    (warning,) = P.summary(kaiser_grey)["warnings"]
    assert "real-print line lies above the into-air line" in warning


# --- hypothesis: validators and the line functions --------------------------

temps = st.floats(min_value=0.0, max_value=500.0)
slopes = st.floats(min_value=1e-3, max_value=0.5)
flows = st.floats(min_value=0.0, max_value=50.0)


@st.composite
def valid_profiles(draw):
    lo = draw(st.floats(min_value=0.0, max_value=400.0))
    hi = draw(st.floats(min_value=lo + 1.0, max_value=500.0))
    rec = draw(st.floats(min_value=lo, max_value=hi))
    slope = draw(slopes)
    t_real = draw(temps)
    f_real = draw(flows)
    gap = draw(st.floats(min_value=0.0, max_value=20.0))
    # into-air: same slope, intercept gap >= 0 above the real-print line
    t_air = draw(temps)
    f_air = f_real + slope * (t_air - t_real) + gap
    if f_air < 0:
        t_air = t_real
        f_air = f_real + gap
    return P.profile_from_dict(make(air=(slope, t_air, f_air),
                                    real=(slope, t_real, f_real),
                                    bounds=(lo, rec, hi)))


@settings(max_examples=150, deadline=None)
@given(valid_profiles(), st.floats(min_value=0, max_value=1), flows)
def test_temperature_for_flow_stays_in_bounds_and_inverts_flow_at(p, wp, flow):
    temp = P.temp_for_flow(p, flow, wp)
    assert p.bounds.min_temp_c <= temp <= p.bounds.max_temp_c
    if p.bounds.min_temp_c < temp < p.bounds.max_temp_c:
        assert P.flow_at(p, temp, wp) == pytest.approx(flow, abs=1e-6, rel=1e-9)


@settings(max_examples=150, deadline=None)
@given(valid_profiles(), st.floats(min_value=0, max_value=1), temps)
def test_working_line_lies_between_the_two_lines(p, wp, temp):
    real, air = P.flow_at(p, temp, 0.0), P.flow_at(p, temp, 1.0)
    assert real - 1e-6 <= P.flow_at(p, temp, wp) <= air + 1e-6


@st.composite
def any_lines_profiles(draw):
    """Any two lines, real print above, below or crossing into air."""
    lo = draw(st.floats(min_value=100.0, max_value=300.0))
    hi = draw(st.floats(min_value=lo + 1.0, max_value=400.0))
    air = (draw(slopes), draw(st.floats(min_value=lo, max_value=hi)), draw(flows))
    real = (draw(slopes), draw(st.floats(min_value=lo, max_value=hi)), draw(flows))
    return P.profile_from_dict(make(air=air, real=real, bounds=(lo, lo, hi)))


@settings(max_examples=200, deadline=None)
@given(any_lines_profiles(), st.floats(min_value=0, max_value=1),
       st.floats(min_value=0, max_value=1), temps)
def test_no_working_line_promises_more_than_into_air_or_less_than_both(
        p, wp1, wp2, temp):
    real, air = p.lines.real_print.line(), p.lines.into_air.line()
    low, high = sorted((wp1, wp2))
    at_low, at_high = P.flow_at(p, temp, low), P.flow_at(p, temp, high)
    lowest = min(air.flow_mm3_s(temp), real.flow_mm3_s(temp))
    assert lowest - 1e-6 <= at_low <= at_high + 1e-6  # more WP, never less flow
    assert at_high <= air.flow_mm3_s(temp) + 1e-6


@settings(max_examples=200, deadline=None)
@given(any_lines_profiles(), st.floats(min_value=0, max_value=1), flows)
def test_temperature_for_flow_inverts_flow_at_on_any_lines(p, wp, flow):
    temp = P.temp_for_flow(p, flow, wp)
    if p.bounds.min_temp_c < temp < p.bounds.max_temp_c:
        assert P.flow_at(p, temp, wp) == pytest.approx(flow, abs=1e-6, rel=1e-9)
    assert P.profile_line(p, wp).temp_c(P.flow_at(p, temp, wp)) <= temp + 1e-6


@settings(max_examples=150, deadline=None)
@given(valid_profiles())
def test_valid_profiles_round_trip(p):
    assert P.decode_profile(P.encode_profile(p)) == p


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=True)
    | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3)
    | st.dictionaries(st.text(max_size=8), inner, max_size=3),
    max_leaves=10)


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(["identity", "lines", "bounds", "provenance", "points",
                        "ddprint", "schema_version"]), json_values)
def test_any_junk_in_a_field_is_refused_with_one_line_or_accepted(field, junk):
    data = make()
    data[field] = junk
    try:
        P.profile_from_dict(data)
    except FlowloopError as e:
        assert "\n" not in str(e) and str(e)


@pytest.mark.parametrize("name, message", [
    (" pad ", "begins or ends with whitespace"), ("\u00a0lead", "whitespace"),
    ("evil\u202etxt.gcode", "U+202E"), ("zero\u200bwidth", "U+200B"),
    ("\u2066isolate\u2069", "U+2066")])
def test_padded_names_and_invisible_format_characters_are_refused(name, message):
    with pytest.raises(FlowloopError, match=re.escape(message)):
        P.profile_from_dict(make(name=name))


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=40))
def test_names_round_trip_or_are_refused(name):
    try:
        p = P.profile_from_dict(make(name=name))
    except FlowloopError as e:
        assert "profile name" in str(e)
        # blank, padded with whitespace, or holding a control, line-break,
        # surrogate, non-XML or invisible format (Cf) character
        assert name != name.strip() or not name.strip() or any(
            ord(c) < 32 or 0x7f <= ord(c) <= 0x9f or c in "\u2028\u2029\ufffe\uffff"
            or 0xd800 <= ord(c) <= 0xdfff or unicodedata.category(c) == "Cf"
            for c in name)
        return
    assert P.decode_profile(P.encode_profile(p)).identity.name == name


@settings(max_examples=200, deadline=None)
@given(st.floats(allow_nan=True, allow_infinity=True))
def test_slopes_must_be_positive_finite(slope):
    data = make(air=(slope, 171.6312, 7.5789), real=(slope, 210.0, 10.1356))
    ok = math.isfinite(slope) and 0 < slope <= P.MAX_SLOPE_MM3_S_PER_C
    try:
        P.profile_from_dict(data)
    except FlowloopError as e:
        assert not ok, str(e)
        return
    assert ok


@pytest.mark.parametrize("data", [b"", b"  \n", ""])
def test_an_empty_file_is_called_empty(data):
    with pytest.raises(FlowloopError) as e:
        P.decode_profile(data)
    assert str(e.value) == "empty: no profile in it"


def test_the_profile_command_says_an_empty_file_is_empty(tmp_path, capsys):
    from flowloop import cli
    empty = tmp_path / "p.json"
    empty.write_bytes(b"")
    assert cli.main(["profile", "show", str(empty)]) == 2
    assert capsys.readouterr().err == (f"flowloop profile: error: {empty}: empty:"
                                       f" no profile in it\n")
