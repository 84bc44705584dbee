# flowloop component: nozzle health from grip, print after print.
#
# At a job's start and end (Moonraker's history) the evidence klippy's
# [flowrate_limiter] has summed since the profile was activated is asked
# (flowrate_limiter/nozzle_evidence); the difference is the job's. Its
# estimate (the hotend's melt capacity against the profile) is kept in the
# database per hotend (`hotend:` of [flowloop]) and profile, the newest
# MAX_PRINTS; the verdict over them decides a warning, which goes out as a
# Moonraker announcement (Mainsail's and Fluidd's notification list shows
# it), a console line and notify_flowloop_nozzle_health. Everything that
# decides is in flowloop.control.nozzle_health.
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any, Dict, List, Optional

from flowloop.control import nozzle_health as nh
from flowloop.control.health_plot import svg
from flowloop.errors import FlowloopError
from flowloop.material.profile import is_extruder_name

from ...common import RequestType, TransportType, WebRequest
from . import args
from .endpoints import register_endpoint
from .errors import one_line, quoted

if TYPE_CHECKING:
    from ...server import Server

KLIPPY_ENDPOINT = "flowrate_limiter/nozzle_evidence"
PREFIX = "nozzle_health:"
MAX_PRINTS = 50
DEFAULT_HOTEND = "default"
ANNOUNCEMENT_FEED = "flowloop"


def history_key(hotend: str, profile: str) -> str:
    return (f"{PREFIX}{hotend.encode('utf-8').hex()}:"
            f"{profile.encode('utf-8').hex()}")


