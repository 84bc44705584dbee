# flowloop component: /server/flowloop/info, what flowloop has loaded in
# Moonraker and in klippy (klippy's [flowloop] object).
#
# klippy is asked with each request, but the answer never waits more than
# KLIPPY_ANSWER_S for it: a klippy that is stopped or busy would otherwise
# hold the request as long as it is. What klippy said last is kept and
# served meanwhile (`klippy_answered` false), and one question at a time is
# outstanding.
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import asyncio
import logging
from typing import TYPE_CHECKING, Any, Dict, Optional

import flowloop
from flowloop.material.active import active_to_stored

from .store import ProfileStore

if TYPE_CHECKING:
    from ...server import Server
    from ..klippy_apis import KlippyAPI
    from ..klippy_connection import KlippyConnection

KLIPPY_ANSWER_S = 2.0


def _klippy_part(host: Optional[Dict[str, Any]]) -> Dict[str, Any]:
    """The fields klippy's [flowloop] object tells (None: klippy has none)."""
    host = host or {}
    part: Dict[str, Any] = {"sections": host.get("sections", []),
                            "sensor_firmware": host.get("sensor_firmware", {})}
    if "version" in host:
        part["klippy_version"] = host["version"]
    return part


class Info:
    def __init__(self, server: Server, store: ProfileStore,
                 spoolman_link: Any, gcode_processor: Optional[str]) -> None:
        self.store = store
        self.spoolman_link = spoolman_link   # a SpoolmanLink, or None
        self.gcode_processor = gcode_processor  # its name when registered
        self.eventloop = server.get_event_loop()
        self.klippy_apis: KlippyAPI = server.lookup_component("klippy_apis")
        self.klippy: KlippyConnection = server.lookup_component("klippy_connection")
        self.last_klippy = _klippy_part(None)  # what klippy said last
        self._asking: Optional[asyncio.Future] = None

    async def _ask_klippy(self) -> None:
        objects = await self.klippy_apis.get_object_list(default=None)
        if objects is None:  # klippy not connected: it has nothing loaded
            self.last_klippy = _klippy_part(None)
            return
        host = None
        if "flowloop" in objects:
            status = await self.klippy_apis.query_objects({"flowloop": None},
                                                          default={})
            host = status.get("flowloop", {})
            if host.get("version") != flowloop.__version__:
                logging.info("flowloop: klippy runs %s, Moonraker %s",
                             host.get("version"), flowloop.__version__)
        self.last_klippy = _klippy_part(host)

    async def get(self) -> Dict[str, Any]:
        if self._asking is None or self._asking.done():
            self._asking = self.eventloop.create_task(self._ask_klippy())
        try:
            await asyncio.wait_for(asyncio.shield(self._asking), KLIPPY_ANSWER_S)
            answered = True
        except asyncio.TimeoutError:
            answered = False
        return {
            "version": flowloop.__version__,
            "klippy_connected": self.klippy.is_connected(),
            "klippy_state": self.klippy.state.name.lower(),
            "klippy_answered": answered,
            **self.last_klippy,
            "profiles": len(self.store.profiles),
            "active_profiles": active_to_stored(self.store.active),
            "spoolman_link": self.spoolman_link is not None,
            # hotend key, profiles not yet written, spool not yet looked up,
            # the last problem with Spoolman (None once it answered again)
            "spoolman": (self.spoolman_link.status()
                         if self.spoolman_link is not None else None),
            "gcode_processor": self.gcode_processor,
        }
