"""Profiles on the filament in Spoolman: the field's document, bad data
named by filament, hotend keys, and which of two writers wins."""

from __future__ import annotations

import json

import pytest

from flowloop.errors import FlowloopError
from flowloop.material import spoolman_field as sf
from flowloop.material.profile import profile_from_dict
from tests.samples import make

pytestmark = pytest.mark.unit


def profile(name="red pla", when="2026-11-01T10:00:00Z", filament=3, **kw):
    data = make(name=name, identity={"spoolman_filament_id": filament}, **kw)
    data["provenance"]["measured_at"] = when
    return profile_from_dict(data)


def filament(value, fid=3, name="PLA red"):
    return {"id": fid, "name": name, "extra": {sf.FIELD_KEY: value}}


def test_the_field_round_trips_as_spoolman_keeps_extra_fields():
    profiles = {"revo_0.4": profile(), "v6_0.6": profile(name="red pla 0.6")}
    value = sf.field_value(profiles)
    # Spoolman keeps each extra value as JSON text: ours is a JSON string
    assert isinstance(json.loads(value), str)
    assert sf.read_field(filament(value)) == profiles


def test_a_filament_without_the_field_has_no_profiles():
    assert sf.read_field({"id": 1, "name": "x", "extra": {}}) == {}
    assert sf.read_field({"id": 1, "name": "x"}) == {}
    assert sf.read_field(filament('""')) == {}


@pytest.mark.parametrize("value, says", [
    ("not json", "is not JSON"),
    (json.dumps(json.dumps({"flowloop": 99, "profiles": {}})), "version 1"),
    (json.dumps(json.dumps({"flowloop": 1})), "no profiles object"),
    (json.dumps(json.dumps({"flowloop": 1, "profiles": {"Bad Key": {}}})),
     "hotend 'Bad Key'"),
    (json.dumps(json.dumps({"flowloop": 1, "profiles": {"revo_0.4": {"x": 1}}})),
     "hotend 'revo_0.4'"),
])
def test_bad_data_is_refused_in_one_line_naming_the_filament(value, says):
    with pytest.raises(FlowloopError) as e:
        sf.read_field(filament(value))
    message = str(e.value)
    assert message.startswith("Spoolman filament 3 ('PLA red'): its"
                              " flowloop_profiles field")
    assert says in message and "\n" not in message


def test_a_profile_that_fails_validation_is_refused():
    bad = make(name="red pla", bounds=(250.0, 210.0, 200.0))   # min above max
    value = json.dumps(json.dumps({"flowloop": 1, "profiles": {"revo_0.4": bad}}))
    with pytest.raises(FlowloopError, match="hotend 'revo_0.4'"):
        sf.read_field(filament(value))


@pytest.mark.parametrize("key", ["revo_0.4", "v6-0.6", "a", "x" * 64])
def test_hotend_keys(key):
    assert sf.check_hotend(key) == key


@pytest.mark.parametrize("key", ["", "Revo", "revo 0.4", "x" * 65, None, 4, "_x"])
def test_bad_hotend_keys_are_refused(key):
    with pytest.raises(FlowloopError, match="is not a hotend key"):
        sf.check_hotend(key)


def test_the_later_measurement_wins_whichever_printer_writes_last():
    old = profile(when="2026-11-01T10:00:00Z")
    new = profile(when="2026-11-02T09:00:00Z", real=(0.15, 210.0, 11.0))
    other = profile(name="red pla 0.6")
    # printer A wrote the newer one; B merges its older one afterwards
    field = sf.merged({}, "revo_0.4", new)
    assert sf.merged(field, "revo_0.4", old)["revo_0.4"] == new
    # the other order gives the same field
    assert sf.merged(sf.merged({}, "revo_0.4", old), "revo_0.4", new) == field
    # another hotend's entry is kept either way
    both = sf.merged(sf.merged({"v6_0.6": other}, "revo_0.4", old), "revo_0.4", new)
    assert both == {"v6_0.6": other, "revo_0.4": new}


def test_the_same_time_goes_to_the_writer():
    a = profile(when="2026-11-01T10:00:00Z")
    b = profile(when="2026-11-01T10:00:00Z", real=(0.15, 210.0, 11.0))
    assert sf.merged({"revo_0.4": a}, "revo_0.4", b)["revo_0.4"] == b


@pytest.mark.parametrize("value", [
    "[" * 3000 + "]" * 3000,                               # the field itself
    json.dumps("[" * 3000 + "]" * 3000),                   # inside its string
    json.dumps(json.dumps({"flowloop": 1, "profiles": {"revo_0.4": {
        "deep": json.loads("[" * 200 + "]" * 200)}}})),
])
def test_a_field_nested_too_deep_is_one_line_not_a_recursion_error(value):
    with pytest.raises(FlowloopError, match="nests .* levels deep; at most 64"):
        sf.read_field(filament(value))


def test_a_filament_id_spoolman_cannot_hold_is_refused():
    assert sf.check_filament_id(sf.MAX_FILAMENT_ID) == 2 ** 31 - 1
    for fid in (0, 2 ** 31, 10 ** 30):
        with pytest.raises(FlowloopError, match="Spoolman numbers filaments"):
            sf.check_filament_id(fid)


def test_work_spoolman_could_not_take_is_tried_again_sooner_then_later():
    waits = [sf.retry_delay_s(n) for n in range(12)]
    assert waits[:4] == [2.0, 4.0, 8.0, 16.0]
    assert waits == sorted(waits) and max(waits) == sf.RETRY_MAX_S
    assert sf.retry_delay_s(10 ** 6) == sf.RETRY_MAX_S
