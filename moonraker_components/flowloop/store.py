# flowloop component: the stores of flowloop's records in Moonraker's
# database, one per kind of record, each in its own namespace with its lock,
# its validation and its schema version (flowloop.host.db_schema says where
# each lives and which migrations an older layout needs):
#
#   ProfileStore       material profiles and each extruder's active profile
#   NozzleHealthStore  one nozzle health history per hotend and profile
#
# The namespaces are protected: Moonraker's database API may read them, only
# these stores write them, and every write is validated first.
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import asyncio
import logging
from typing import (
    Any,
    Awaitable,
    Callable,
    Dict,
    List,
    Optional,
    Tuple,
    TypeVar,
)

from flowloop.control import nozzle_health as nh
from flowloop.errors import FlowloopError
from flowloop.host import db_schema as schema
from flowloop.host.db_schema import ACTIVE_KEY, PROFILE_PREFIX, profile_key
from flowloop.material import profile as fl_profile
from flowloop.material.active import (
    ActiveProfile,
    active_from_stored,
    active_to_stored,
)

from .errors import one_line

__all__ = ["ACTIVE_KEY", "NozzleHealthStore", "ProfileStore", "SchemaVersions",
           "UnknownProfile", "profile_key"]

T = TypeVar("T")


class SchemaVersions:
    """Each flowloop namespace's schema version (schema.SCHEMA_NAMESPACE)."""

    def __init__(self, database: Any) -> None:
        self.db = database.register_local_namespace(schema.SCHEMA_NAMESPACE)

    async def migrate(self, namespace: str, current: int,
                      migrate: Callable[[int], Awaitable[None]]) -> None:
        """Run `migrate(version)` for each version the namespace is behind,
        then record `current`. A migration that stops part way is run again
        at the next start (each one may run twice without loss)."""
        try:
            found = schema.stored_version(await self.db.get(namespace, None),
                                          namespace)
        except FlowloopError as e:
            logging.info(f"flowloop: {one_line(e)}; migrated from version 0")
            found = 0
        if found > current:
            logging.info(f"flowloop: database namespace {namespace!r} is at "
                         f"schema version {found}, written by a newer flowloop;"
                         f" this one reads version {current}")
        steps = schema.migrations(found, current)
        for version in steps:
            logging.info(f"flowloop: database namespace {namespace!r}: "
                         f"migrating from schema version {version}")
            await migrate(version)
        if steps:
            await self.db.insert(namespace, current)


class UnknownProfile(Exception):
    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.name = name


class ProfileStore:
    """The profiles and activations, validated and held in memory.

    Changed only under write_lock and only after the database write, so a
    write that raises changes nothing here and concurrent writes cannot
    interleave. (Moonraker logs an sqlite error on insert instead of raising
    it.)
    """

    NAMESPACE = schema.PROFILES_NAMESPACE
    VERSION = schema.PROFILES_VERSION

    def __init__(self, database: Any, versions: SchemaVersions) -> None:
        self.db = database.register_local_namespace(self.NAMESPACE)
        self.versions = versions
        self.profiles: Dict[str, fl_profile.Profile] = {}
        # The same profiles as JSON-able dicts, built once per write: a GET
        # answers with the held value instead of converting on every request.
        self.profile_dicts: Dict[str, Dict[str, Any]] = {}
        self.active: Dict[str, ActiveProfile] = {}
        self.write_lock = asyncio.Lock()

    async def _migrate(self, version: int) -> None:
        # 0 -> 1: the records stay as they are; the nozzle histories kept
        # beside them leave with NozzleHealthStore's migration (run first).
        pass

    async def load(self) -> None:
        await self.versions.migrate(self.NAMESPACE, self.VERSION, self._migrate)
        for key, value in await self.db.items():
            if key == ACTIVE_KEY:
                try:
                    self.active, skipped = active_from_stored(value)
                except FlowloopError as e:
                    skipped = [str(e)]
                for reason in skipped:  # left in the database until the next write
                    logging.info(f"flowloop: stored activation skipped: {reason}")
            elif key.startswith(PROFILE_PREFIX):
                try:
                    profile = fl_profile.profile_from_dict(value)
                except FlowloopError as e:
                    # Kept in the database untouched: a newer flowloop may read it.
                    logging.info(f"flowloop: stored profile {key} skipped: {e}")
                    continue
                self._hold(profile, fl_profile.profile_to_dict(profile))

    def _hold(self, profile: fl_profile.Profile, as_dict: Dict[str, Any]) -> None:
        self.profiles[profile.name] = profile
        self.profile_dicts[profile.name] = as_dict

    def known(self, name: str) -> fl_profile.Profile:
        profile = self.profiles.get(name)
        if profile is None:
            raise UnknownProfile(name)
        return profile

    def active_for(self, name: str) -> List[str]:
        """The extruders this profile is active on."""
        return sorted(ext for ext, entry in self.active.items() if entry.name == name)

    async def put(self, profile: fl_profile.Profile) -> str:
        """Store (create or replace) a profile; 'created' or 'updated'."""
        name = profile.name
        async with self.write_lock:
            action = "updated" if name in self.profiles else "created"
            as_dict = fl_profile.profile_to_dict(profile)
            await self.db.insert(profile_key(name), as_dict)
            self._hold(profile, as_dict)
        return action

    async def remove(self, name: str) -> List[str]:
        """Delete a profile; returns the extruders it was active on (now none)."""
        async with self.write_lock:
            self.known(name)
            stopped = self.active_for(name)
            active = {ext: entry for ext, entry in self.active.items()
                      if ext not in stopped}
            await self.db.delete(profile_key(name))
            if stopped:
                await self.db.insert(ACTIVE_KEY, active_to_stored(active))
            del self.profiles[name]
            del self.profile_dicts[name]
            self.active = active
        return stopped

    async def set_active(self, extruder: str, entry: ActiveProfile,
                         before: Callable[[], Awaitable[T]]) -> T:
        """Make entry the extruder's active profile. `before` runs under the
        lock once the profile is known to exist (klippy is told first), and
        its answer is returned."""
        async with self.write_lock:
            self.known(entry.name)  # again under the lock: a delete may have run
            answer = await before()
            active = {**self.active, extruder: entry}
            await self.db.insert(ACTIVE_KEY, active_to_stored(active))
            self.active = active
        return answer

    async def confirm_active(
            self, extruder: str,
            refusal: Callable[[ActiveProfile], Awaitable[Optional[str]]]
    ) -> Optional[Tuple[ActiveProfile, str]]:
        """Ask `refusal` (klippy) about the extruder's activation, under the
        lock; one it refuses (it answers why) is dropped and returned with
        that reason."""
        async with self.write_lock:
            entry = self.active.get(extruder)
            if entry is None:
                return None
            reason = await refusal(entry)
            if reason is None:
                return None
            active = {ext: kept for ext, kept in self.active.items()
                      if ext != extruder}
            await self.db.insert(ACTIVE_KEY, active_to_stored(active))
            self.active = active
        return entry, reason


