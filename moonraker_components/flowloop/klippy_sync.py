# flowloop component: keep klippy's copy of each extruder's active profile.
#
# klippy holds the active profile itself (its [flowloop] object answers the
# flowloop/set_active_profile endpoint); this part sends it whenever it
# changes and again each time klippy becomes ready.
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any, Dict, Optional

from flowloop.material.active import ActiveProfile

from ...common import WebRequest
from .errors import one_line
from .store import ProfileStore

if TYPE_CHECKING:
    from ...server import Server
    from ..klippy_connection import KlippyConnection

KLIPPY_ENDPOINT = "flowloop/set_active_profile"


class KlippySync:
    def __init__(self, server: Server, store: ProfileStore) -> None:
        self.server = server
        self.store = store
        self.klippy: KlippyConnection = server.lookup_component("klippy_connection")
        server.register_event_handler("server:klippy_ready", self._on_klippy_ready)

    async def send(self, extruder: str, entry: Optional[ActiveProfile] = None,
                   quiet: bool = False) -> bool:
        """Send an extruder's activation (default: the stored one; none clears
        it) to klippy; False if klippy is not ready (or refused, when quiet)."""
        if not self.klippy.is_ready():
            return False
        if entry is None:
            entry = self.store.active.get(extruder)
        params: Dict[str, Any] = {"extruder": extruder, "profile": None}
        if entry is not None and entry.name in self.store.profile_dicts:
            params["profile"] = self.store.profile_dicts[entry.name]
            params["working_point"] = entry.working_point
        try:
            await self.klippy.request(WebRequest(KLIPPY_ENDPOINT, params))
        except self.server.error as e:
            if not quiet:
                raise self.server.error(
                    one_line(f"klippy refused the profile: {e}"), 400) from None
            logging.info(f"flowloop: klippy refused the profile for {extruder}: {e}")
            return False
        return True

    async def resend(self, name: str) -> None:
        """klippy keeps a copy: send the new one wherever the profile is active."""
        for extruder in self.store.active_for(name):
            await self.send(extruder, quiet=True)

    async def _on_klippy_ready(self) -> None:
        for extruder in sorted(self.store.active):
            sent = await self.send(extruder, quiet=True)
            logging.info(f"flowloop: active profile for {extruder} "
                         f"{'sent to' if sent else 'NOT accepted by'} klippy")

