"""Profile names: one line of visible text that round-trips through every
endpoint (an HTTP query strips whitespace; format characters hide text)."""

from __future__ import annotations

import unicodedata

import pytest
from hypothesis import given
from hypothesis import strategies as st

from flowloop.errors import FlowloopError
from flowloop.material.profile import MAX_NAME_CHARS, check_name


@pytest.mark.parametrize("name", ["herz-pla-red_80", "a.b.c", "üñï 0.4 mm",
                                  "two  inner  spaces", "日本語", "a" * MAX_NAME_CHARS])
def test_visible_one_line_names_are_kept_as_they_are(name):
    assert check_name(name) == name


@pytest.mark.parametrize("name", [" pad ", "pad ", " pad", "\u00a0nbsp", "nbsp\u00a0",
                                  "\u3000ideographic", "end\u2003"])
def test_leading_or_trailing_whitespace_is_refused(name):
    with pytest.raises(FlowloopError, match="begins or ends with whitespace"):
        check_name(name)


@pytest.mark.parametrize("char", ["\u202e", "\u202d", "\u200b", "\u200e", "\u2066",
                                  "\u2067", "\u2068", "\u2069", "\ufeff", "\u00ad"])
def test_invisible_format_characters_are_refused_by_code_point(char):
    with pytest.raises(FlowloopError) as err:
        check_name(f"pla{char}red")
    assert f"U+{ord(char):04X}" in str(err.value)


@given(st.text(min_size=1, max_size=40))
def test_an_accepted_name_survives_stripping_and_has_no_format_character(name):
    try:
        check_name(name)
    except FlowloopError as e:
        assert "\n" not in str(e)
    else:
        assert name == name.strip()
        assert not any(unicodedata.category(c) == "Cf" for c in name)
