# flowloop component: the live page at /server/flowloop/page/ and the two
# things it asks that only flowloop knows: the active profile's lines and an
# annotated file's plan. Everything else the page reads from Moonraker's
# websocket (printer.objects.subscribe).
#
# The page is one HTML document with its scripts inline (built once, here,
# from the files in flowloop/host/page/), served by an endpoint, so it sits
# behind Moonraker's authorization like every flowloop endpoint. Moonraker's
# static file handler checks authorization too, but it serves every file as
# an attachment (a browser would save the page instead of showing it) and
# a token in the page's URL would not reach the page's sub-requests.
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import asyncio
import html
import json
import logging
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, Dict, Optional, Tuple

from flowloop.errors import FlowloopError
from flowloop.host import info as host_info
from flowloop.host import live_page
from flowloop.material import profile as fl_profile

from ...common import RequestType, TransportType, WebRequest
from . import args
from .errors import one_line, quoted
from .info import KLIPPY_ANSWER_S
from .store import ProfileStore

if TYPE_CHECKING:
    from ...server import Server

PAGE_PATH = host_info.PAGE_PATH


class Page:
    def __init__(self, server: Server, store: ProfileStore) -> None:
        self.server = server
        self.store = store
        self.file_manager = server.lookup_component("file_manager")
        self.klippy_apis = server.lookup_component("klippy_apis")
        # Each heater's max_temp as klippy reported it: it changes only with
        # klippy's config, so it is asked again only after klippy restarts.
        self._heater_max_temp_c: Dict[str, float] = {}
        server.register_event_handler("server:klippy_ready",
                                      self._heater_max_temp_c.clear)
        # Read once: a request hands out the held bytes.
        try:
            self.document = live_page.document()
        except FlowloopError as e:  # a broken install: say so on the page
            logging.error(f"flowloop: the live page cannot be served: {e}")
            self.document = html.escape(one_line(e)).encode()
        # The last plan asked for, by (path, size, mtime, profile, wp): the
        # page asks again after every reconnect; a profile stored again under
        # its name is another profile.
        self._plan_key: Optional[Tuple[Any, ...]] = None
        self._plan: Dict[str, Any] = {}
        for path in (PAGE_PATH, PAGE_PATH.rstrip("/")):
            server.register_endpoint(
                path, RequestType.GET, self._handle_page,
                transports=TransportType.HTTP, wrap_result=False,
                content_type="text/html; charset=utf-8")
        server.register_endpoint(
            "/server/flowloop/page/lines", RequestType.GET, self._handle_lines)
        server.register_endpoint(
            "/server/flowloop/page/plan", RequestType.GET, self._handle_plan)

    async def _heater_max_temp(self, extruder: str) -> Optional[float]:
        """The extruder heater's max_temp as klippy reports it with the active
        profile (None: klippy does not tell within KLIPPY_ANSWER_S)."""
        if extruder not in self._heater_max_temp_c:
            try:
                status = await asyncio.wait_for(self.klippy_apis.query_objects(
                    {"flowloop": ["profiles"]}, default={}), KLIPPY_ANSWER_S)
            except asyncio.TimeoutError:
                return None
            for name, shown in status.get("flowloop", {}).get("profiles",
                                                              {}).items():
                if shown.get("heater_max_temp_c") is not None:
                    self._heater_max_temp_c[name] = shown["heater_max_temp_c"]
        return self._heater_max_temp_c.get(extruder)

    def _active(self, extruder: str) -> Tuple[Optional[fl_profile.Profile], float]:
        entry = self.store.active.get(extruder)
        if entry is None or entry.name not in self.store.profiles:
            return None, fl_profile.DEFAULT_WORKING_POINT
        return self.store.profiles[entry.name], entry.working_point

    async def _handle_page(self, web_request: WebRequest) -> bytes:
        return self.document

    async def _handle_lines(self, web_request: WebRequest) -> Dict[str, Any]:
        extruder = args.extruder(web_request.get_args())
        profile, wp = self._active(extruder)
        if profile is None:
            return {"extruder": extruder, "lines": None,
                    "why": f"no active profile for {extruder}"}
        heater_max_temp_c = await self._heater_max_temp(extruder)
        return {"extruder": extruder, "why": "",
                "lines": live_page.profile_lines(profile, wp, heater_max_temp_c)}

    async def _handle_plan(self, web_request: WebRequest) -> Dict[str, Any]:
        extruder = args.extruder(web_request.get_args())
        _, path = args.gcode_file(web_request.get_args(),
                                  self.file_manager.get_directory("gcodes"))
        profile, wp = self._active(extruder)
        stat = path.stat()
        key = (str(path), stat.st_size, stat.st_mtime_ns,
               None if profile is None else fl_profile.encode_profile(profile, 0), wp)
        if key != self._plan_key:
            plan = await self._run_plan(path, profile, wp)
            self._plan_key, self._plan = key, plan
        return {"extruder": extruder, **self._plan}

    async def _run_plan(self, path: Path, profile: Optional[fl_profile.Profile],
                        wp: float) -> Dict[str, Any]:
        # A long print's replay is seconds of pure Python: in a process of
        # its own, so it holds neither Moonraker's loop nor its GIL.
        argv, stdin = live_page.plan_command(sys.executable, path, profile, wp)
        proc = await asyncio.create_subprocess_exec(
            *argv, stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE)
        try:
            out, err = await asyncio.wait_for(proc.communicate(stdin),
                                              live_page.PLAN_TIMEOUT_S)
        except asyncio.TimeoutError:
            proc.kill()
            await proc.wait()
            raise args.refusal(f"planning {quoted(path.name)} took longer than "
                               f"{live_page.PLAN_TIMEOUT_S:g} s", 500) from None
        if proc.returncode != 0:
            logging.error(f"flowloop: the plan of {path} failed: "
                          f"{err.decode(errors='replace')[-2000:]}")
            raise args.refusal(f"planning {quoted(path.name)} failed (see "
                               f"moonraker.log)", 500)
        return json.loads(out)
