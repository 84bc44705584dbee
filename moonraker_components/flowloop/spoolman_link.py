# flowloop component: the Spoolman link.
#
# Loading a spool (Moonraker's [spoolman] sets the active spool) activates,
# on the spool's extruder, the profile for the spool's filament: the one kept
# on the filament in Spoolman for this printer's hotend (`hotend:`), stored
# here as the local copy, else a local profile naming the filament; of
# several local ones, the latest measured (one rule for both:
# flowloop.material.active.profile_for_filament). A profile stored here for a
# filament Spoolman knows is written onto that filament for this hotend; one
# for a filament Spoolman does not know is refused. The field's format and
# who wins when two printers write at once: flowloop.material.spoolman_field.
#
# Spoolman down (unreachable, over 2 s, 5xx): one line in the log and in
# flowloop's info, the active profile unchanged; the spool is looked up and
# the profiles not yet written are written on a timer with backoff
# (spoolman_field.retry_delay_s: 2 s doubling to 5 min, until done) and once
# Moonraker reconnects to Spoolman (Moonraker does not announce the same
# spool twice; a slow Spoolman stays connected).
#
# Moonraker keeps one active spool per printer: on a toolchanger the spool is
# the tool's that prints when it is set (the tool change macro sets each
# tool's spool; flowloop.material.active.spool_extruder), unless
# spoolman_extruder names one extruder.
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import asyncio
import logging
from typing import TYPE_CHECKING, Any, Dict, Optional, Set, Tuple

from flowloop.errors import FlowloopError
from flowloop.material import spoolman_field as sf
from flowloop.material.active import (
    ActiveProfile,
    follow_spool,
    keeping_working_point,
    profile_for_filament,
    spool_extruder,
    spool_filament_id,
)
from flowloop.material.profile import Profile
from flowloop.nesting import check_json_depth

from ...utils import json_wrapper as jsonw
from .args import refusal
from .errors import one_line, quoted
from .profiles import Profiles
from .store import ProfileStore

if TYPE_CHECKING:
    from ...server import Server

CONNECT_TIMEOUT_S = 1.0
REQUEST_TIMEOUT_S = 2.0


class SpoolmanDown(Exception):
    """Spoolman could not be asked (unreachable, timed out, 5xx)."""


