"""Where flowloop's records live in Moonraker's database and which
migrations an older layout needs (flowloop.host.db_schema); the Moonraker
tier's test_database_migration.py runs them on a database written the old
way."""

from __future__ import annotations

import pytest

from flowloop.errors import FlowloopError
from flowloop.host import db_schema as schema


def test_each_kind_of_record_has_its_own_namespace_and_version():
    namespaces = [schema.PROFILES_NAMESPACE, schema.NOZZLE_HEALTH_NAMESPACE,
                  schema.SCHEMA_NAMESPACE]
    assert len(set(namespaces)) == 3
    assert schema.PROFILES_VERSION >= 1 and schema.NOZZLE_HEALTH_VERSION >= 1


def test_a_legacy_history_key_keeps_its_hotend_and_profile():
    old = "nozzle_health:" + b"v6 0.4".hex() + ":" + b"PLA <b>".hex()
    assert schema.from_legacy_health_key(old) == schema.nozzle_health_key(
        "v6 0.4", "PLA <b>")
    assert schema.from_legacy_health_key(schema.profile_key("PLA")) is None
    assert schema.from_legacy_health_key(schema.ACTIVE_KEY) is None


def test_a_database_before_versions_is_version_0_and_migrates_once():
    assert schema.stored_version(None, "flowloop") == 0
    assert schema.migrations(0, 1) == [0]
    assert schema.migrations(1, 1) == []
    assert schema.migrations(0, 3) == [0, 1, 2]


def test_a_newer_flowloops_namespace_is_not_migrated_back():
    assert schema.migrations(2, 1) == []


@pytest.mark.parametrize("value", [-1, "1", 1.0, True, [1]])
def test_a_version_that_is_not_one_is_one_line(value):
    with pytest.raises(FlowloopError, match="schema version of database "
                                            "namespace 'flowloop'"):
        schema.stored_version(value, "flowloop")
