# flowloop component: what clients and klippy may do with profiles (store,
# delete, activate). Each writes through the store, keeps klippy's copy
# current and tells clients with a notify_flowloop_profile_changed.
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Dict

from flowloop.material import profile as fl_profile
from flowloop.material.active import ActiveProfile

from .klippy_sync import KlippySync
from .store import ProfileStore

if TYPE_CHECKING:
    from ...server import Server

NOTIFICATION = "flowloop:profile_changed"


class Profiles:
    def __init__(self, server: Server, store: ProfileStore,
                 klippy: KlippySync) -> None:
        self.server = server
        self.store = store
        self.klippy = klippy
        server.register_notification(NOTIFICATION, "flowloop_profile_changed")

    def notify(self, action: str, name: str, **extra: Any) -> None:
        self.server.send_event(NOTIFICATION, {"action": action, "name": name, **extra})

    async def store_profile(self, profile: fl_profile.Profile,
                            source: str) -> Dict[str, Any]:
        action = await self.store.put(profile)
        self.notify(action, profile.name, source=source,
                    profile=fl_profile.summary(profile))
        await self.klippy.resend(profile.name)
        return {"name": profile.name, "action": action}

    async def delete_profile(self, name: str) -> Dict[str, Any]:
        stopped = await self.store.remove(name)
        for extruder in stopped:  # clears klippy's copy
            await self.klippy.send(extruder, quiet=True)
        self.notify("deleted", name, deactivated=stopped)
        return {"name": name, "action": "deleted", "deactivated": stopped}

    async def activate(self, extruder: str, entry: ActiveProfile) -> Dict[str, Any]:
        sent = await self.store.set_active(
            extruder, entry, lambda: self.klippy.send(extruder, entry))
        self.notify("activated", entry.name, extruder=extruder,
                    working_point=entry.working_point, sent_to_klippy=sent)
        return {"extruder": extruder, "name": entry.name,
                "working_point": entry.working_point, "sent_to_klippy": sent}
