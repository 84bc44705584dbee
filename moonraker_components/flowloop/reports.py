# flowloop component: a flow report for every job of Moonraker's history.
#
# While a job runs, the klippy objects flowloop publishes are read from
# Moonraker's own subscription and fed to the core's recorder every
# SAMPLE_PERIOD_S; when the job ends its dump and its HTML report are
# written under the data path (flowloop/reports/JOB.json, JOB.html): the
# number_of_reports_to_keep whose jobs ended last are kept, of the jobs still
# in Moonraker's history (it reuses ids once cleared: a report whose job is
# gone, or whose id now names another job, goes). Everything that decides
# (what a sample is, what the report says, which reports go) is in
# flowloop.report. The job's figures (under-extruded filament, lowest grip,
# the limiter's cost, peak flow) go to Moonraker's job history as numbers
# (job_history.py) as each sample is taken; the report itself is served at
# /server/flowloop/report?job_id=JOB, a path that resolves from a UI's
# origin too (nginx passes /server/ to Moonraker).
#
# This file may be distributed under the terms of the GNU GPLv3 license.

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Dict, Optional

from flowloop.control.tools import tool_objects
from flowloop.errors import FlowloopError
from flowloop.material.profile import is_extruder_name
from flowloop.report import dump, job_figures, render
from flowloop.report.recorder import (
    DEFAULT_FILAMENT_DIAMETER_MM,
    SAMPLE_PERIOD_S,
    Job,
    Recorder,
    Tools,
    sample_from_status,
    status_objects,
)

from ...common import RequestType, TransportType, WebRequest
from . import args
from .errors import one_line, quoted
from .job_history import JobHistory

if TYPE_CHECKING:
    from ...server import Server

DEFAULT_REPORTS_TO_KEEP = 10
REPORTS_FOLDER = ("flowloop", "reports")