class NozzleHealthStore:
    """One nozzle health history per hotend and profile.

    Read from the database when asked (never all at start-up); written under
    write_lock, one read-change-write at a time, and only a history that
    nh.check_history reads whole is written.
    """

    NAMESPACE = schema.NOZZLE_HEALTH_NAMESPACE
    VERSION = schema.NOZZLE_HEALTH_VERSION

    def __init__(self, database: Any, versions: SchemaVersions) -> None:
        self.db = database.register_local_namespace(self.NAMESPACE)
        self.versions = versions
        self.write_lock = asyncio.Lock()

    async def load(self, profiles: ProfileStore) -> None:
        """Migrate what an older flowloop wrote (before profiles.load())."""
        async def migrate(version: int) -> None:
            # 0 -> 1: the histories move out of the profiles' namespace
            keys = await profiles.db.keys()
            moved = {new: old for old in keys
                     if (new := schema.from_legacy_health_key(old)) is not None}
            if not moved:
                return
            records = await profiles.db.get_batch(list(moved.values()))
            await self.db.insert_batch({new: records[old]
                                        for new, old in moved.items()
                                        if old in records})
            await profiles.db.delete_batch(list(moved.values()))
            logging.info(f"flowloop: {len(moved)} nozzle health histories "
                         f"moved to database namespace {self.NAMESPACE!r}")
        await self.versions.migrate(self.NAMESPACE, self.VERSION, migrate)

    async def get(self, hotend: str, profile: str) -> Optional[Dict[str, Any]]:
        return await self.db.get(schema.nozzle_health_key(hotend, profile), None)

    async def histories(self) -> List[Any]:
        """Every history (a toolchanger's tools each have theirs)."""
        return await self.db.values()

    async def update(self, hotend: str, profile: str,
                     change: Callable[[Optional[Dict[str, Any]]], Dict[str, Any]]
                     ) -> Tuple[Optional[Dict[str, Any]], Dict[str, Any]]:
        """(before, after): the history `change` makes of the stored one,
        checked whole and written (FlowloopError: nothing written)."""
        key = schema.nozzle_health_key(hotend, profile)
        async with self.write_lock:
            before = await self.db.get(key, None)
            after = nh.check_history(change(before))
            if (after["hotend"], after["profile"]) != (hotend, profile):
                raise FlowloopError("a nozzle health history stored under "
                                    "another hotend or profile")
            await self.db.insert(key, after)
        return before, after

    async def remove(self, hotend: str, profile: str) -> Optional[Dict[str, Any]]:
        """Delete one history; the one deleted, or None (there was none)."""
        key = schema.nozzle_health_key(hotend, profile)
        async with self.write_lock:
            before = await self.db.get(key, None)
            if before is not None:
                await self.db.delete(key)
        return before