class NozzleHealth:
    def __init__(self, server: Server, db: Any, hotend: Optional[str]) -> None:
        self.server = server
        self.db = db  # the flowloop namespace (ProfileStore's)
        self.hotend = hotend or DEFAULT_HOTEND
        self.klippy = server.lookup_component("klippy_connection")
        self.started: Optional[Dict[str, Any]] = None  # job id, evidence at start
        server.register_notification("flowloop:nozzle_health",
                                     "flowloop_nozzle_health")
        server.register_event_handler("history:history_changed", self._on_history)
        register_endpoint(server, "/server/flowloop/nozzle_health",
                          RequestType.GET | RequestType.POST, self._handle)
        register_endpoint(server, "/server/flowloop/nozzle_health/plot",
                          RequestType.GET, self._handle_plot,
                          transports=TransportType.HTTP, wrap_result=False,
                          content_type="image/svg+xml")

    # --- jobs ----------------------------------------------------------------
    def tool_hotend(self, extruder: str) -> str:
        return nh.tool_hotend(self.hotend, extruder)

    async def _evidence(self) -> Dict[str, Optional[Dict[str, Any]]]:
        """Every tool's evidence (tools without a limiter are left out)."""
        if not self.klippy.is_ready():
            return {}
        kapis = self.server.lookup_component("klippy_apis")
        objects = await kapis.get_object_list(default=[])
        out: Dict[str, Optional[Dict[str, Any]]] = {}
        problem = None
        for extruder in sorted(filter(is_extruder_name, objects)):
            try:
                answer = await self.klippy.request(
                    WebRequest(KLIPPY_ENDPOINT, {"extruder": extruder}))
            except self.server.error as e:  # no [flowrate_limiter] on it
                problem = e
                continue
            out[extruder] = (answer.get("evidence") if isinstance(answer, dict)
                             else None)
        if not out and problem is not None:
            logging.info(f"flowloop: no nozzle evidence from klippy: "
                         f"{one_line(problem)}")
        return out

    async def _on_history(self, event: Dict[str, Any]) -> None:
        job = event.get("job") or {}
        if event.get("action") == "added":
            self.started = {"job_id": job.get("job_id"),
                            "evidence": await self._evidence()}
        elif event.get("action") == "finished" and self.started is not None \
                and self.started["job_id"] == job.get("job_id"):
            start, self.started = self.started["evidence"], None
            try:
                end = await self._evidence()
                for extruder, evidence in end.items():
                    before = start.get(extruder)
                    if not nh.printed_between(before, evidence):
                        continue   # a tool that did not print this job
                    await self.record(job.get("job_id"), before, evidence,
                                      self.tool_hotend(extruder))
            except Exception as e:  # never take Moonraker's job handling down
                logging.exception(f"flowloop: nozzle health of job "
                                  f"{job.get('job_id')} failed: {one_line(e)}")

    async def record(self, job_id: Any, start: Optional[Dict[str, Any]],
                     end: Optional[Dict[str, Any]],
                     hotend: Optional[str] = None) -> Dict[str, Any]:
        """A job's estimate stored under its hotend and profile; the verdict."""
        hotend = hotend or self.hotend
        evidence = nh.evidence_between(
            None if start is None else nh.PrintEvidence.from_dict(start),
            None if end is None else nh.PrintEvidence.from_dict(end))
        found = nh.estimate(evidence)
        entry = {"job_id": job_id, "time": time.time(), **found.to_dict()}
        if not found.profile:
            logging.info(f"flowloop: nozzle health of job {job_id}: {found.reason}")
            return {"entry": entry, "verdict": None}
        key = history_key(hotend, found.profile)
        stored = await self.db.get(key, {"hotend": hotend,
                                         "profile": found.profile, "prints": []})
        was_warning = (stored.get("verdict") or {}).get("warn", False)
        stored["prints"] = (stored["prints"] + [entry])[-MAX_PRINTS:]
        verdict = self._verdict(stored["prints"])
        stored["verdict"] = verdict.__dict__
        await self.db.insert(key, stored)
        if verdict.warn:
            self._warn(stored, verdict, first=not was_warning)
        return {"entry": entry, "verdict": verdict.__dict__}

    @staticmethod
    def _verdict(prints: List[Dict[str, Any]]) -> nh.Verdict:
        return nh.judge([nh.PrintEstimate.from_dict(p) for p in prints])

    def _warn(self, stored: Dict[str, Any], verdict: nh.Verdict,
              first: bool) -> None:
        title = (f"flowloop: nozzle health, hotend {stored['hotend']}, "
                 f"profile {stored['profile']}")
        evidence = ", ".join(
            f"{p['ratio']:.0%}" for p in stored["prints"][-8:]
            if p.get("ratio") is not None)
        text = (f"{verdict.text}. Melt capacity against the profile over the "
                f"last prints: {evidence}.")
        self.server.send_event("flowloop:nozzle_health", {**stored, "text": text})
        self.server.send_event("server:gcode_response", f"// {title}: {text}")
        if first:  # once when it starts, not every print it goes on
            announcements = self.server.lookup_component("announcements", None)
            if announcements is not None:
                announcements.add_internal_announcement(
                    title, text, "", "high", ANNOUNCEMENT_FEED)

    # --- endpoints -------------------------------------------------------------
    async def histories(self) -> List[Dict[str, Any]]:
        """Every hotend's (a toolchanger's tools each have theirs)."""
        items = await self.db.items()
        return [value for key, value in items if key.startswith(PREFIX)]

    async def _handle(self, web_request: WebRequest) -> Dict[str, Any]:
        if web_request.get_request_type() == RequestType.POST:
            # a print's evidence from elsewhere (a replayed or offline print)
            given = web_request.get_args()
            try:
                return await self.record(given.get("job_id"), given.get("start"),
                                         given.get("evidence"))
            except FlowloopError as e:
                raise args.refusal(one_line(e)) from None
        return {"hotend": self.hotend, "histories": await self.histories()}

    async def _handle_plot(self, web_request: WebRequest) -> bytes:
        name = args.text(web_request.get_args(), "profile", "profile name")
        given = web_request.get_args()
        hotend = args.text(given, "hotend", "hotend") if "hotend" in given \
            else self.hotend
        stored = await self.db.get(history_key(hotend, name), None)
        if stored is not None:
            prints = [nh.PrintEstimate.from_dict(p) for p in stored["prints"]]
            return svg(prints, f"hotend {hotend}, profile {name}").encode()
        raise args.refusal(f"no nozzle health for profile {quoted(name)}", 404)
