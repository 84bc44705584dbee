"""Where flowloop keeps its records in Moonraker's database, and which
migrations an older layout needs.

One namespace per kind of record, each written by one store of the Moonraker
component (its lock, its validation): PROFILES_NAMESPACE holds the material
profiles and the active profile of each extruder, NOZZLE_HEALTH_NAMESPACE one
history per hotend and profile. Each namespace's schema version is kept apart
from its records, in SCHEMA_NAMESPACE under the namespace's name (as
Moonraker's history keeps its tables' versions in its table registry), so
Moonraker's database API shows a namespace's records and nothing else.

Version 0 is a database written before versions: the nozzle histories were
kept beside the profiles, in PROFILES_NAMESPACE under LEGACY_HEALTH_PREFIX.
"""

from __future__ import annotations

from typing import Any, List, Optional

from ..errors import FlowloopError

SCHEMA_NAMESPACE = "flowloop_schema"
PROFILES_NAMESPACE = "flowloop"
NOZZLE_HEALTH_NAMESPACE = "flowloop_nozzle_health"
PROFILES_VERSION = 1
NOZZLE_HEALTH_VERSION = 1

PROFILE_PREFIX = "profile:"
ACTIVE_KEY = "active"
LEGACY_HEALTH_PREFIX = "nozzle_health:"


def _hex(text: str) -> str:
    return text.encode("utf-8").hex()


def profile_key(name: str) -> str:
    """A profile's key: its name's UTF-8 hex (a name never becomes a key
    path, a file name or G-code)."""
    return PROFILE_PREFIX + _hex(name)


def nozzle_health_key(hotend: str, profile: str) -> str:
    """A history's key in NOZZLE_HEALTH_NAMESPACE."""
    return f"{_hex(hotend)}:{_hex(profile)}"


def from_legacy_health_key(key: str) -> Optional[str]:
    """The version-1 key of a nozzle history kept in PROFILES_NAMESPACE at
    version 0; None for a key that is not one."""
    if not key.startswith(LEGACY_HEALTH_PREFIX):
        return None
    return key[len(LEGACY_HEALTH_PREFIX):]


def stored_version(value: Any, namespace: str) -> int:
    """A namespace's version as SCHEMA_NAMESPACE holds it (none: 0, a
    database written before versions)."""
    if value is None:
        return 0
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise FlowloopError(f"the schema version of database namespace "
                            f"{namespace!r} is {value!r}, not a version")
    return value


def migrations(found: int, current: int) -> List[int]:
    """The versions to migrate from, oldest first, to reach `current`; none
    for a namespace at `current` or written by a newer flowloop (read as far
    as this one can, its version left as it is)."""
    return list(range(found, current))
