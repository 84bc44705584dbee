# flowloop component: /server/flowloop/info, what flowloop has loaded in
# Moonraker and in klippy (klippy's [flowloop] object).
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any, Dict, Optional

import flowloop
from flowloop.material.active import active_to_stored

from .store import ProfileStore

if TYPE_CHECKING:
    from ...server import Server
    from ..klippy_apis import KlippyAPI


class Info:
    def __init__(self, server: Server, store: ProfileStore,
                 spoolman_link: bool, gcode_processor: Optional[str]) -> None:
        self.store = store
        self.spoolman_link = spoolman_link
        self.gcode_processor = gcode_processor  # its name when registered
        self.klippy_apis: KlippyAPI = server.lookup_component("klippy_apis")

    async def get(self) -> Dict[str, Any]:
        info: Dict[str, Any] = {
            "version": flowloop.__version__,
            "klippy_connected": False,
            "sections": [],
            "sensor_firmware": {},
            "profiles": len(self.store.profiles),
            "active_profiles": active_to_stored(self.store.active),
            "spoolman_link": self.spoolman_link,
            "gcode_processor": self.gcode_processor,
        }
        objects = await self.klippy_apis.get_object_list(default=None)
        if objects is None:
            return info
        info["klippy_connected"] = True
        if "flowloop" not in objects:
            return info
        status = await self.klippy_apis.query_objects({"flowloop": None}, default={})
        host = status.get("flowloop", {})
        info["klippy_version"] = host.get("version")
        info["sections"] = host.get("sections", [])
        info["sensor_firmware"] = host.get("sensor_firmware", {})
        if info["klippy_version"] != flowloop.__version__:
            logging.info("flowloop: klippy runs %s, Moonraker %s",
                         info["klippy_version"], flowloop.__version__)
        return info
