# flowloop component: the Spoolman link. When Moonraker's [spoolman] sets the
# active spool, the profile naming that spool's filament becomes active on
# the linked extruder (the rule is flowloop.material.active.follow_spool).
# A spool loaded while Spoolman cannot say what it holds is looked up again
# when Moonraker reconnects to Spoolman (Moonraker does not announce the
# same spool twice).
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any, Dict

from flowloop.material.active import follow_spool

from .errors import quoted
from .profiles import Profiles
from .store import ProfileStore

if TYPE_CHECKING:
    from ...server import Server


class SpoolmanLink:
    def __init__(self, server: Server, extruder: str, default_wp: float,
                 store: ProfileStore, profiles: Profiles) -> None:
        self.server = server
        self.extruder = extruder
        self.default_wp = default_wp
        self.store = store
        self.profiles = profiles
        # the active spool whose filament Spoolman could not be asked for
        self.unresolved_spool: Any = None
        server.register_event_handler("spoolman:active_spool_set",
                                      self._on_active_spool_set)
        server.register_event_handler("spoolman:spoolman_status_changed",
                                      self._on_spoolman_status)

    def check_spoolman(self) -> None:
        if self.server.lookup_component("spoolman", None) is None:
            self.server.add_warning(
                "[flowloop] spoolman_link is enabled but Moonraker has no "
                "[spoolman] section: profiles will not follow the active spool")

    async def _fetch_spool(self, spool_id: Any) -> Any:
        spoolman = self.server.lookup_component("spoolman", None)
        if spoolman is None:
            return None
        http_client = self.server.lookup_component("http_client")
        resp = await http_client.get(f"{spoolman.spoolman_url}/v1/spool/{spool_id}",
                                     connect_timeout=1.0, request_timeout=2.0)
        if resp.has_error():
            logging.info(f"flowloop: Spoolman spool {spool_id}: HTTP "
                         f"{resp.status_code}")
            if resp.status_code == 599 or resp.status_code >= 500:
                # unreachable, timed out or failing: ask again on reconnect
                self.unresolved_spool = spool_id
            return None
        return resp.json()

    async def _on_spoolman_status(self, data: Dict[str, Any]) -> None:
        if not (isinstance(data, dict) and data.get("spoolman_connected")):
            return
        spoolman = self.server.lookup_component("spoolman", None)
        spool_id = self.unresolved_spool
        if spool_id is not None and spoolman is not None \
                and getattr(spoolman, "spool_id", None) == spool_id:
            logging.info(f"flowloop: Spoolman is back: looking up spool "
                         f"{spool_id} again")
            await self._on_active_spool_set({"spool_id": spool_id})

    async def _on_active_spool_set(self, data: Dict[str, Any]) -> None:
        spool_id = data.get("spool_id") if isinstance(data, dict) else None
        self.unresolved_spool = None
        if spool_id is None:
            return
        spool = await self._fetch_spool(spool_id)
        if spool is None:
            return
        entry = follow_spool(spool, self.store.profiles,
                             self.store.active.get(self.extruder), self.default_wp)
        if entry is None:
            logging.info(f"flowloop: no profile for the filament of Spoolman "
                         f"spool {spool_id}")
            return
        try:
            await self.profiles.activate(self.extruder, entry)
        except self.server.error as e:
            logging.info(f"flowloop: Spoolman link could not activate "
                         f"{quoted(entry.name)}: {e}")
