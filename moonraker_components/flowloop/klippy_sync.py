# flowloop component: klippy's copy of each extruder's active profile.
#
# klippy holds the active profile itself (its [flowloop] object answers the
# flowloop/set_active_profile endpoint). An activation stands only while
# klippy accepts it; Profiles decides what happens on a refusal, this part
# only sends and tells a refusal (klippy's 400) from klippy being away. An
# activation carries the hotend's melt ratio for the profile from its last
# print (nozzle health's carried ratio): the limiter's grip model starts from
# what this hotend melted in its earlier prints.
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any, Awaitable, Callable, Dict, Optional

from flowloop.material.active import ActiveProfile

from ...common import WebRequest
from .errors import one_line
from .store import ProfileStore

if TYPE_CHECKING:
    from ...server import Server
    from ..klippy_connection import KlippyConnection

KLIPPY_ENDPOINT = "flowloop/set_active_profile"


class KlippyRefused(Exception):
    """klippy answered the activation with an error (its one line)."""


class KlippySync:
    def __init__(self, server: Server, store: ProfileStore) -> None:
        self.server = server
        self.store = store
        self.klippy: KlippyConnection = server.lookup_component("klippy_connection")
        # (extruder, profile name) -> the melt ratio to send, or None
        self.melt_ratio_of: Optional[Callable[[str, str],
                                              Awaitable[Optional[float]]]] = None

    async def send(self, extruder: str, entry: Optional[ActiveProfile]) -> bool:
        """Send an extruder's activation (None clears it) to klippy: True
        once klippy took it, False when klippy is away (not ready, or gone
        while asked); KlippyRefused when klippy refused it."""
        if not self.klippy.is_ready():
            return False
        params: Dict[str, Any] = {"extruder": extruder, "profile": None}
        if entry is not None:
            params["profile"] = self.store.profile_dicts[entry.name]
            params["working_point"] = entry.working_point
            if self.melt_ratio_of is not None:
                ratio = await self.melt_ratio_of(extruder, entry.name)
                if ratio is not None:
                    params["melt_ratio"] = ratio
        try:
            await self.klippy.request(WebRequest(KLIPPY_ENDPOINT, params))
        except self.server.error as e:
            if e.status_code != 400:  # 503 disconnected, 500 timed out
                logging.info(f"flowloop: klippy did not answer for {extruder}: {e}")
                return False
            raise KlippyRefused(one_line(e)) from None
        return True
