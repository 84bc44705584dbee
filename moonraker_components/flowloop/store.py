# flowloop component: material profiles and active profiles in Moonraker's
# database.
#
# Profiles live in the database namespace "flowloop", one record per profile
# under a key made from the name's UTF-8 hex (a name never becomes a key path,
# a file name or G-code). The namespace is protected: Moonraker's database API
# may read it, only this component writes it, so every write is validated.
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import asyncio
import logging
from typing import Any, Awaitable, Callable, Dict, List, Optional, Tuple, TypeVar

from flowloop.errors import FlowloopError
from flowloop.material import profile as fl_profile
from flowloop.material.active import (
    ActiveProfile,
    active_from_stored,
    active_to_stored,
)

NAMESPACE = "flowloop"
PROFILE_PREFIX = "profile:"
ACTIVE_KEY = "active"

T = TypeVar("T")


def profile_key(name: str) -> str:
    return PROFILE_PREFIX + name.encode("utf-8").hex()


class UnknownProfile(Exception):
    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.name = name


class ProfileStore:
    """The database's content, validated and held in memory.

    Changed only under write_lock and only after the database write, so a
    write that raises changes nothing here and concurrent writes cannot
    interleave. (Moonraker logs an sqlite error on insert instead of raising
    it.)
    """

    def __init__(self, database: Any) -> None:
        self.db = database.register_local_namespace(NAMESPACE)
        self.profiles: Dict[str, fl_profile.Profile] = {}
        # The same profiles as JSON-able dicts, built once per write: a GET
        # answers with the held value instead of converting on every request.
        self.profile_dicts: Dict[str, Dict[str, Any]] = {}
        self.active: Dict[str, ActiveProfile] = {}
        self.write_lock = asyncio.Lock()

    async def load(self) -> None:
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
