# flowloop component: nozzle health from grip, print after print.
#
# At a job's start and end (Moonraker's history) the evidence klippy's
# [flowrate_limiter] has summed since the profile was activated is asked
# (flowrate_limiter/nozzle_evidence); the difference is the job's. Its
# estimate (the hotend's melt capacity against the profile) is kept in the
# database per hotend (`hotend:` of [flowloop]) and profile (its own store,
# store.NozzleHealthStore), one record per job, the newest MAX_PRINTS_KEPT;
# the verdict over them decides a warning (nh.health_warning: which is said,
# and whether it is announced), which goes out as a Moonraker announcement
# linking the health plot (Mainsail's and Fluidd's notification list shows
# it), a console line and notify_flowloop_nozzle_health, names in them as
# nh.label shows them (one line, no markup). A POST (a print from elsewhere)
# is checked whole before anything is stored; a DELETE removes one profile's
# history. The melt ratio last judged for the profile a job starts with goes
# to the job's history entry (job_history.py), and goes with an activation of
# the profile to klippy (melt_ratio: klippy_sync.py), where the limiter's grip
# model starts from it. Everything that decides is in
# flowloop.control.nozzle_health.
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING, Any, Dict, List, Optional, Tuple

from flowloop.control import nozzle_health as nh
from flowloop.control.health_plot import svg
from flowloop.errors import FlowloopError
from flowloop.material.profile import is_extruder_name
from flowloop.report import job_figures

from ...common import RequestType, TransportType, WebRequest
from . import args
from .errors import one_line, quoted
from .job_history import JobHistory
from .store import NozzleHealthStore, ProfileStore

if TYPE_CHECKING:
    from ...server import Server

KLIPPY_ENDPOINT = "flowrate_limiter/nozzle_evidence"
DEFAULT_HOTEND = "default"
ANNOUNCEMENT_FEED = "flowloop"


