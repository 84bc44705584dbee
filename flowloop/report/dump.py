"""A flow report's data as a small JSON file, and back.

The file is what Moonraker stores per job and what `flowloop report` renders
offline. It carries its format and version; a file this version cannot read
is refused with one line saying what it is and what was expected.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence

from .. import files
from ..errors import FlowloopError
from .recorder import (
    CHANNELS,
    Bins,
    Event,
    Job,
    Layer,
    Recorder,
    Sample,
    Span,
    Spans,
)

FORMAT = "flowloop-flow-report"
VERSION = 1
# A stored report's name: its job's id in Moonraker's history (hex digits)
JOB_ID = re.compile(r"[0-9A-F]{1,16}")
# A job id as Moonraker's history gives them: its number as f"{n:06X}"
MOONRAKER_JOB_ID = re.compile(r"[0-9A-F]{6,16}")
# A report's job and the history's job of the same id started together
# (the same job), not within this (the id reused after the history was cleared)
SAME_START_S = 1.0
# totals kept as they are (everything else is rebuilt)
_COUNTS = ("samples", "sensor_samples", "faulted_samples", "planned_samples",
           "events_dropped")


def check_job_id(value: Any) -> str:
    """A job id as Moonraker's history names jobs (6 to 16 hex digits;
    lower-case ASCII letters read as upper-case, no other character folded
    into one). FlowloopError (one line) for anything else."""
    if isinstance(value, str) and value.isascii() \
            and MOONRAKER_JOB_ID.fullmatch(value.upper()):
        return value.upper()
    shown = json.dumps(value[:40]) if isinstance(value, str) \
        else type(value).__name__
    raise FlowloopError(f"job id {shown} is not a job of Moonraker's history "
                        f"(6 to 16 hex digits, e.g. 00002A)")


def to_dict(rec: Recorder) -> Dict[str, Any]:
    return {
        "format": FORMAT,
        "version": VERSION,
        "job": dataclasses.asdict(rec.job),
        "filament_diameter_mm": rec.filament_diameter_mm,
        "grip_noise": rec.grip_noise,
        **{name: getattr(rec, name) for name in _COUNTS},
        "last_time_s": None if rec.last is None else round(rec.last.time_s, 4),
        "commanded_mm": round(rec.commanded_mm, 4),
        "under_mm": round(rec.under_mm, 4),
        "bins": {"width_s": rec.bins.width_s, "max_bins": rec.bins.max_bins,
                 "channels": list(CHANNELS), "rows": _rounded_rows(rec.bins)},
        "layers": [_rounded(dataclasses.asdict(layer))
                   for _, layer in sorted(rec.layers.items())],
        "slowdowns": [_rounded(dataclasses.asdict(s)) for s in rec.slowdowns.items],
        "faults": [_rounded(dataclasses.asdict(s)) for s in rec.faults.items],
        "profiles": [_rounded(dataclasses.asdict(s)) for s in rec.profiles.items],
        "events": [_rounded(dataclasses.asdict(e)) for e in rec.events],
    }


def dumps(rec: Recorder) -> str:
    return json.dumps(to_dict(rec), separators=(",", ":"), allow_nan=False)


def _rounded(d: Dict[str, Any]) -> Dict[str, Any]:
    return {k: round(v, 4) if isinstance(v, float) else v for k, v in d.items()}


def _rounded_rows(bins: Bins) -> List[Any]:
    return [None if row is None else
            [None if cell is None else [int(cell[0])] + [round(v, 4) for v in cell[1:]]
             for cell in row]
            for row in bins.rows]


def from_dict(data: Any, source: str = "the dump") -> Recorder:
    """A Recorder as it was dumped (FlowloopError: not one this version reads)."""
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise FlowloopError(f"{source} is not a flowloop flow report dump (no "
                            f"\"format\": \"{FORMAT}\")")
    version = data.get("version")
    if version != VERSION:
        raise FlowloopError(f"{source} is a flow report dump of version "
                            f"{version!r}; this flowloop reads version {VERSION}")
    try:
        return _recorder(data)
    except (KeyError, TypeError, ValueError, IndexError) as e:
        raise FlowloopError(f"{source} is a damaged flow report dump "
                            f"({type(e).__name__}: {e})") from None


def _recorder(data: Dict[str, Any]) -> Recorder:
    bins_data = data["bins"]
    if list(bins_data["channels"]) != list(CHANNELS):
        raise ValueError(f"channels {bins_data['channels']} are not {list(CHANNELS)}")
    bins = Bins(int(bins_data["max_bins"]), float(bins_data["width_s"]))
    bins.rows = [None if row is None else
                 [None if cell is None else [float(v) for v in cell] for cell in row]
                 for row in bins_data["rows"]]
    rec = Recorder(job=Job(**data["job"]),
                   filament_diameter_mm=float(data["filament_diameter_mm"]),
                   grip_noise=float(data["grip_noise"]), bins=bins,
                   commanded_mm=float(data["commanded_mm"]),
                   under_mm=float(data["under_mm"]))
    for name in _COUNTS:
        setattr(rec, name, int(data[name]))
    rec.layers = {int(d["layer"]): Layer(**d) for d in data["layers"]}
    for name in ("slowdowns", "faults", "profiles"):
        spans = Spans()
        spans.items = [Span(**d) for d in data[name]]
        setattr(rec, name, spans)
    rec.events = [Event(**d) for d in data["events"]]
    if data["last_time_s"] is not None:
        rec.last = Sample(float(data["last_time_s"]), print_state="")
    return rec


def loads(text: str, source: str = "the dump") -> Recorder:
    try:
        data = json.loads(text)
    except ValueError as e:
        raise FlowloopError(f"{source} is not JSON ({e})") from None
    return from_dict(data, source)


def load(path: Path) -> Recorder:
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise FlowloopError(f"cannot read {path}: {e}") from None
    return loads(text, str(path))


def save(path: Path, text: str) -> None:
    """Write a dump or report whole or not at all (OSError as raised: a full
    disk leaves the file that was there, and no partial one)."""
    files.write_text_atomically(path, text)


@dataclasses.dataclass(frozen=True)
class StoredReport:
    """A stored dump as pruning sees it: its job and when that job ended."""

    path: Path
    job_id: str
    started_at: Optional[float]   # None: a dump that does not say
    ended_at: float               # the job's start plus its length, else the
                                  # file's time (written as the job ended)


def _stored_report(path: Path, text: Optional[str] = None) -> StoredReport:
    """The report stored at path (text: its dump, when not written yet)."""
    started = ended = None
    try:
        if text is None:
            text = path.read_text(encoding="utf-8")
        job = json.loads(text).get("job") or {}
        started, length = job.get("started_at"), job.get("end_s")
        started = float(started) if started is not None else None
        if started is not None and length is not None:
            ended = started + float(length)
    except (OSError, ValueError, TypeError, AttributeError, RecursionError):
        pass    # listed with its problem; its file's time orders it
    if ended is None or not math.isfinite(ended):
        try:
            ended = path.stat().st_mtime
        except OSError:
            ended = time.time() if text is not None else 0.0
    return StoredReport(path, path.stem, started, ended)


def stored_reports(folder: Path) -> List[StoredReport]:
    """The dumps stored in a folder (JOB.json), the job that ended last
    first (Moonraker reuses job ids once its history is cleared: the number
    says nothing of the order)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    found = [_stored_report(p) for p in folder.glob("*.json")
             if JOB_ID.fullmatch(p.stem)]
    return sorted(found, key=lambda r: (r.ended_at, r.job_id), reverse=True)


