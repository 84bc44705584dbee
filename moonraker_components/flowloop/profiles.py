# flowloop component: what clients and klippy may do with profiles (store,
# delete, activate). Each writes through the store, keeps klippy's copy
# current and tells clients with a notify_flowloop_profile_changed.
#
# One rule keeps the active profiles Moonraker stores and klippy's copies
# the same: an activation stands only while klippy accepts it. With klippy
# ready it is sent first and stored only if klippy takes it (refused: 400,
# nothing stored). With klippy away it is stored and queued; each time
# klippy becomes ready every stored activation is sent again, and one klippy
# refuses then (an extruder it no longer has, a heater too cold for the
# profile) is dropped and notified as `refused`. Storing an active profile
# again sends the new version the same way.
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any, Awaitable, Callable, Dict, List, Optional

from flowloop.material import profile as fl_profile
from flowloop.material.active import ActiveProfile

from .args import refusal
from .klippy_sync import KlippyRefused, KlippySync
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
        # async checks a profile (and its source) must pass before it is
        # stored, each raising its refusal: the Spoolman link's
        self.before_store: List[Callable[[fl_profile.Profile, str],
                                         Awaitable[None]]] = []
        # async work a stored profile (and its source) gets before the store
        # is answered: the Spoolman link's write, so that a store answered
        # is a store shared (or listed unwritten while Spoolman is away)
        self.after_store: List[Callable[[fl_profile.Profile, str],
                                        Awaitable[None]]] = []
        server.register_notification(NOTIFICATION, "flowloop_profile_changed")
        server.register_event_handler("server:klippy_ready", self._on_klippy_ready)

    def notify(self, action: str, name: str, **extra: Any) -> None:
        self.server.send_event(NOTIFICATION, {"action": action, "name": name, **extra})

    async def store_profile(self, profile: fl_profile.Profile,
                            source: str) -> Dict[str, Any]:
        for check in self.before_store:
            await check(profile, source)
        action = await self.store.put(profile)
        self.notify(action, profile.name, source=source,
                    profile=fl_profile.summary(profile))
        dropped = [extruder for extruder in self.store.active_for(profile.name)
                   if await self._confirm(extruder)]
        for share in self.after_store:
            await share(profile, source)
        return {"name": profile.name, "action": action, "deactivated": dropped}

    async def delete_profile(self, name: str) -> Dict[str, Any]:
        stopped = await self.store.remove(name)
        for extruder in stopped:
            await self._clear_klippy(extruder)
        self.notify("deleted", name, deactivated=stopped)
        return {"name": name, "action": "deleted", "deactivated": stopped}

    async def activate(self, extruder: str, entry: ActiveProfile) -> Dict[str, Any]:
        try:
            sent = await self.store.set_active(
                extruder, entry, lambda: self.klippy.send(extruder, entry))
        except KlippyRefused as e:
            raise refusal(f"klippy refused the profile: {e}") from None
        self.notify("activated", entry.name, extruder=extruder,
                    working_point=entry.working_point, sent_to_klippy=sent)
        return {"extruder": extruder, "name": entry.name,
                "working_point": entry.working_point, "sent_to_klippy": sent}

    # --- klippy's copies ----------------------------------------------------------

    async def _clear_klippy(self, extruder: str) -> None:
        try:
            await self.klippy.send(extruder, None)
        except KlippyRefused as e:
            logging.info(f"flowloop: klippy did not clear {extruder}: {e}")

    async def _confirm(self, extruder: str) -> bool:
        """Send the extruder's stored activation to klippy again (queued while
        klippy is away); one klippy refuses is dropped, klippy's copy cleared
        and clients notified: True."""
        async def refusal(entry: ActiveProfile) -> Optional[str]:
            try:
                if await self.klippy.send(extruder, entry):
                    logging.info(f"flowloop: active profile for {extruder} sent "
                                 f"to klippy")
                return None
            except KlippyRefused as e:
                # klippy keeps what it had (an older version of the profile)
                await self._clear_klippy(extruder)
                return f"klippy refused the profile: {e}"

        dropped = await self.store.confirm_active(extruder, refusal)
        if dropped is None:
            return False
        entry, reason = dropped
        logging.info(f"flowloop: the active profile for {extruder} dropped: "
                     f"{reason}")
        self.notify("refused", entry.name, source="klippy", extruder=extruder,
                    working_point=entry.working_point, reason=reason)
        return True

    async def _on_klippy_ready(self) -> None:
        for extruder in sorted(self.store.active):
            await self._confirm(extruder)