class NozzleHealth:
    def __init__(self, server: Server, store: ProfileStore,
                 health: NozzleHealthStore, hotend: Optional[str],
                 job_history: JobHistory) -> None:
        self.server = server
        self.job_history = job_history
        self.store = store
        self.health = health
        self.hotend = hotend or DEFAULT_HOTEND
        self.klippy = server.lookup_component("klippy_connection")
        self.started: Optional[Dict[str, Any]] = None  # job id, evidence at start
        server.register_notification("flowloop:nozzle_health",
                                     "flowloop_nozzle_health")
        server.register_event_handler("history:history_changed", self._on_history)
        server.register_endpoint(
            "/server/flowloop/nozzle_health",
            RequestType.GET | RequestType.POST | RequestType.DELETE, self._handle)
        server.register_endpoint(
            "/server/flowloop/nozzle_health/plot", RequestType.GET,
            self._handle_plot, transports=TransportType.HTTP, wrap_result=False,
            content_type="image/svg+xml")

    # --- jobs ----------------------------------------------------------------
    def tool_hotend(self, extruder: str) -> str:
        return nh.tool_hotend(self.hotend, extruder)

    async def _evidence(self) -> Dict[str, Dict[str, Any]]:
        """Every tool's answer: its `evidence` and `model_melt_ratio`
        (tools without a limiter are left out)."""
        if not self.klippy.is_ready():
            return {}
        kapis = self.server.lookup_component("klippy_apis")
        objects = await kapis.get_object_list(default=[])
        out: Dict[str, Dict[str, Any]] = {}
        problem = None
        for extruder in sorted(filter(is_extruder_name, objects)):
            try:
                answer = await self.klippy.request(
                    WebRequest(KLIPPY_ENDPOINT, {"extruder": extruder}))
            except self.server.error as e:  # no [flowrate_limiter] on it
                problem = e
                continue
            out[extruder] = answer if isinstance(answer, dict) else {}
        if not out and problem is not None:
            logging.info(f"flowloop: no nozzle evidence from klippy: "
                         f"{one_line(problem)}")
        return out

    async def _on_history(self, event: Dict[str, Any]) -> None:
        job = event.get("job") or {}
        if event.get("action") == "added":
            self.started = {"job_id": job.get("job_id"),
                            "evidence": await self._evidence()}
            await self._history_melt_ratio(self.started["evidence"])
        elif event.get("action") == "finished" and self.started is not None \
                and self.started["job_id"] == job.get("job_id"):
            start, self.started = self.started["evidence"], None
            try:
                end = await self._evidence()
            except Exception as e:  # never take Moonraker's job handling down
                logging.exception(f"flowloop: nozzle health of job "
                                  f"{job.get('job_id')} failed: {one_line(e)}")
                return
            for extruder, answer in end.items():
                await self._record_tool(job.get("job_id"), extruder,
                                        start.get(extruder, {}).get("evidence"),
                                        answer.get("evidence"),
                                        answer.get("model_melt_ratio"))

    async def _history_melt_ratio(self, answers: Dict[str, Dict[str, Any]]
                                  ) -> None:
        """The melt ratio last judged for the profile the job starts with
        (the first tool that has one), into the job's history entry."""
        for extruder, answer in answers.items():
            found = answer.get("evidence")
            profile = found.get("profile") if isinstance(found, dict) else None
            if not isinstance(profile, str) or not profile:
                continue
            self.job_history.update({job_figures.MELT_RATIO.name: job_figures.
                                     melt_ratio(nh.newest_ratio(await self._estimates(
                                         extruder, profile)))})
            return

    async def _estimates(self, extruder: str, profile: str
                         ) -> List[nh.PrintEstimate]:
        hotend = self.tool_hotend(extruder)
        return self._loaded(hotend, profile,
                            await self.health.get(hotend, profile))[1]

    async def carried_ratio(self, extruder: str, profile: str) -> Optional[float]:
        """What an activation of a profile on this tool seeds its limiter's
        grip model with (nh.carried_ratio; None: the profile's line)."""
        return nh.carried_ratio(await self._estimates(extruder, profile))

    async def _record_tool(self, job_id: str, extruder: str, before: Any,
                           after: Any, model_ratio: Any = None) -> None:
        """One tool's part of a job; a tool whose evidence does not read is
        one line in the log, the other tools are judged all the same."""
        try:
            if not (isinstance(after, dict) and (before is None or isinstance(
                    before, dict)) and nh.printed_between(before, after)):
                return   # a tool that did not print this job
            await self.record(job_id, before, after, self.tool_hotend(extruder),
                              model_ratio)
        except FlowloopError as e:
            logging.info(f"flowloop: nozzle health of job {job_id}, {extruder}: "
                         f"{one_line(e)}")
        except Exception as e:  # never take Moonraker's job handling down
            logging.exception(f"flowloop: nozzle health of job {job_id}, "
                              f"{extruder} failed: {one_line(e)}")

    async def record(self, job_id: str, start: Optional[Dict[str, Any]],
                     end: Optional[Dict[str, Any]],
                     hotend: Optional[str] = None,
                     model_ratio: Any = None) -> Dict[str, Any]:
        """A job's estimate from klippy's snapshots, with what the limiter's
        model believed at its end (FlowloopError: evidence that does not
        read; a ratio that is not a finite number is left out)."""
        return await self.record_evidence(
            job_id, None if start is None else nh.PrintEvidence.from_dict(start),
            None if end is None else nh.PrintEvidence.from_dict(end), hotend,
            model_ratio)

    async def record_evidence(self, job_id: str,
                              start: Optional[nh.PrintEvidence],
                              end: Optional[nh.PrintEvidence],
                              hotend: Optional[str] = None,
                              model_ratio: Any = None) -> Dict[str, Any]:
        """A job's estimate stored under its hotend and profile (the job's
        earlier record replaced); the verdict."""
        hotend = hotend or self.hotend
        found = nh.estimate(nh.evidence_between(start, end), model_ratio)
        entry = {"job_id": job_id, "time": time.time(), **found.to_dict()}
        if not found.profile:
            logging.info(f"flowloop: nozzle health of job {job_id}: {found.reason}")
            return {"entry": entry, "verdict": None}
        judged: List[nh.Verdict] = []

        def change(stored: Optional[Dict[str, Any]]) -> Dict[str, Any]:
            prints, _ = self._loaded(hotend, found.profile, stored)
            prints = nh.with_print(prints, entry)
            judged.append(nh.judge([nh.PrintEstimate.from_dict(p)
                                    for p in prints]))
            return nh.history_record(hotend, found.profile, prints, judged[-1])
        before, stored = await self.health.update(hotend, found.profile, change)
        verdict = judged[-1]
        warning = nh.health_warning(hotend, found.profile, stored["prints"],
                                    verdict, nh.was_warning(before))
        if warning is not None:
            self._warn(stored, warning)
        return {"entry": entry, "verdict": verdict.__dict__}

    @staticmethod
    def _loaded(hotend: str, profile: str, stored: Any
                ) -> Tuple[List[Dict[str, Any]], List[nh.PrintEstimate]]:
        """The stored prints that read and their estimates; the rest skipped
        with one line in the log (dropped at the history's next write)."""
        if stored is None:
            return [], []
        prints, estimates, problems = nh.load_history(stored)
        if problems:
            logging.info(f"flowloop: nozzle health of hotend {quoted(hotend)}, "
                         f"profile {quoted(profile)}: {len(problems)} "
                         f"stored print(s) skipped: "
                         f"{one_line('; '.join(problems))[:500]}")
        return prints, estimates

    def _warn(self, stored: Dict[str, Any], warning: nh.HealthWarning) -> None:
        self.server.send_event("flowloop:nozzle_health",
                               {**stored, "title": warning.title,
                                "text": warning.text, "url": warning.url})
        self.server.send_event("server:gcode_response",
                               f"// {warning.title}: {warning.text}")
        if warning.announce:
            announcements = self.server.lookup_component("announcements", None)
            if announcements is not None:
                announcements.add_internal_announcement(
                    warning.title, warning.text, warning.url, "high",
                    ANNOUNCEMENT_FEED)

    # --- endpoints -------------------------------------------------------------
    async def _handle(self, web_request: WebRequest) -> Dict[str, Any]:
        req_type = web_request.get_request_type()
        if req_type == RequestType.POST:
            # a print's evidence from elsewhere (a replayed or offline print)
            try:
                posted = nh.post_request(web_request.get_args(),
                                         self.store.profiles)
                return await self.record_evidence(posted.job_id, posted.start,
                                                  posted.end)
            except FlowloopError as e:
                raise args.refusal(e) from None
        if req_type == RequestType.DELETE:
            return await self._delete(*self._history_args(web_request))
        return {"hotend": self.hotend, "histories": await self.health.histories()}

    def _history_args(self, web_request: WebRequest) -> Tuple[str, str]:
        """(hotend, profile) of a request naming one history."""
        given = web_request.get_args()
        name = args.text(given, "profile", "profile name")
        hotend = args.text(given, "hotend", "hotend") if "hotend" in given \
            else self.hotend
        return hotend, name

    async def _delete(self, hotend: str, name: str) -> Dict[str, Any]:
        stored = await self.health.remove(hotend, name)
        if stored is None:
            raise args.refusal(f"no nozzle health for profile {quoted(name)}"
                               f" on hotend {quoted(hotend)}", 404)
        prints = stored.get("prints") if isinstance(stored, dict) else None
        logging.info(f"flowloop: nozzle health of hotend {quoted(hotend)}, "
                     f"profile {quoted(name)} deleted")
        return {"hotend": hotend, "profile": name, "action": "deleted",
                "prints": len(prints) if isinstance(prints, list) else 0}

    async def _handle_plot(self, web_request: WebRequest) -> bytes:
        hotend, name = self._history_args(web_request)
        stored = await self.health.get(hotend, name)
        if stored is not None:
            _, prints = self._loaded(hotend, name, stored)
            return svg(prints, f"hotend {hotend}, profile {name}").encode()
        raise args.refusal(f"no nozzle health for profile {quoted(name)}", 404)
