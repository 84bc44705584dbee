"""One parser for every list of numbers a user types (readings, probes, speeds)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from flowloop.errors import FlowloopError
from flowloop.numbers import parse_numbers

finite = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False)


@given(st.lists(finite, min_size=1, max_size=9),
       st.sampled_from([",", ", ", " ", " , "]))
def test_numbers_round_trip_through_text(values, sep):
    assert parse_numbers(sep.join(repr(v) for v in values), "A1") == tuple(values)


@given(st.text(max_size=40))
def test_any_text_parses_to_finite_positive_numbers_or_one_line_error(text):
    try:
        values = parse_numbers(text, "A1", positive=True)
    except FlowloopError as e:
        assert "\n" not in str(e) and str(e).startswith("A1: ")
    else:
        assert values and all(math.isfinite(v) and v > 0 for v in values)


@pytest.mark.parametrize("text, kw, message", [
    ("", {}, "A1: no readings given"),
    (" , ", {}, "A1: no readings given"),
    ("10,,x", {}, "A1: 'x' is not a number"),
    ("10,inf", {}, "A1: 'inf' is not a finite number"),
    ("nan", {}, "A1: 'nan' is not a finite number"),
    ("10,-1", {"positive": True}, "A1: reading -1 must be positive"),
    ("0", {"positive": True}, "A1: reading 0 must be positive"),
    ("1,2", {"count": 3}, "A1: needs 3 readings, got 2"),
    ("1", {"minimum_count": 2}, "A1: needs at least 2 readings, got 1"),
])
def test_bad_text_is_refused_naming_the_parameter(text, kw, message):
    with pytest.raises(FlowloopError) as e:
        parse_numbers(text, "A1", what="reading", **kw)
    assert str(e.value) == message


def test_signs_trailing_commas_and_sequences_are_accepted():
    assert parse_numbers("-86.6,-50,0.3,", "--probe", count=3) == (-86.6, -50.0, 0.3)
    assert parse_numbers([1, "2.5"], "A1", positive=True) == (1.0, 2.5)


@pytest.mark.parametrize("text", ["9,9", "150,12", "9,9 9,8", "-0,5", "0,5, 0,6"])
def test_a_decimal_comma_is_refused_with_what_to_type_instead(text):
    with pytest.raises(FlowloopError) as e:
        parse_numbers(text, "A1", what="reading", decimal_comma_refused=True)
    message = str(e.value)
    assert message.startswith("A1: '") and "has a decimal comma" in message
    assert "write " in message and "separate readings with spaces" in message


@pytest.mark.parametrize("text, values", [
    ("9.9,9.8", (9.9, 9.8)), ("9 9", (9.0, 9.0)), ("0,100,0", (0.0, 100.0, 0.0)),
    ("9, 9", (9.0, 9.0)), ("-86.6,-50,0.3", (-86.6, -50.0, 0.3))])
def test_lists_that_cannot_be_a_decimal_comma_are_read_as_lists(text, values):
    assert parse_numbers(text, "A1", decimal_comma_refused=True) == values


def test_where_whole_numbers_are_usual_a_comma_separates_them():
    # G-code parameters cannot hold spaces: SPEEDS=1,2 and TEMPS=200,220 are lists
    assert parse_numbers("1,2", "SPEEDS") == (1.0, 2.0)


# --- one number: read_number, read_integer, check_result ---------------------
from flowloop.numbers import check_result, read_integer, read_number  # noqa: E402


@pytest.mark.parametrize("text, bounds, message", [
    ("nan", {"above": 0.0}, "LENGTH: must be above 0, got nan"),
    ("inf", {"minimum": 1.0, "maximum": 200.0},
     "LENGTH: must be a number from 1 to 200, got inf"),
    ("-inf", {}, "LENGTH: must be a finite number, got -inf"),
    ("1e-320", {"above": 0.0}, "LENGTH: must be above 0, got 1e-320"),
    ("1_000", {"above": 0.0}, "LENGTH: must be above 0, got 1_000"),
    ("\uff11\uff12", {"above": 0.0}, "LENGTH: must be above 0, got '\\uff11\\uff12'"),
    ("0", {"above": 0.0, "maximum": 10.0},
     "LENGTH: must be above 0 and at most 10, got 0"),
    ("1", {"above": 0.0, "below": 1.0}, "LENGTH: must be above 0 and below 1, got 1"),
    ("1e308", {"maximum": 2.0}, "LENGTH: must be at most 2, got 1e308"),
    ("x" * 5000, {"minimum": 0.0},
     "LENGTH: must be at least 0, got " + "x" * 37 + "..."),
    ("", {}, "LENGTH: must be a finite number, got ''"),
])
def test_a_bad_number_is_refused_with_its_bound_in_one_line(text, bounds, message):
    with pytest.raises(FlowloopError) as e:
        read_number(text, "LENGTH", **bounds)
    assert str(e.value) == message


@pytest.mark.parametrize("text, value", [
    ("12", 12.0), ("-0.5", -0.5), ("+.5", 0.5), ("1e-3", 0.001), ("1E3", 1000.0),
    (" 7 ", 7.0), ("5.", 5.0)])
def test_plain_decimal_text_is_read(text, value):
    assert read_number(text, "X") == value


def test_a_missing_parameter_gives_its_default_or_is_refused():
    assert read_number(None, "X", 3.0) == 3.0
    assert read_number(None, "X", None, above=0.0) is None
    with pytest.raises(FlowloopError, match="^X: missing$"):
        read_number(None, "X")


@pytest.mark.parametrize("text", ["1.0", "1_0", "\uff11", "nan", "1e1", "0x1", "2"])
def test_a_switch_takes_plain_whole_numbers_only(text):
    with pytest.raises(FlowloopError) as e:
        read_integer(text, "ENABLE", minimum=0, maximum=1)
    assert str(e.value).startswith("ENABLE: must be a whole number from 0 to 1, got ")


def test_whole_numbers_are_read():
    assert read_integer("1", "ENABLE", minimum=0, maximum=1) == 1
    assert read_integer("+12", "LAYER", minimum=1) == 12


@given(st.text(max_size=60))
def test_any_text_is_a_number_within_the_bound_or_one_line_naming_it(text):
    try:
        value = read_number(text, "FLOW", above=0.0, maximum=1000.0)
    except FlowloopError as e:
        message = str(e)
        assert "\n" not in message and len(message) < 120
        assert message.startswith("FLOW: must be above 0 and at most 1000, got ")
    else:
        assert math.isfinite(value) and 2.2e-308 < value <= 1000.0


@pytest.mark.parametrize("text", ["1_000", "\uff11", "nan", "1e-320x"])
def test_lists_read_numbers_as_single_parameters_do(text):
    with pytest.raises(FlowloopError, match="not a"):
        parse_numbers(f"1,{text}", "SPEEDS")


def test_a_list_refuses_subnormal_values_where_they_must_be_positive():
    with pytest.raises(FlowloopError, match="must be positive"):
        parse_numbers("1,1e-320", "SPEEDS", what="speed", positive=True)


@pytest.mark.parametrize("value", [math.nan, math.inf, -1.0, 0.0, 1e-320])
def test_a_computed_value_outside_its_options_bound_is_refused(value):
    with pytest.raises(FlowloopError) as e:
        check_result(value, "stepper_x: rotation_distance", above=0.0)
    assert str(e.value).startswith("stepper_x: rotation_distance: must be above 0,")


def test_a_computed_value_within_its_bound_passes():
    assert check_result(40.123, "rotation_distance", above=0.0) == 40.123
