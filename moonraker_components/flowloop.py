# flowloop: material profiles and flowloop status for Moonraker clients.
#
# Section [flowloop] in moonraker.conf. Installed by `flowloop install` as a
# link in moonraker/components/. The thinking is in the flowloop package;
# this file registers endpoints and talks to klippy and the database.
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any, Dict

import flowloop

from ..common import RequestType

if TYPE_CHECKING:
    from ..common import WebRequest
    from ..confighelper import ConfigHelper
    from .klippy_apis import KlippyAPI


class Flowloop:
    def __init__(self, config: ConfigHelper) -> None:
        self.server = config.get_server()
        self.klippy_apis: KlippyAPI = self.server.lookup_component("klippy_apis")
        self.server.register_endpoint(
            "/server/flowloop/info", RequestType.GET, self._handle_info)

    async def _handle_info(self, web_request: WebRequest) -> Dict[str, Any]:
        info: Dict[str, Any] = {
            "version": flowloop.__version__,
            "klippy_connected": False,
            "sections": [],
            "sensor_firmware": {},
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


def load_component(config: ConfigHelper) -> Flowloop:
    return Flowloop(config)