def stored(folder: Path) -> List[Path]:
    """The dumps stored in a folder, the job that ended last first."""
    return [r.path for r in stored_reports(folder)]


def to_remove(reports: Sequence[StoredReport], keep: int,
              history: Optional[Mapping[str, Optional[float]]] = None
              ) -> List[str]:
    """The job ids whose reports go: with `history` (job id -> its start
    time, for each of these ids Moonraker's history holds), every report
    whose job is no longer there (the id absent, or reused by a job that
    started at another time), then all but the `keep` that ended last."""
    def in_history(r: StoredReport) -> bool:
        if history is None:
            return True
        if r.job_id not in history:
            return False
        start = history[r.job_id]
        return start is None or r.started_at is None \
            or abs(start - r.started_at) <= SAME_START_S
    kept = [r for r in sorted(reports, key=lambda r: (r.ended_at, r.job_id),
                              reverse=True) if in_history(r)][:keep]
    kept_ids = {r.job_id for r in kept}
    return [r.job_id for r in reports if r.job_id not in kept_ids]


def prune(folder: Path, keep: int,
          history: Optional[Mapping[str, Optional[float]]] = None,
          adding: Optional[StoredReport] = None) -> List[str]:
    """Remove the dumps (and their .html) that to_remove names; the job ids
    removed. adding: a report about to be stored, counted as stored already,
    so that the old ones go before it is written and a listing never shows
    more than `keep` (its own id is among those removed when it would go)."""
    reports = stored_reports(folder)
    if adding is not None:   # a stored report of its id (reused) is replaced
        reports = [r for r in reports if r.job_id != adding.job_id]
    removed = to_remove(reports + ([adding] if adding else []), keep, history)
    for report in reports:
        if report.job_id not in removed:
            continue
        for suffix in (".json", ".html"):
            try:
                report.path.with_suffix(suffix).unlink()
            except FileNotFoundError:
                pass
    return removed


def store(folder: Path, rec: Recorder, keep: int,
          history: Optional[Mapping[str, Optional[float]]] = None,
          html: Optional[Callable[[Recorder], str]] = None) -> bool:
    """Store a finished job's dump (and its html(rec) page) in folder as
    JOB.json, the reports to_remove names pruned first: a listing at any
    moment shows at most `keep` reports, the new one among them once it is
    there. False when the new report itself would be pruned (its job not in
    `history`): nothing is written then."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    job_id = rec.job.job_id or "unknown"
    text = dumps(rec)
    new = _stored_report(folder / f"{job_id}.json", text)
    if job_id in prune(folder, keep, history, adding=new):
        return False
    save(folder / f"{job_id}.json", text)
    if html is not None:
        save(folder / f"{job_id}.html", html(rec))
    return True


def summaries(folder: Path) -> List[Dict[str, Optional[Any]]]:
    """The summary of each report stored in folder, the job that ended last
    first; a dump that cannot be read as its job id and the problem. A dump
    removed between the listing and its reading (pruned as another job
    ended) is left out, as a listing a moment later leaves it out: it was
    listed as a problem of job_id only, while its file was fine."""
    out: List[Dict[str, Optional[Any]]] = []
    for path in stored(folder):
        try:
            out.append(summary(load(path)))
        except FlowloopError as e:
            if path.exists():
                out.append({"job_id": path.stem, "problem": str(e)})
    return out


def summary(rec: Recorder) -> Dict[str, Optional[Any]]:
    """The few figures a list of reports shows per job."""
    return {
        "job_id": rec.job.job_id,
        "filename": rec.job.filename,
        "state": rec.job.state,
        "started_at": rec.job.started_at,
        "duration_s": round(rec.duration_s(), 1),
        "under_extruded_mm": round(rec.under_mm, 2),
        "slowed_s": round(sum(rec.slowdown_by_reason().values()), 1),
        "lost_s": round(rec.lost_s(), 1),
        "lacks": rec.lacks(),
    }
