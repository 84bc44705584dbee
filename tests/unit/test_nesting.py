"""How deep outside JSON nests, measured without recursion
(flowloop.nesting): request bodies and Spoolman's extra fields are refused
past MAX_JSON_DEPTH before anything decodes them."""

from __future__ import annotations

import json
import time

import pytest

from flowloop.errors import FlowloopError
from flowloop.nesting import MAX_JSON_DEPTH, check_json_depth, json_depth

pytestmark = pytest.mark.unit


@pytest.mark.parametrize("text, depth", [
    ("{}", 1), ('{"a": [1, {"b": []}]}', 4), ("3", 0), ("", 0),
    ('"[[[[" ', 0),                          # brackets in a string
    ('["\\"[[[", [[]]]', 3),                 # an escaped quote inside it
    ('["\\\\", [[]]]', 3),                   # an escaped backslash before it
    ('[[[ "unterminated [[[[', 3),           # never past the end
    (b'{"a": {"b": {}}}', 3),
])
def test_the_depth_is_counted_outside_strings(text, depth):
    assert json_depth(text) == depth


def test_a_document_nested_past_the_limit_is_one_line():
    check_json_depth("[" * MAX_JSON_DEPTH + "]" * MAX_JSON_DEPTH, "it")
    with pytest.raises(FlowloopError, match="the body nests 3000 levels deep; "
                                            "at most 64 are read"):
        check_json_depth("[" * 3000 + "]" * 3000, "the body")


def test_a_large_document_is_measured_in_linear_time():
    wide = json.dumps([{"name": "x" * 50, "values": list(range(20))}] * 20000)
    quotes = '"' + '\\"' * 2_000_000                    # no string ever ends
    started = time.perf_counter()
    assert json_depth(wide) == 3 and json_depth(quotes) == 0
    assert time.perf_counter() - started < 2.0
