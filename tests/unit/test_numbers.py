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