class Reports:
    def __init__(self, server: Server, keep: int,
                 job_history: JobHistory) -> None:
        self.server = server
        self.job_history = job_history
        self.keep = keep
        self.eventloop = server.get_event_loop()
        self.klippy_apis = server.lookup_component("klippy_apis")
        self.folder = Path(server.get_app_args()["data_path"]).joinpath(
            *REPORTS_FOLDER)
        self.status: Dict[str, Dict[str, Any]] = {}
        self.sensor_name: Optional[str] = None
        self.tools: Tools = {}      # extruder -> its sensor, limiter, autotemp
        self.filament_diameter_mm = DEFAULT_FILAMENT_DIAMETER_MM
        self.recorder: Optional[Recorder] = None
        self._started = 0.0
        self._sampler: Optional[asyncio.Task] = None
        server.register_event_handler("server:klippy_ready", self._on_klippy_ready)
        server.register_event_handler("history:history_changed", self._on_history)
        server.register_endpoint("/server/flowloop/reports", RequestType.GET,
                                 self._handle_list)
        server.register_endpoint("/server/flowloop/report", RequestType.GET,
                                 self._handle_report, transports=TransportType.HTTP,
                                 wrap_result=False,
                                 content_type="text/html; charset=utf-8")

    # --- klippy's objects --------------------------------------------------------
    async def _on_klippy_ready(self) -> None:
        try:
            objects = await self.klippy_apis.get_object_list(default=[])
            answer = await self.klippy_apis.query_objects(
                {"configfile": ["settings"]}, default={})
            settings = answer.get("configfile", {}).get("settings", {})
            # every tool's objects: the report follows the tool that prints
            extruders = sorted(filter(is_extruder_name, objects))
            self.tools = {e: tool_objects(objects, settings, e)
                          for e in extruders}
            sensors = [own["sensor"].split(" ", 1)[1]
                       for own in self.tools.values() if own["sensor"]]
            self.sensor_name = ", ".join(sensors) or None
            self.filament_diameter_mm = float(settings.get("extruder", {}).get(
                "filament_diameter", DEFAULT_FILAMENT_DIAMETER_MM))
            status = await self.klippy_apis.subscribe_objects(
                status_objects(self.tools), self._on_status, default={})
        except self.server.error as e:
            logging.info(f"flowloop: flow reports get no klippy status: "
                         f"{one_line(e)}")
            return
        self.status = {name: dict(fields) for name, fields in status.items()}

    async def _on_status(self, data: Dict[str, Any], eventtime: float) -> None:
        for name, fields in data.items():
            self.status.setdefault(name, {}).update(fields)

    # --- jobs --------------------------------------------------------------------
    async def _on_history(self, event: Dict[str, Any]) -> None:
        job = event.get("job") or {}
        if event.get("action") == "added":
            self._start(job)
        elif event.get("action") == "finished" and self.recorder is not None \
                and self.recorder.job.job_id == job.get("job_id"):
            await self._finish(job.get("status") or "unknown")

    def _start(self, job: Dict[str, Any]) -> None:
        self._stop_sampler()
        self.recorder = Recorder(
            job=Job(job_id=job.get("job_id"), filename=job.get("filename"),
                    started_at=job.get("start_time"), sensor_name=self.sensor_name),
            filament_diameter_mm=self.filament_diameter_mm)
        self._started = time.monotonic()
        self._sampler = self.eventloop.create_task(self._sample_loop())

    async def _sample_loop(self) -> None:
        try:
            while self.recorder is not None:
                self.recorder.sample(sample_from_status(
                    time.monotonic() - self._started, self.status, self.tools))
                self.job_history.update(job_figures.recorded(self.recorder))
                await asyncio.sleep(SAMPLE_PERIOD_S)
        except (TypeError, ValueError, AttributeError, IndexError) as e:
            # a status of a shape flowloop does not know: one line, the job
            # goes on (its report has no samples after this point)
            logging.error(f"flowloop: the flow report stopped sampling: "
                          f"{one_line(e)}")

    def _stop_sampler(self) -> None:
        if self._sampler is not None:
            self._sampler.cancel()
            self._sampler = None

    async def _finish(self, state: str) -> None:
        self._stop_sampler()
        rec, self.recorder = self.recorder, None
        if rec is None:
            return
        rec.finish(state, time.monotonic() - self._started)
        try:
            # the history first, then the old reports pruned and the new one
            # written in one go: a listing never shows more than keep
            history = await self._history_starts(rec.job.job_id)
            await self.eventloop.run_in_thread(
                dump.store, self.folder, rec, self.keep, history, render.html)
        except OSError as e:  # a full disk: the job's history is Moonraker's, kept
            logging.error(f"flowloop: the flow report of job {rec.job.job_id} was "
                          f"not stored: {one_line(e)}")
        except Exception as e:  # never take Moonraker's job handling down with it
            logging.exception(f"flowloop: the flow report of job {rec.job.job_id} "
                              f"failed: {one_line(e)}")

    async def _history_starts(self, new_job_id: Optional[str]
                              ) -> Optional[Dict[str, Optional[float]]]:
        """Job id -> start time, for each stored report's job and the new
        one that Moonraker's history holds (None: no history to ask)."""
        history = self.server.lookup_component("history", None)
        if history is None:
            return None
        reports = await self.eventloop.run_in_thread(
            dump.stored_reports, self.folder)
        starts: Dict[str, Optional[float]] = {}
        for job_id in {r.job_id for r in reports} | ({new_job_id} - {None}):
            job = await history.get_job(job_id)
            if job is not None:
                starts[job_id] = job.get("start_time")
        return starts

    # --- endpoints ---------------------------------------------------------------
    async def _handle_list(self, web_request: WebRequest) -> Dict[str, Any]:
        reports = await self.eventloop.run_in_thread(dump.summaries, self.folder)
        for entry in reports:
            if "problem" in entry:  # a dump that cannot be read: its one line
                entry["problem"] = one_line(entry["problem"])
        recording = None if self.recorder is None else self.recorder.job.job_id
        return {"reports": reports, "recording": recording,
                "number_of_reports_to_keep": self.keep}

    async def _handle_report(self, web_request: WebRequest) -> bytes:
        try:
            job_id = dump.check_job_id(
                args.text(web_request.get_args(), "job_id", "job id"))
        except FlowloopError as e:
            raise args.refusal(e) from None
        rec = self.recorder
        if rec is not None and rec.job.job_id == job_id:  # the print running now
            # a copy taken here (the sampler goes on changing the recorder),
            # rendered in a thread
            copy = dump.to_dict(rec)
            return (await self.eventloop.run_in_thread(
                lambda: render.html(dump.from_dict(copy)))).encode()
        path = self.folder / f"{job_id}.html"
        try:
            return await self.eventloop.run_in_thread(path.read_bytes)
        except FileNotFoundError:
            pass
        # a job the history holds: a page that says so where its report would
        # be (Moonraker writes every refusal as JSON and gives a component no
        # request headers, so a browser cannot be told from a client); an id
        # that names no job: a refusal
        history = self.server.lookup_component("history", None)
        job = None if history is None else await history.get_job(job_id)
        if job is None:
            raise args.refusal(f"no flow report for job {quoted(job_id)}",
                               404) from None
        return render.not_kept_html(job_id, job.get("filename"), self.keep).encode()