class SpoolmanLink:
    def __init__(self, server: Server, extruder: Optional[str], default_wp: float,
                 store: ProfileStore, profiles: Profiles,
                 hotend: Optional[str] = None) -> None:
        self.server = server
        self.extruder = extruder   # None: the tool that prints
        self.default_wp = default_wp
        self.store = store
        self.profiles = profiles
        self.hotend = hotend
        # the active spool whose filament Spoolman could not be asked for
        self.unresolved_spool: Any = None
        # profiles to write onto their filament once Spoolman answers
        self.unwritten: Set[str] = set()
        self.field_registered = False
        self.last_problem: Optional[str] = None
        # retries of the work above: failed tries in a row, one at a time
        self.failures = 0
        self.retry_timer = server.get_event_loop().register_timer(self._retry)
        self.catch_up_lock = asyncio.Lock()
        server.register_event_handler("spoolman:active_spool_set",
                                      self._on_active_spool_set)
        server.register_event_handler("spoolman:spoolman_status_changed",
                                      self._on_spoolman_status)
        if hotend is not None:
            profiles.before_store.append(self._check_filament)
            profiles.after_store.append(self._share)

    def check_spoolman(self) -> None:
        if self.server.lookup_component("spoolman", None) is None:
            self.server.add_warning(
                "[flowloop] spoolman_link is enabled but Moonraker has no "
                "[spoolman] section: profiles will not follow the active spool")

    def status(self) -> Dict[str, Any]:
        """For flowloop's info: the hotend key, what is waiting, the last
        problem (None once Spoolman answered again)."""
        return {"hotend": self.hotend, "unwritten": sorted(self.unwritten),
                "unresolved_spool": self.unresolved_spool,
                "problem": self.last_problem}

    # --- Spoolman's API ------------------------------------------------------------

    def _problem(self, message: str) -> None:
        self.last_problem = message
        logging.info(f"flowloop: {message}")

    async def _api(self, method: str, path: str, body: Any = None) -> Tuple[int, Any]:
        """(status, JSON) of one request; SpoolmanDown when it cannot say."""
        spoolman = self.server.lookup_component("spoolman", None)
        if spoolman is None:
            raise SpoolmanDown("Moonraker has no [spoolman]")
        http_client = self.server.lookup_component("http_client")
        resp = await http_client.request(
            method, f"{spoolman.spoolman_url}{path}", body,
            connect_timeout=CONNECT_TIMEOUT_S, request_timeout=REQUEST_TIMEOUT_S)
        if resp.status_code == 599 or resp.status_code >= 500:
            raise SpoolmanDown(f"HTTP {resp.status_code}")
        try:
            check_json_depth(resp.content, "Spoolman's answer")
            return resp.status_code, resp.json() if resp.content else None
        except (jsonw.JSONDecodeError, FlowloopError) as e:  # not JSON we read
            logging.info(f"flowloop: Spoolman {method} {path}: {one_line(e)}")
            return resp.status_code, None

    # --- loading a spool --------------------------------------------------------

    async def _on_active_spool_set(self, data: Dict[str, Any]) -> None:
        spool_id = data.get("spool_id") if isinstance(data, dict) else None
        self.unresolved_spool = None
        if spool_id is None:
            return
        try:
            status, spool = await self._api("GET", f"/v1/spool/{spool_id}")
        except SpoolmanDown as e:
            self.unresolved_spool = spool_id
            self._problem(f"Spoolman spool {spool_id}: {e}; the active profile"
                          " stays until Spoolman answers")
            self._schedule_retry()
            return
        self.last_problem = None
        if status != 200 or not isinstance(spool, dict):
            logging.info(f"flowloop: Spoolman spool {spool_id}: HTTP {status}")
            return
        extruder = spool_extruder(self.extruder, await self._printing_tool())
        entry = await self._shared_entry(spool, extruder) or follow_spool(
            spool, self.store.profiles, self.store.active.get(extruder),
            self.default_wp)
        if entry is None:
            logging.info(f"flowloop: no profile for the filament of Spoolman "
                         f"spool {spool_id}")
            return
        try:
            await self.profiles.activate(extruder, entry)
        except self.server.error as e:
            logging.info(f"flowloop: Spoolman link could not activate "
                         f"{quoted(entry.name)}: {e}")

    async def _printing_tool(self) -> Optional[str]:
        """The extruder klippy says is active (None: not asked, or no
        answer within REQUEST_TIMEOUT_S)."""
        if self.extruder is not None:
            return None
        klippy_apis = self.server.lookup_component("klippy_apis")
        try:
            status = await asyncio.wait_for(klippy_apis.query_objects(
                {"toolhead": ["extruder"]}, default={}), REQUEST_TIMEOUT_S)
        except asyncio.TimeoutError:
            return None
        return status.get("toolhead", {}).get("extruder")

    async def _shared_entry(self, spool: Dict[str, Any],
                            extruder: str) -> Optional[ActiveProfile]:
        """The profile for the spool's filament and this hotend: Spoolman's
        (stored here as the local copy), or a later one measured here, which
        is then written back (Spoolman has no conditional write: another
        printer's write from an older read can have replaced it). None if
        neither exists, or Spoolman's field holds bad data."""
        filament = spool.get("filament")
        if self.hotend is None or not isinstance(filament, dict):
            return None
        try:
            shared = sf.read_field(filament).get(self.hotend)
        except FlowloopError as e:
            self._problem(f"{e}; not used")
            return None
        mine = profile_for_filament(self.store.profiles, spool_filament_id(spool))
        if mine is not None and (shared is None or (mine != shared
                                                    and sf.newer(mine, shared))):
            if shared is not None:
                logging.info(f"flowloop: {sf.filament_label(filament)} keeps"
                             f" {quoted(shared.name)} for hotend {self.hotend};"
                             f" the later {quoted(mine.name)} measured here is"
                             " written back")
            await self._write(mine)
            return self._active(mine.name, extruder)
        if shared is None:
            return None
        local = self.store.profiles.get(shared.name)
        if local is not None and local != shared \
                and sf.filament_id_of(local) != sf.filament_id_of(shared):
            self._problem(f"{sf.filament_label(filament)} keeps profile"
                          f" {quoted(shared.name)} for hotend {self.hotend}, but"
                          " a local profile of that name is for another"
                          " filament: not replaced, not used")
            return None
        if local != shared:
            await self.profiles.store_profile(shared, "spoolman")
        return self._active(shared.name, extruder)

    def _active(self, name: str, extruder: str) -> ActiveProfile:
        return keeping_working_point(name, self.store.active.get(extruder),
                                     self.default_wp)

    # --- storing a profile ------------------------------------------------------

    async def _check_filament(self, profile: Profile, source: str) -> None:
        """Before a profile is stored: refuse one for a filament Spoolman
        does not know (Spoolman down: stored, written when it is back). One
        that came from Spoolman's filament needs no asking."""
        fid = sf.filament_id_of(profile)
        if fid is None or source == "spoolman":
            return
        try:
            sf.check_filament_id(fid)
        except FlowloopError as e:
            raise refusal(f"profile {quoted(profile.name)}: {e} "
                          f"(identity.spoolman_filament_id)") from None
        try:
            status, _ = await self._api("GET", f"/v1/filament/{fid}")
        except SpoolmanDown:
            return
        if status == 404:
            raise refusal(f"profile {quoted(profile.name)}: Spoolman has no"
                          f" filament {fid} (identity.spoolman_filament_id)")

    async def _share(self, profile: Profile, source: str) -> None:
        """After a profile is stored, before the store is answered: onto its
        filament (one that came from Spoolman is there already). Awaited, so
        that two printers' stores both answered have both written: a spool
        loaded after them finds what the race left and mends it."""
        if source != "spoolman" and sf.filament_id_of(profile) is not None:
            await self._write(profile)

    async def _write(self, profile: Profile) -> None:
        """Put the profile on its filament for this hotend: read, merge,
        write, read back (another printer may have written meanwhile)."""
        fid = sf.filament_id_of(profile)
        try:
            await self._register_field()
            for _ in range(sf.WRITE_ATTEMPTS):
                current = await self._field(fid)
                if current is None:
                    break
                field = sf.merged(current, self.hotend, profile)
                if field[self.hotend] != profile:
                    self._lost_to(fid, profile, field[self.hotend])
                    break
                status, body = await self._api(
                    "PATCH", f"/v1/filament/{fid}",
                    {"extra": {sf.FIELD_KEY: sf.field_value(field)}})
                if status != 200:
                    self._problem(f"Spoolman filament {fid}: writing"
                                  f" {quoted(profile.name)} answered HTTP {status}")
                    break
                written = await self._field(fid)
                kept = None if written is None else written.get(self.hotend)
                if kept == profile:
                    logging.info(f"flowloop: profile {quoted(profile.name)}"
                                 f" written onto Spoolman filament {fid} for"
                                 f" hotend {self.hotend}")
                    break
                if written is None or (kept is not None
                                       and not sf.newer(profile, kept)):
                    self._lost_to(fid, profile, kept)
                    break
                # another printer wrote the field from an older read: again
            else:
                self._problem(f"Spoolman filament {fid}: other printers kept"
                              f" writing it; {quoted(profile.name)} is put back"
                              " at this printer's next spool of it")
            self.unwritten.discard(profile.name)
        except SpoolmanDown as e:
            self.unwritten.add(profile.name)
            self._problem(f"Spoolman filament {fid}: {e}; profile"
                          f" {quoted(profile.name)} is written when it answers")
            self._schedule_retry()

    def _lost_to(self, fid: int, profile: Profile, kept: Optional[Profile]) -> None:
        if kept is None:
            return
        logging.info(f"flowloop: Spoolman filament {fid} keeps a later profile"
                     f" for hotend {self.hotend} ({quoted(kept.name)}, measured"
                     f" {kept.provenance.measured_at}): {quoted(profile.name)}"
                     " is not written there")

    async def _register_field(self) -> None:
        if self.field_registered:
            return
        status, body = await self._api(
            "POST", f"/v1/field/filament/{sf.FIELD_KEY}", sf.field_registration())
        if status != 200:
            raise SpoolmanDown(f"registering its {sf.FIELD_KEY} field: HTTP"
                               f" {status} {body}")
        self.field_registered = True

    async def _field(self, fid: int) -> Optional[Dict[str, Profile]]:
        """The filament's profiles; None (said in the log) when Spoolman has
        no such filament or its field holds bad data (never overwritten)."""
        status, filament = await self._api("GET", f"/v1/filament/{fid}")
        if status != 200 or not isinstance(filament, dict):
            self._problem(f"Spoolman filament {fid}: HTTP {status}")
            return None
        try:
            return sf.read_field(filament)
        except FlowloopError as e:
            self._problem(f"{e}; not overwritten")
            return None

    # --- Spoolman back ---------------------------------------------------------

    async def _on_spoolman_status(self, data: Dict[str, Any]) -> None:
        if not (isinstance(data, dict) and data.get("spoolman_connected")):
            return
        self.last_problem = None
        await self._catch_up()

    def _work_left(self) -> bool:
        return bool(self.unwritten) or self.unresolved_spool is not None

    def _schedule_retry(self) -> None:
        """The next try of what is left, after the backoff's wait (a try
        already waiting is not moved)."""
        if self._work_left() and not self.retry_timer.is_running():
            self.retry_timer.start(delay=sf.retry_delay_s(self.failures))

    async def _retry(self, eventtime: float) -> float:
        await self._catch_up()
        if not self._work_left():
            self.failures = 0
            self.retry_timer.stop()
            return eventtime
        self.failures += 1
        return eventtime + sf.retry_delay_s(self.failures)

    def close(self) -> None:
        self.retry_timer.stop()

    async def _catch_up(self) -> None:
        """Write the profiles not yet written, look up the spool not yet
        resolved (still Moonraker's active one)."""
        async with self.catch_up_lock:
            for name in sorted(self.unwritten):
                profile = self.store.profiles.get(name)
                if profile is None:
                    self.unwritten.discard(name)
                else:
                    await self._write(profile)
            spoolman = self.server.lookup_component("spoolman", None)
            spool_id = self.unresolved_spool
            if spool_id is None:
                return
            if spoolman is None or getattr(spoolman, "spool_id", None) != spool_id:
                self.unresolved_spool = None   # another spool since: its own event
                return
            logging.info(f"flowloop: looking up Spoolman spool {spool_id} again")
            await self._on_active_spool_set({"spool_id": spool_id})
