# flowloop component: the HTTP/JSON-RPC endpoints and the remote method klippy
# calls. Arguments are checked here, one clear line on refusal; the work is
# done by Profiles and Info.
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any, Dict, Optional

from flowloop.errors import FlowloopError
from flowloop.material import plot
from flowloop.material import profile as fl_profile
from flowloop.material.active import (
    ActiveProfile,
    active_to_stored,
    working_point_arg,
)

from ...common import RequestType, WebRequest
from .errors import one_line, quoted
from .info import Info
from .profiles import Profiles
from .store import ProfileStore, UnknownProfile

if TYPE_CHECKING:
    from ...server import Server


def _utf8(text: str) -> bytes:
    try:
        return text.encode("utf-8")
    except UnicodeEncodeError as e:  # a lone surrogate, from a JSON "\ud800" escape
        raise FlowloopError(f"not a JSON profile: the text holds an unpaired "
                            f"surrogate at character {e.start}") from None


class Api:
    def __init__(self, server: Server, store: ProfileStore, profiles: Profiles,
                 info: Info, default_wp: float) -> None:
        self.server = server
        self.eventloop = server.get_event_loop()
        self.store = store
        self.profiles = profiles
        self.info = info
        self.default_wp = default_wp
        for path, methods, handler in (
            ("/server/flowloop/info", RequestType.GET, self._handle_info),
            ("/server/flowloop/profile",
             RequestType.GET | RequestType.POST | RequestType.DELETE,
             self._handle_profile),
            ("/server/flowloop/profiles", RequestType.GET, self._handle_list),
            ("/server/flowloop/profile/activate", RequestType.POST,
             self._handle_activate),
        ):
            server.register_endpoint(path, methods, handler)
        server.register_endpoint(
            "/server/flowloop/profile/plot", RequestType.GET, self._handle_plot,
            wrap_result=False, content_type="image/svg+xml")
        server.register_remote_method(
            "flowloop_store_profile", self._remote_store_profile)

    # --- arguments -----------------------------------------------------------

    def _error(self, msg: Any, code: int = 400) -> Exception:
        return self.server.error(one_line(msg), code)

    def _not_found(self, name: str) -> Exception:
        return self._error(f"no profile named {quoted(name)}", 404)

    def _known(self, name: str) -> fl_profile.Profile:
        try:
            return self.store.known(name)
        except UnknownProfile:
            raise self._not_found(name) from None

    def _name_arg(self, web_request: WebRequest) -> str:
        name = web_request.get("name", None)
        if name is None:
            raise self._error("the profile name is missing (argument 'name')")
        if not isinstance(name, str):
            raise self._error("the profile name must be a string")
        try:
            return fl_profile.check_name(name)
        except FlowloopError as e:
            raise self._error(e) from None

    def _wp_arg(self, value: Any) -> float:
        try:
            return working_point_arg(value)
        except FlowloopError as e:
            raise self._error(e) from None

    def _extruder_arg(self, extruder: Any) -> str:
        if not fl_profile.is_extruder_name(extruder):
            raise self._error(f"{quoted(str(extruder))} is not an extruder name "
                              f"(extruder, extruder1, ...)")
        return extruder

    def parse_profile(self, value: Any) -> fl_profile.Profile:
        if value is None:
            raise self._error("the profile is missing (argument 'profile')")
        try:
            if isinstance(value, str):  # JSON text: decoded without recursion
                return fl_profile.decode_profile(_utf8(value))
            return fl_profile.profile_from_dict(value)
        except FlowloopError as e:
            raise self._error(f"argument 'profile': {e}") from None
        except RecursionError:  # a nesting no profile has
            raise self._error("argument 'profile': nested too deeply to be a "
                              "profile") from None

    async def parse_profile_off_loop(self, value: Any) -> fl_profile.Profile:
        # Validating a large profile takes milliseconds of CPU: in a thread,
        # Moonraker keeps answering other clients meanwhile.
        return await self.eventloop.run_in_thread(self.parse_profile, value)

    async def _activate(self, name: str, extruder: Any, wp: Any) -> Dict[str, Any]:
        extruder = self._extruder_arg(extruder)
        entry = ActiveProfile(name=name, working_point=self._wp_arg(wp))
        try:
            return await self.profiles.activate(extruder, entry)
        except UnknownProfile:  # deleted meanwhile
            raise self._not_found(name) from None

    # --- endpoints -----------------------------------------------------------

    async def _handle_profile(self, web_request: WebRequest) -> Dict[str, Any]:
        req_type = web_request.get_request_type()
        if req_type == RequestType.POST:
            profile = await self.parse_profile_off_loop(
                web_request.get("profile", None))
            return await self.profiles.store_profile(profile, "api")
        name = self._name_arg(web_request)
        if req_type == RequestType.DELETE:
            try:
                return await self.profiles.delete_profile(name)
            except UnknownProfile:
                raise self._not_found(name) from None
        self._known(name)
        return {"name": name, "profile": self.store.profile_dicts[name]}

    async def _handle_list(self, web_request: WebRequest) -> Dict[str, Any]:
        return {"profiles": [fl_profile.summary(self.store.profiles[name])
                             for name in sorted(self.store.profiles)],
                "active": active_to_stored(self.store.active)}

    async def _handle_activate(self, web_request: WebRequest) -> Dict[str, Any]:
        name = self._name_arg(web_request)
        extruder = web_request.get("extruder", "extruder")
        entry = self.store.active.get(extruder) if isinstance(extruder, str) else None
        wp = web_request.get("working_point", self.default_wp if entry is None
                             else entry.working_point)
        return await self._activate(name, extruder, wp)

    async def _handle_plot(self, web_request: WebRequest) -> str:
        name = self._name_arg(web_request)
        profile = self._known(name)
        wp = self._wp_arg(web_request.get("working_point", self.default_wp))
        return await self.eventloop.run_in_thread(plot.svg, profile, wp)

    async def _handle_info(self, web_request: WebRequest) -> Dict[str, Any]:
        return await self.info.get()

    # --- klippy ----------------------------------------------------------------

    async def _remote_store_profile(self, profile: Any = None,
                                    activate_extruder: Optional[str] = None,
                                    working_point: Any = None) -> None:
        # Called by klippy (action_call_remote_method): no one to answer, so
        # a refusal goes to the log and to clients as a notification.
        try:
            parsed = await self.parse_profile_off_loop(profile)
            if activate_extruder is not None:  # checked before anything is stored
                extruder = self._extruder_arg(activate_extruder)
                wp = self._wp_arg(self.default_wp if working_point is None
                                  else working_point)
            await self.profiles.store_profile(parsed, "klippy")
            if activate_extruder is not None:
                await self._activate(parsed.name, extruder, wp)
        except self.server.error as e:
            logging.info(f"flowloop_store_profile refused: {e}")
            self.profiles.notify("refused", "", source="klippy", reason=str(e))
