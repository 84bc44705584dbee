# flowloop: material profiles and flowloop status for Moonraker clients.
#
# Section [flowloop] in moonraker.conf. Installed by `flowloop install` as a
# link in moonraker/components/. The thinking is in the flowloop package;
# this file registers endpoints and talks to klippy and the database.
#
# Profiles live in the database namespace "flowloop", one record per profile
# under a key made from the name's UTF-8 hex (a name never becomes a key path,
# a file name or G-code). The namespace is protected: Moonraker's database API
# may read it, only this component writes it, so every write is validated.
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import asyncio
import json
import logging
from typing import TYPE_CHECKING, Any, Dict, Optional

import flowloop
from flowloop.errors import FlowloopError
from flowloop.material import plot
from flowloop.material import profile as fl_profile

from ..common import RequestType, WebRequest

if TYPE_CHECKING:
    from ..confighelper import ConfigHelper
    from .klippy_apis import KlippyAPI
    from .klippy_connection import KlippyConnection

NAMESPACE = "flowloop"
PROFILE_PREFIX = "profile:"
ACTIVE_KEY = "active"
KLIPPY_ENDPOINT = "flowloop/set_active_profile"


def profile_key(name: str) -> str:
    return PROFILE_PREFIX + name.encode("utf-8").hex()


def quoted(name: str) -> str:
    """A name for a one-line message: JSON-quoted, ASCII only."""
    return json.dumps(name)


