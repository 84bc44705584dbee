"""Active profiles as typed records, the Spoolman rule, and request numbers."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from flowloop.errors import FlowloopError
from flowloop.material import active as A
from flowloop.material.profile import profile_from_dict
from tests.samples import make


def profile(name, filament_id=None):
    return profile_from_dict(make(name=name, identity={
        "spoolman_filament_id": filament_id}))


def spool(filament_id):
    return {"id": 7, "filament": {"id": filament_id, "name": "PLA red"}}


PROFILES = {p.name: p for p in (profile("zeta pla", 3), profile("alpha pla", 3),
                                 profile("petg", 4), profile("unlinked"))}


def test_the_profile_naming_the_spools_filament_becomes_active():
    entry = A.follow_spool(spool(4), PROFILES, None)
    assert entry == A.ActiveProfile(name="petg", working_point=0.5)


def measured(name, filament_id, measured_at):
    return profile_from_dict(make(name=name, identity={
        "spoolman_filament_id": filament_id},
        provenance={"method": "manual", "measured_at": measured_at}))


def test_of_several_profiles_for_one_filament_the_latest_measured_wins():
    # the rule of both paths of the link: with hotend: the local candidate
    # for Spoolman's field, without it the profile activated
    older = measured("alpha pla", 3, "2026-01-05T10:00:00+00:00")
    later = measured("zeta pla", 3, "2026-03-01T10:00:00+00:00")
    for order in ((older, later), (later, older)):
        profiles = {p.name: p for p in order}
        assert A.profile_for_filament(profiles, 3) is later
        assert A.follow_spool(spool(3), profiles, None).name == "zeta pla"


def test_of_profiles_measured_at_the_same_time_the_first_by_name_wins():
    backwards = dict(reversed(list(PROFILES.items())))
    assert A.follow_spool(spool(3), PROFILES, None).name == "alpha pla"
    assert A.follow_spool(spool(3), backwards, None).name == "alpha pla"


def test_an_activation_keeps_the_extruders_working_point():
    current = A.ActiveProfile(name="unlinked", working_point=0.8)
    assert A.keeping_working_point("petg", current, 0.3) == \
        A.ActiveProfile(name="petg", working_point=0.8)
    assert A.keeping_working_point("petg", None, 0.3) == \
        A.ActiveProfile(name="petg", working_point=0.3)


def test_following_a_spool_keeps_the_extruders_working_point():
    current = A.ActiveProfile(name="unlinked", working_point=0.8)
    assert A.follow_spool(spool(4), PROFILES, current).working_point == 0.8
    assert A.follow_spool(spool(4), PROFILES, None, default_wp=0.3).working_point \
        == 0.3


@pytest.mark.parametrize("record", [
    spool(99),                      # no profile names this filament
    {"id": 7, "filament": {}},      # no filament id
    {"id": 7},                      # no filament
    {"id": 7, "filament": {"id": "3"}},
    {"id": 7, "filament": {"id": True}},
    [3], None, "spool",
])
def test_a_spool_no_profile_names_leaves_the_active_profile_alone(record):
    assert A.follow_spool(record, PROFILES, None) is None


def test_stored_active_profiles_round_trip_as_typed_records():
    active = {"extruder1": A.ActiveProfile(name="petg", working_point=0.25),
              "extruder": A.ActiveProfile(name="alpha pla")}
    stored = A.active_to_stored(active)
    assert stored == {"extruder": {"name": "alpha pla", "working_point": 0.5},
                      "extruder1": {"name": "petg", "working_point": 0.25}}
    assert A.active_from_stored(stored) == (active, [])


@pytest.mark.parametrize("entry, message", [
    (("heater_bed", {"name": "x"}), "not an extruder"),
    (("extruder1", {"name": "x", "colour": "red"}), "unknown field"),
    (("extruder1", {"name": "x", "working_point": 2.0}), "0..1"),
    (("extruder1", {"name": " x"}), "whitespace"),
    (("extruder1", {}), "missing required field `name`"),
    (("extruder1", "x"), "Expected `object`"),
])
def test_a_damaged_activation_is_left_out_and_the_others_kept(entry, message):
    good = {"name": "petg", "working_point": 0.25}
    active, skipped = A.active_from_stored(dict([entry], extruder=good))
    assert active == {"extruder": A.ActiveProfile(name="petg", working_point=0.25)}
    assert len(skipped) == 1 and message in skipped[0] and "\n" not in skipped[0]


def test_an_active_record_that_is_not_an_object_is_refused():
    with pytest.raises(FlowloopError, match="must be an object, got list"):
        A.active_from_stored([])


@pytest.mark.parametrize("value, number", [
    (0, 0.0), (1, 1.0), (0.25, 0.25), ("0.7", 0.7), (" 0.5 ", 0.5), ("1e-1", 0.1)])
def test_a_working_point_is_a_number_or_its_text_in_0_to_1(value, number):
    assert A.working_point_arg(value) == number


@pytest.mark.parametrize("value, shown", [
    ("abc", "'abc'"), ("", "''"), ("nan", "'nan'"), ("inf", "'inf'"),
    ("1.5", "'1.5'"), (-0.1, "-0.1"), (math.nan, "nan"), (True, "true"),
    (None, "null"), ([0.5], "[0.5]"), ({"wp": 1}, '{"wp":1}'),
    ("x" * 100, "'" + "x" * 36 + "...")])
def test_a_bad_working_point_names_the_parameter_the_value_and_the_range(value,
                                                                         shown):
    with pytest.raises(FlowloopError) as err:
        A.working_point_arg(value)
    assert str(err.value) == (f"working_point: got {shown}; accepts a number from "
                              f"0 (real print) to 1 (into air)")


@given(st.one_of(st.floats(), st.text(max_size=20), st.integers(), st.none(),
                 st.booleans(), st.lists(st.floats(), max_size=3)))
def test_any_value_is_a_working_point_or_a_one_line_refusal(value):
    try:
        wp = A.working_point_arg(value)
    except FlowloopError as e:
        assert str(e).startswith("working_point: got ") and "\n" not in str(e)
    else:
        assert 0.0 <= wp <= 1.0


def test_the_cli_names_a_bad_wp_the_same_way(capsys):
    from flowloop import cli
    with pytest.raises(SystemExit):
        cli.main(["profile", "show", "--wp", "abc", "any.json"])
    err = capsys.readouterr().err
    assert ("argument --wp: got 'abc'; accepts a number from 0 (real print) to 1 "
            "(into air)") in err


def test_a_spool_goes_to_the_tool_that_prints_unless_the_link_names_one():
    from flowloop.material.active import spool_extruder
    assert spool_extruder(None, "extruder1") == "extruder1"
    assert spool_extruder("extruder", "extruder1") == "extruder"
    # klippy did not say (not connected, no answer): the first tool
    assert spool_extruder(None, None) == "extruder"
    assert spool_extruder(None, "") == "extruder"
