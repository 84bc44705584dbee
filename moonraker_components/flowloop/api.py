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
from flowloop.material.active import ActiveProfile, active_to_stored

from ...common import RequestType, WebRequest
from . import args
from .errors import quoted
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

    def _not_found(self, name: str) -> Exception:
        return args.refusal(f"no profile named {quoted(name)}", 404)

    def _known(self, name: str) -> fl_profile.Profile:
        try:
            return self.store.known(name)
        except UnknownProfile:
            raise self._not_found(name) from None

    def parse_profile(self, value: Any) -> fl_profile.Profile:
        if value is None:
            raise args.refusal("the profile is missing (argument 'profile')")
        try:
            if isinstance(value, str):  # JSON text: decoded without recursion
                return fl_profile.decode_profile(_utf8(value))
            return fl_profile.profile_from_dict(value)
        except FlowloopError as e:
            raise args.refusal(f"argument 'profile': {e}") from None
        except RecursionError:  # a nesting no profile has
            raise args.refusal("argument 'profile': nested too deeply to be a "
                               "profile") from None

    async def parse_profile_off_loop(self, value: Any) -> fl_profile.Profile:
        # Validating a large profile takes milliseconds of CPU: in a thread,
        # Moonraker keeps answering other clients meanwhile.
        return await self.eventloop.run_in_thread(self.parse_profile, value)

    async def _activate(self, name: str, extruder: str, wp: float) -> Dict[str, Any]:
        entry = ActiveProfile(name=name, working_point=wp)
        try:
            return await self.profiles.activate(extruder, entry)
        except UnknownProfile:  # deleted meanwhile
            raise self._not_found(name) from None

    # --- endpoints -----------------------------------------------------------

    async def _handle_profile(self, web_request: WebRequest) -> Dict[str, Any]:
        req_type = web_request.get_request_type()
        if req_type == RequestType.POST:
            profile = await self.parse_profile_off_loop(
                web_request.get_args().get("profile"))
            return await self.profiles.store_profile(profile, "api")
        name = args.profile_name(web_request)
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
        name = args.profile_name(web_request)
        extruder = args.extruder(web_request.get_args())
        entry = self.store.active.get(extruder)
        wp = args.working_point(web_request.get_args(), self.default_wp
                                if entry is None else entry.working_point)
        return await self._activate(name, extruder, wp)

    async def _handle_plot(self, web_request: WebRequest) -> str:
        profile = self._known(args.profile_name(web_request))
        wp = args.working_point(web_request.get_args(), self.default_wp)
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
                extruder = args.extruder({"activate_extruder": activate_extruder},
                                         "activate_extruder")
                wp = args.working_point({} if working_point is None else
                                        {"working_point": working_point},
                                        self.default_wp)
            await self.profiles.store_profile(parsed, "klippy")
            if activate_extruder is not None:
                await self._activate(parsed.name, extruder, wp)
        except self.server.error as e:
            logging.info(f"flowloop_store_profile refused: {e}")
            self.profiles.notify("refused", "", source="klippy", reason=str(e))