class Flowloop:
    def __init__(self, config: ConfigHelper) -> None:
        self.server = config.get_server()
        self.eventloop = self.server.get_event_loop()
        self.spoolman_link = config.getboolean("spoolman_link", False)
        self.spoolman_extruder = config.get("spoolman_extruder", "extruder")
        if not fl_profile.is_extruder_name(self.spoolman_extruder):
            raise config.error(
                f"[flowloop] spoolman_extruder: {self.spoolman_extruder!r} is not "
                f"an extruder name (extruder, extruder1, ...)")
        self.default_wp = config.getfloat(
            "working_point", fl_profile.DEFAULT_WORKING_POINT, minval=0.0, maxval=1.0)
        self.klippy_apis: KlippyAPI = self.server.lookup_component("klippy_apis")
        self.klippy: KlippyConnection = self.server.lookup_component(
            "klippy_connection")
        database = self.server.lookup_component("database")
        self.db = database.register_local_namespace(NAMESPACE)
        # The database's content, validated. Changed only under write_lock and
        # only after the database write, so a write that raises changes
        # nothing here and concurrent writes cannot interleave. (Moonraker
        # logs an sqlite error on insert instead of raising it.)
        self.profiles: Dict[str, fl_profile.Profile] = {}
        self.active: Dict[str, Dict[str, Any]] = {}  # extruder -> name, wp
        self.write_lock = asyncio.Lock()
        for path, methods, handler in (
            ("/server/flowloop/info", RequestType.GET, self._handle_info),
            ("/server/flowloop/profile",
             RequestType.GET | RequestType.POST | RequestType.DELETE,
             self._handle_profile),
            ("/server/flowloop/profiles", RequestType.GET, self._handle_list),
            ("/server/flowloop/profile/activate", RequestType.POST,
             self._handle_activate),
        ):
            self.server.register_endpoint(path, methods, handler)
        self.server.register_endpoint(
            "/server/flowloop/profile/plot", RequestType.GET, self._handle_plot,
            wrap_result=False, content_type="image/svg+xml")
        self.server.register_notification(
            "flowloop:profile_changed", "flowloop_profile_changed")
        self.server.register_remote_method(
            "flowloop_store_profile", self._remote_store_profile)
        self.server.register_event_handler(
            "server:klippy_ready", self._on_klippy_ready)
        if self.spoolman_link:
            self.server.register_event_handler(
                "spoolman:active_spool_set", self._on_active_spool_set)

    async def component_init(self) -> None:
        for key, value in await self.db.items():
            if key == ACTIVE_KEY and isinstance(value, dict):
                self.active = value
            elif key.startswith(PROFILE_PREFIX):
                try:
                    profile = fl_profile.profile_from_dict(value)
                except FlowloopError as e:
                    # Kept in the database untouched: a newer flowloop may read it.
                    logging.info(f"flowloop: stored profile {key} skipped: {e}")
                    continue
                self.profiles[profile.name] = profile
        if self.spoolman_link and \
                self.server.lookup_component("spoolman", None) is None:
            self.server.add_warning(
                "[flowloop] spoolman_link is enabled but Moonraker has no [spoolman] "
                "section: profiles will not follow the active spool")

    # --- helpers -------------------------------------------------------------

    def _error(self, msg: str, code: int = 400) -> Exception:
        # One ASCII line: it becomes an HTTP reason phrase.
        text = " ".join(str(msg).split()).encode("ascii", "backslashreplace")
        return self.server.error(text.decode(), code)

    def _name_arg(self, web_request: WebRequest) -> str:
        name = web_request.get("name", None)
        if name is None:
            raise self._error("the profile name is missing (argument 'name')")
        if not isinstance(name, str):
            raise self._error("the profile name must be a string")
        try:
            return fl_profile.check_name(name)
        except FlowloopError as e:
            raise self._error(str(e)) from None

    def _known(self, name: str) -> fl_profile.Profile:
        profile = self.profiles.get(name)
        if profile is None:
            raise self._error(f"no profile named {quoted(name)}", 404)
        return profile

    def _wp_arg(self, web_request: WebRequest, default: float) -> float:
        value = web_request.get("working_point", default)
        try:
            if isinstance(value, str):
                value = float(value)
            return fl_profile.check_working_point(value)
        except (ValueError, FlowloopError) as e:
            raise self._error(str(e)) from None

    def _notify(self, action: str, name: str, **extra: Any) -> None:
        self.server.send_event("flowloop:profile_changed",
                               {"action": action, "name": name, **extra})

    # --- storing -------------------------------------------------------------

    def parse_profile(self, value: Any) -> fl_profile.Profile:
        if value is None:
            raise self._error("the profile is missing (argument 'profile')")
        if isinstance(value, str):
            try:
                value = json.loads(value)
            except ValueError:
                raise self._error("the profile is not valid JSON") from None
        try:
            return fl_profile.profile_from_dict(value)
        except FlowloopError as e:
            raise self._error(str(e)) from None

    async def store_profile(self, profile: fl_profile.Profile,
                            source: str) -> Dict[str, Any]:
        name = profile.name
        async with self.write_lock:
            action = "updated" if name in self.profiles else "created"
            await self.db.insert(profile_key(name),
                                 fl_profile.profile_to_dict(profile))
            self.profiles[name] = profile
        self._notify(action, name, source=source,
                     profile=fl_profile.summary(profile))
        active_for = [ext for ext, entry in self.active.items()
                      if entry.get("name") == name]
        for extruder in active_for:  # klippy keeps a copy: send the new one
            await self._send_to_klippy(extruder, quiet=True)
        return {"name": name, "action": action}

    async def delete_profile(self, name: str) -> Dict[str, Any]:
        async with self.write_lock:
            self._known(name)
            stopped = sorted(ext for ext, entry in self.active.items()
                             if entry.get("name") == name)
            active = {ext: entry for ext, entry in self.active.items()
                      if ext not in stopped}
            await self.db.delete(profile_key(name))
            if stopped:
                await self.db.insert(ACTIVE_KEY, active)
            del self.profiles[name]
            self.active = active
        for extruder in stopped:  # clears klippy's copy
            await self._send_to_klippy(extruder, quiet=True)
        self._notify("deleted", name, deactivated=stopped)
        return {"name": name, "action": "deleted", "deactivated": stopped}

    async def _remote_store_profile(self, profile: Any = None,
                                    activate_extruder: Optional[str] = None,
                                    working_point: Optional[float] = None) -> None:
        # Called by klippy (action_call_remote_method): no one to answer, so
        # a refusal goes to the log and to clients as a notification.
        try:
            parsed = self.parse_profile(profile)
            await self.store_profile(parsed, "klippy")
            if activate_extruder is not None:
                await self.activate(parsed.name, activate_extruder,
                                    self.default_wp if working_point is None
                                    else working_point)
        except self.server.error as e:
            logging.info(f"flowloop_store_profile refused: {e}")
            self._notify("refused", "", source="klippy", reason=str(e))

    async def activate(self, name: str, extruder: Any,
                       wp: float) -> Dict[str, Any]:
        if not fl_profile.is_extruder_name(extruder):
            raise self._error(f"{quoted(str(extruder))} is not an extruder name "
                              f"(extruder, extruder1, ...)")
        try:
            wp = fl_profile.check_working_point(wp)
        except FlowloopError as e:
            raise self._error(str(e)) from None
        entry = {"name": name, "working_point": wp}
        async with self.write_lock:
            self._known(name)  # again under the lock: a delete may have run
            sent = await self._send_to_klippy(extruder, entry)
            active = {**self.active, extruder: entry}
            await self.db.insert(ACTIVE_KEY, active)
            self.active = active
        self._notify("activated", name, extruder=extruder, working_point=wp,
                     sent_to_klippy=sent)
        return {"extruder": extruder, "name": name, "working_point": wp,
                "sent_to_klippy": sent}

    async def _send_to_klippy(self, extruder: str,
                              entry: Optional[Dict[str, Any]] = None,
                              quiet: bool = False) -> bool:
        """Send an extruder's activation (default: the stored one; none clears
        it) to klippy; False if klippy is not ready."""
        if not self.klippy.is_ready():
            return False
        if entry is None:
            entry = self.active.get(extruder) or {}
        profile = self.profiles.get(entry.get("name", ""))
        params = {"extruder": extruder,
                  "profile": None if profile is None
                  else fl_profile.profile_to_dict(profile),
                  "working_point": entry.get("working_point", self.default_wp)}
        try:
            await self.klippy.request(WebRequest(KLIPPY_ENDPOINT, params))
        except self.server.error as e:
            if not quiet:
                raise self._error(f"klippy refused the profile: {e}") from None
            logging.info(f"flowloop: klippy refused the profile for {extruder}: {e}")
            return False
        return True

    async def _on_klippy_ready(self) -> None:
        for extruder in sorted(self.active):
            sent = await self._send_to_klippy(extruder, quiet=True)
            logging.info(f"flowloop: active profile for {extruder} "
                         f"{'sent to' if sent else 'NOT accepted by'} klippy")

    async def _on_active_spool_set(self, data: Dict[str, Any]) -> None:
        spool_id = data.get("spool_id") if isinstance(data, dict) else None
        spoolman = self.server.lookup_component("spoolman", None)
        if spool_id is None or spoolman is None:
            return
        http_client = self.server.lookup_component("http_client")
        resp = await http_client.get(f"{spoolman.spoolman_url}/v1/spool/{spool_id}",
                                     connect_timeout=1.0, request_timeout=2.0)
        if resp.has_error():
            logging.info(f"flowloop: Spoolman spool {spool_id}: HTTP "
                         f"{resp.status_code}")
            return
        spool = resp.json()
        filament = (spool.get("filament") if isinstance(spool, dict) else None) or {}
        filament_id = filament.get("id")
        matches = sorted(name for name, p in self.profiles.items()
                         if p.identity.spoolman_filament_id == filament_id)
        if filament_id is None or not matches:
            logging.info(f"flowloop: no profile for Spoolman filament {filament_id}")
            return
        entry = self.active.get(self.spoolman_extruder) or {}
        try:
            await self.activate(matches[0], self.spoolman_extruder,
                                entry.get("working_point", self.default_wp))
        except self.server.error as e:
            logging.info(f"flowloop: Spoolman link could not activate "
                         f"{quoted(matches[0])}: {e}")

    # --- endpoints -----------------------------------------------------------

    async def _handle_profile(self, web_request: WebRequest) -> Dict[str, Any]:
        req_type = web_request.get_request_type()
        if req_type == RequestType.POST:
            profile = self.parse_profile(web_request.get("profile", None))
            return await self.store_profile(profile, "api")
        name = self._name_arg(web_request)
        if req_type == RequestType.DELETE:
            return await self.delete_profile(name)
        return {"name": name,
                "profile": fl_profile.profile_to_dict(self._known(name))}

    async def _handle_list(self, web_request: WebRequest) -> Dict[str, Any]:
        return {"profiles": [fl_profile.summary(self.profiles[name])
                             for name in sorted(self.profiles)],
                "active": dict(self.active)}

    async def _handle_activate(self, web_request: WebRequest) -> Dict[str, Any]:
        name = self._name_arg(web_request)
        extruder = web_request.get_str("extruder", "extruder")
        entry = self.active.get(extruder) or {}
        wp = self._wp_arg(web_request, entry.get("working_point", self.default_wp))
        return await self.activate(name, extruder, wp)

    async def _handle_plot(self, web_request: WebRequest) -> str:
        name = self._name_arg(web_request)
        profile = self._known(name)
        wp = self._wp_arg(web_request, self.default_wp)
        return await self.eventloop.run_in_thread(plot.svg, profile, wp)

    async def _handle_info(self, web_request: WebRequest) -> Dict[str, Any]:
        info: Dict[str, Any] = {
            "version": flowloop.__version__,
            "klippy_connected": False,
            "sections": [],
            "sensor_firmware": {},
            "profiles": len(self.profiles),
            "active_profiles": dict(self.active),
            "spoolman_link": self.spoolman_link,
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
