"""The offline bake: autotemp's targets written into the file as plain M104.

`flowloop annotate IN -o OUT --bake PROFILE.json` plans the file and its
AUTOTEMP_FLOW announcements exactly as `annotate` does, then replays them
through the same controller `[autotemp]` runs (flowloop.control.autotemp):
each announcement reaches it at its place in print time, and the target is
sampled as a printer would (every GRID_S). Instead of the announcements,
`M104 S<target>` commands go into the file:

- one at the first move line every BAKE_STEP_S of print time, when the
  target changes;
- Klipper runs a command up to READAHEAD_S before the move after it, and the
  next M104 replaces it: each carries the highest target over that whole
  span, rounded up to a whole degree, so the heater is never set lower than
  [autotemp] would set it;
- the slicer's own M104 after the first baked one is commented out
  (`M104 S0`, heater off, is kept); M109 stays and waits;
- the print starts where the plan does (flowloop.gcode.start): the start
  G-code's last heat-and-wait before the first extrusion is raised to the
  planned nozzle temperature there, kept if it is hotter, or an M109 added
  (after a start macro, whose temperature the file does not show); no baked
  M104 goes before that wait, which would override it;
- with the printer's heater range known (flowloop.control.heater_range: [extruder]
  min_temp/max_temp from --printer-cfg), every target is a whole degree
  within it: the plan is capped at max_temp (below the profile's maximum
  where that is lower), and the file's own M104/M109 and the start macro's
  temperature outside the range are brought within it, so Klipper refuses
  none of them.

The timeline (demanded flow, targets, the modelled nozzle and the melt
capacity there) is kept for `--plot` (timeline_svg).
"""

from __future__ import annotations

import codecs
import contextlib
import math
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import BinaryIO, List, NamedTuple, Optional, Tuple

import numpy as np

from .. import files
from ..control.autotemp import DEFAULT_PARAMS, GRID_S, Autotemp, flat_line_note
from ..control.hotend import HotendModel, HotendParams
from ..errors import FlowloopError
from ..material.profile import Profile
from .annotate import (
    COMMAND,
    FORMAT_VERSION,
    HEADER_BYTES,
    MAX_LEAD_S,
    READAHEAD_S,
    AnnotateSettings,
    Annotator,
    feed,
    is_annotated,
    newline_of,
    quantise_flow,
)
from .bulk_planner import Segments, planned_ahead
from .heater import HeaterRange, bake_note, cap_line
from .melt import Cells
from .reference_planner import PrinterLimits
from .start import LineFix, StartFix, StartHeat, find_start_heat, heat_at, start_fix

BAKE_STEP_S = 0.5
# Print time without extrusion after the last extruding move worth a note
# (an end G-code's moves take seconds).
TRAVEL_TAIL_S = 30.0
_ANNOUNCEMENT = re.compile(
    COMMAND + r" FLOW=(?P<flow>[0-9.]+) LEAD=(?P<lead>[0-9.]+)"
    r" DURATION=(?P<duration>[0-9.]+)$")
_M104 = re.compile(rb"^\s*M104(\s|$)", re.IGNORECASE)
_S_ZERO = re.compile(rb"\sS0*(\.0*)?(\s|;|$)", re.IGNORECASE)


@dataclass
class Timeline:
    """What the bake planned, on the GRID_S grid from time 0."""
    demand_mm3_s: List[float] = field(default_factory=list)
    target_c: List[Optional[float]] = field(default_factory=list)
    nozzle_c: List[float] = field(default_factory=list)
    capacity_mm3_s: List[float] = field(default_factory=list)


@dataclass(frozen=True)
class BakeResult:
    commands: int            # M104 written
    overridden: int          # the slicer's M104 commented out
    min_target_c: Optional[float]
    max_target_c: Optional[float]
    capped_windows: int      # windows needing more than the limits allow
    peak_flow_mm3_s: float
    print_time_s: float
    under_capacity_s: float  # extruding time the modelled nozzle melts too little
    start: Optional[StartFix] = None  # what was done so the print starts on plan
    heater: Optional[HeaterRange] = None  # the printer's range, where known
    cap_c: float = 0.0       # the plan's highest target: the lower of the
    # profile's max_temp_c and the heater's max_temp
    capped_by_heater: bool = False   # the heater's max_temp is that cap
    brought_within: int = 0  # the file's own M104/M109 outside the heater's range
    flow_windows: int = 0    # announced windows with flow
    last_extrusion_s: Optional[float] = None  # print time the last extrusion ends
    flat_line: Optional[str] = None  # the profile's line barely rises (a note)
    behind_s: float = 0.0    # print time the modelled nozzle was behind the plan
    longest_rise_s: float = 0.0  # the plan's rise from min to max temperature
    lead_s: float = 0.0      # how far ahead the windows were announced

    @property
    def lead_needed_s(self) -> float:
        """The lead that announces a window needing max_temp in time for the
        longest rise (whole 10 s, within annotate's bounds)."""
        if not math.isfinite(self.longest_rise_s):
            return MAX_LEAD_S
        return min(MAX_LEAD_S, max(
            self.lead_s, 10.0 * math.ceil((self.longest_rise_s + READAHEAD_S) / 10.0)))

    @property
    def travel_tail_s(self) -> float:
        """Print time after the last extrusion ends, where it is more than
        TRAVEL_TAIL_S (0 otherwise)."""
        if self.last_extrusion_s is None:
            return 0.0
        tail = self.print_time_s - self.last_extrusion_s
        return tail if tail > TRAVEL_TAIL_S else 0.0


class _Recorder(Annotator):
    """The annotator, keeping its commands (offset, print time, line)."""

    def __init__(self, settings: AnnotateSettings, newline: bytes):
        super().__init__(settings, _Empty(), _Empty(), newline)
        self.commands: List[Tuple[int, float, str]] = []
        self.moves: List[Tuple[float, int]] = []       # (print time, offset)
        self.demand: List[float] = []                   # peak per GRID_S
        self.first_extrusion: Optional[Tuple[float, int]] = None  # (time, offset)
        self.last_extrusion_s: Optional[float] = None   # when the last ends

    def emit(self, offset: int, time_s: float, line: str) -> None:
        self.commands.append((offset, time_s, line))

    def lines(self, batch: Segments) -> None:
        new = np.flatnonzero(np.concatenate((
            [not self.moves or self.moves[-1][1] != batch.offset[0]],
            batch.offset[1:] != batch.offset[:-1])))
        self.moves.extend(zip(batch.start_s[new].tolist(),
                              batch.offset[new].tolist()))
        flowing = np.flatnonzero(batch.flow_mm3_s > 0.0)
        if flowing.size:
            if self.first_extrusion is None:
                k = int(flowing[0])
                self.first_extrusion = (float(batch.start_s[k]),
                                        int(batch.offset[k]))
            k = int(flowing[-1])
            self.last_extrusion_s = float(batch.start_s[k] + batch.duration_s[k])
        super().lines(batch)

    def cells(self, cells: Cells) -> None:
        """The melt flow's peak per GRID_S, as announced (cells of
        flowloop.gcode.melt)."""
        if len(cells):
            first = np.floor(cells.start_s / GRID_S).astype(np.int64)
            last = np.floor(np.append(cells.start_s[1:], cells.end_s) / GRID_S
                            ).astype(np.int64)
            top = int(last[-1])
            if len(self.demand) <= top:
                self.demand.extend([0.0] * (top + 1 - len(self.demand)))
            demand = np.asarray(self.demand)
            np.maximum.at(demand, first, cells.flow_mm3_s)
            np.maximum.at(demand, last, cells.flow_mm3_s)
            self.demand = demand.tolist()
        super().cells(cells)


class _Empty:
    def read(self, size=-1):
        return b""

    def write(self, data):
        return len(data)


def parse_announcement(line: str) -> Tuple[float, float, float]:
    """(FLOW, LEAD, DURATION) of one announcement line as annotate writes it
    (COMMAND FLOW= LEAD= DURATION=); FlowloopError for any other line."""
    m = _ANNOUNCEMENT.match(line)
    if m is None:
        raise FlowloopError(f"not an announcement: {line!r}")
    return float(m["flow"]), float(m["lead"]), float(m["duration"])


def replay(commands: List[Tuple[int, float, str]], end_s: float,
           controller: Autotemp, start: Optional[Tuple[float, float]] = None
           ) -> List[Optional[float]]:
    """The target [autotemp] sets at each GRID_S of print time, each
    announcement reaching it at its place (in print time). start: (print
    time, temperature) where the start G-code's wait leaves the nozzle, as
    the printer's first flush tells [autotemp] (Autotemp.on_flush: the
    heater's target); without it the controller's model starts at the
    profile's minimum, and a file that starts hot is pushed as if cold."""
    targets: List[Optional[float]] = []
    if start is not None and controller.active:
        controller.plan.start_at(*start)
    i = 0
    for k in range(math.ceil(end_s / GRID_S) + 1):
        t = k * GRID_S
        while i < len(commands) and commands[i][1] <= t:
            controller.announce(commands[i][1],
                                *parse_announcement(commands[i][2]))
            i += 1
        targets.append(controller.target_at(t, GRID_S))
    return targets


class Placement(NamedTuple):
    time_s: float    # print time of the move line the M104 goes before
    offset: int      # that line's byte offset
    target_c: int    # whole degrees


def bake_schedule(commands: List[Tuple[int, float, str]],
                  moves: List[Tuple[float, int]], controller: Autotemp,
                  from_offset: int = 0, heater: Optional[HeaterRange] = None,
                  start: Optional[Tuple[float, float]] = None
                  ) -> List[Placement]:
    """The M104 to write, at move lines from byte from_offset on, one every
    BAKE_STEP_S of print time where the target changes. Klipper runs an
    M104 up to READAHEAD_S before the move after it, and it holds until the
    next one runs: each is the controller's target set READAHEAD_S early and
    held until the next one's move, so the nozzle is on the plan whenever
    in that span it runs, rounded up to a whole degree (within the heater's
    range, if known); the controller's model is told the value written.
    start: (print time, temperature) where the start G-code's wait leaves
    the nozzle, if known."""
    slots: List[Tuple[float, int]] = []
    for time_s, offset in moves:
        if offset < from_offset:
            continue
        if not slots or time_s >= slots[-1][0] + BAKE_STEP_S:
            slots.append((time_s, offset))
    out: List[Placement] = []
    last = None
    i = 0
    started = start is None
    for k, (time_s, offset) in enumerate(slots):
        until = slots[k + 1][0] if k + 1 < len(slots) else time_s + BAKE_STEP_S
        set_s = max(0.0, time_s - READAHEAD_S)
        while i < len(commands) and commands[i][1] <= set_s:
            controller.announce(commands[i][1], *parse_announcement(commands[i][2]))
            i += 1
        if not started and controller.active:
            # the wait's temperature, held until the first baked M104 can run
            controller.plan.start_at(min(set_s, start[0]), start[1])
            started = True
        target = controller.target_at(set_s, until - set_s)
        if target is None:
            continue
        value = _whole(target, heater)
        controller.applied(set_s, value)
        if value != last:
            out.append(Placement(time_s, offset, value))
            last = value
    return out


def schedule_targets(placements: List[Placement], end_s: float,
                     early_s: float = READAHEAD_S) -> List[Optional[float]]:
    """The baked targets on the GRID_S grid, each M104 acting early_s before
    its move (None before the first)."""
    targets: List[Optional[float]] = [None] * (math.ceil(end_s / GRID_S) + 1)
    for p in placements:
        k = max(0, math.ceil((p.time_s - early_s) / GRID_S - 1e-9))
        if k < len(targets):
            targets[k] = float(p.target_c)
    held = None
    for k, value in enumerate(targets):
        held = value if value is not None else held
        targets[k] = held
    return targets


def _whole(temp_c: float, heater: Optional[HeaterRange]) -> int:
    """A target as written: whole degrees, rounded up, within the heater's
    range where known."""
    return heater.whole(temp_c) if heater is not None \
        else math.ceil(temp_c - 1e-6)


def _simulate(timeline: Timeline, targets: List[Optional[float]],
              controller: Autotemp, start_c: float, from_s: float = 0.0) -> float:
    """The modelled nozzle under the targets, held at start_c (the start
    G-code's wait) until from_s; returns the extruding time during which it
    melts less than is demanded."""
    plan = controller.plan
    model = HotendModel(controller.params, temp_c=start_c, target_c=start_c)
    held = start_c
    short_s = 0.0
    for k, target in enumerate(targets):
        if target is not None and k * GRID_S >= from_s - 1e-9:
            held = target
        model.set_target(k * GRID_S, held)
        demand = timeline.demand_mm3_s[k] if k < len(timeline.demand_mm3_s) else 0.0
        temp = model.advance((k + 1) * GRID_S, demand)
        capacity = plan.line.flow_mm3_s(temp)
        timeline.nozzle_c.append(temp)
        timeline.capacity_mm3_s.append(capacity)
        if demand > capacity + 1e-9:
            short_s += GRID_S
    return short_s


def plan_announcements(src: Path, limits: PrinterLimits,
                       settings: AnnotateSettings, newline: bytes = b"\n"
                       ) -> _Recorder:
    """The file planned and annotated in memory: `.commands` (offset, print
    time, AUTOTEMP_FLOW line), `.moves`, `.demand` (peak melt flow
    per GRID_S, as announced),
    `.end_s`."""
    rec = _Recorder(settings, newline)
    try:
        # the planner ahead in a process or a thread (flowloop.gcode.ahead),
        # stopped when this is done, whatever happens
        with contextlib.closing(planned_ahead(src, limits)) as events:
            feed(rec, events)
    except FlowloopError as e:
        raise FlowloopError(f"{src}: {e}") from None
    return rec


def bake_file(src: Path, dst: Path, profile: Profile, working_point: float,
              params: HotendParams = DEFAULT_PARAMS,
              limits: Optional[PrinterLimits] = None,
              settings: Optional[AnnotateSettings] = None,
              heater: Optional[HeaterRange] = None
              ) -> Tuple[BakeResult, Timeline]:
    """Bake src into dst (written whole or not at all); heater: the
    printer's [extruder] min_temp..max_temp, where known."""
    limits = limits if limits is not None else PrinterLimits()
    settings = settings if settings is not None else AnnotateSettings()
    src, dst = Path(src), Path(dst)
    try:
        with open(src, "rb") as f:
            head = f.read(HEADER_BYTES)
    except OSError as e:
        raise FlowloopError(f"{src}: cannot read: {e.strerror}") from None
    if is_annotated(head):
        raise FlowloopError(f"{src}: annotated or baked already; bake the"
                            " slicer's file")
    newline = newline_of(src)
    rec = plan_announcements(src, limits, settings, newline)
    heater_max_temp_c = None if heater is None else heater.max_temp_c
    controller = Autotemp(params, heater_max_temp_c)
    controller.set_profile(profile, working_point)
    if controller.plan is None:
        raise FlowloopError(f"{profile.name}: {controller.why}")
    end_s = rec.end_s + 1.0
    fix, from_s = _start(src, rec, params, heater, profile, working_point,
                         newline)
    placements = bake_schedule(
        rec.commands, rec.moves, controller, fix.end if fix is not None else 0,
        heater, None if fix is None else (from_s, float(fix.start_c)))
    # the M104 act up to READAHEAD_S early: the modelled run is the worse
    # of the two ends
    early = schedule_targets(placements, end_s)
    late = schedule_targets(placements, end_s, 0.0)
    known = [x for x in early if x is not None]
    start_c = fix.start_c if fix is not None else (
        known[0] if known else controller.plan.limits.min_temp_c)
    demand = rec.demand + [0.0] * max(0, len(early) - len(rec.demand))
    short_s = _simulate(Timeline(demand_mm3_s=demand), late, controller,
                        start_c, from_s)
    timeline = Timeline(demand_mm3_s=demand, target_c=early)
    short_s = max(short_s, _simulate(timeline, early, controller, start_c,
                                     from_s))
    overridden = brought_within = 0

    def write(out: BinaryIO) -> None:
        nonlocal overridden, brought_within
        overridden, brought_within = _write(src, out, placements, newline,
                                            profile, working_point, params, fix,
                                            heater)
    files.replace_atomically(dst, write, src)
    cap_c = controller.plan.limits.max_temp_c
    result = BakeResult(
        commands=len(placements), overridden=overridden,
        # what the file sets, not what the plan held before the start's wait
        min_target_c=min((p.target_c for p in placements), default=None),
        max_target_c=max((p.target_c for p in placements), default=None),
        capped_windows=controller.plan.capped_windows,
        # the file's peak as its annotation announces it (annotate's summary)
        peak_flow_mm3_s=quantise_flow(rec.peak),
        print_time_s=rec.end_s, under_capacity_s=short_s, start=fix,
        heater=heater, cap_c=cap_c,
        capped_by_heater=cap_c < profile.bounds.max_temp_c,
        brought_within=brought_within,
        flow_windows=controller.plan.flow_windows,
        last_extrusion_s=rec.last_extrusion_s,
        flat_line=flat_line_note(controller.plan.line, controller.plan.limits),
        behind_s=controller.plan.behind_s,
        longest_rise_s=controller.plan.longest_rise_s(), lead_s=settings.lead_s)
    return result, timeline


def _start(src: Path, rec: _Recorder, params: HotendParams,
           heater: Optional[HeaterRange], profile: Profile,
           working_point: float, newline: bytes
           ) -> Tuple[Optional[StartFix], float]:
    """What the start G-code is made to do (None: nothing is extruded), and
    the print time from which the baked targets hold."""
    if rec.first_extrusion is None:
        return None, 0.0
    first_s, first_offset = rec.first_extrusion
    # The plan's nozzle when the first extrusion starts, as the printer knows
    # it then: the announcements up to that time, replayed afresh.
    probe = Autotemp(params, None if heater is None else heater.max_temp_c)
    probe.set_profile(profile, working_point)
    replay(rec.commands, first_s, probe)
    plan_start_c = _whole(probe.plan.nozzle_c(first_s), heater)
    with open(src, "rb") as f:
        heat = find_start_heat(f, first_offset)
    heat_fix = None
    if heater is not None and heat.temp_c is not None \
            and not heater.accepts(heat.temp_c):
        # the wait as written, brought within the range (an M109 by
        # _write's cap_line, a start macro's parameter here)
        capped = heat_at(heat, heater.whole(heat.temp_c))
        if heat.kind == "macro":
            heat_fix = _macro_fix(heat, capped, heater, newline)
        heat = capped
    fix = replace(start_fix(heat, plan_start_c, newline.decode()),
                  heat_fix=heat_fix)
    from_s = next((t for t, offset in rec.moves if offset >= fix.end), first_s)
    return fix, from_s


def _macro_fix(heat: StartHeat, capped: StartHeat, heater: HeaterRange,
               newline: bytes) -> LineFix:
    """The start macro's line with its temperature within the heater's
    range, the original in a comment, as cap_line writes an M104."""
    side = "lowered" if heat.temp_c > heater.max_temp_c else "raised"
    name = heat.text.split()[0]
    return LineFix(
        heat.offset,
        capped.text + bake_note(heat.text, heat.temp_c, heater)
        + newline.decode(),
        f"start: {name}'s {heat.param}={heat.temp_c:g} (line {heat.line_no})"
        f" is outside the printer's {heater.limit(heat.temp_c)} C"
        f" ({heater.source}): {side} to {heat.param}={capped.temp_c:g}")


def marker_line(profile: Profile, working_point: float,
                params: HotendParams) -> str:
    # It matches annotate.MARKER_REGEX: a baked file is never annotated again.
    return (f"; flowloop autotemp annotations v{FORMAT_VERSION} baked: M104 for"
            f" profile {profile.name} at working point {working_point:g},"
            f" time constant {params.time_constant_s:g} s, dead time"
            f" {params.dead_time_s:g} s")


def _write(src: Path, out: BinaryIO, placements: List[Placement],
           newline: bytes, profile: Profile, working_point: float,
           params: HotendParams, fix: Optional[StartFix] = None,
           heater: Optional[HeaterRange] = None) -> Tuple[int, int]:
    """Write the baked file; (slicer M104 commented out, the file's own
    M104/M109 brought within the heater's range)."""
    overridden = brought_within = 0
    i = 0
    first = placements[0].offset if placements else None
    with open(src, "rb") as f:
        # a UTF-8 byte-order mark is left out, as annotate leaves it out: the
        # marker is the file's first bytes
        offset = len(codecs.BOM_UTF8)
        if f.read(offset) != codecs.BOM_UTF8:
            f.seek(0)
            offset = 0
        out.write(marker_line(profile, working_point, params).encode() + newline)
        for line in f:
            if fix is not None and fix.line is not None and fix.offset == offset:
                # the start's wait, before any baked M104 at the same line
                out.write(fix.line.encode())
                if fix.action == "raise":
                    offset += len(line)
                    continue
            while i < len(placements) and placements[i].offset <= offset:
                out.write(f"M104 S{placements[i].target_c}".encode() + newline)
                i += 1
            if fix is not None and fix.heat_fix is not None \
                    and fix.heat_fix.offset == offset:
                out.write(fix.heat_fix.line.encode())
            elif first is not None and offset > first and _M104.match(line) \
                    and not _S_ZERO.search(line.split(b";")[0] + b" "):
                out.write(b"; " + line.rstrip(b"\r\n")
                          + b" ; overridden by flowloop bake" + newline)
                overridden += 1
            elif heater is not None:
                capped, changed = cap_line(line, heater, newline)
                out.write(capped)
                brought_within += changed
            else:
                out.write(line)
            offset += len(line)
    return overridden, brought_within


# --- the timeline as SVG (flowloop.material.plot's primitives) -----------------

def time_axis(end_s: float) -> Tuple[str, List[Tuple[float, str]]]:
    """The print-time axis' label and (seconds, text) ticks: seconds up to
    10 minutes, minutes up to 2 hours, h:mm beyond (20000 s reads 5:33)."""
    from ..material import plot
    if end_s <= 600:
        return "print time (s)", [(t, f"{t:g}") for t in plot.nice_ticks(0.0, end_s)]
    if end_s <= 7200:
        return "print time (min)", [(m * 60, f"{m:g}")
                                    for m in plot.nice_ticks(0.0, end_s / 60)]
    return "print time (h:mm)", [(h * 3600, f"{int(h)}:{round(h % 1 * 60):02d}")
                                 for h in plot.nice_ticks(0.0, end_s / 3600)]


def timeline_svg(timeline: Timeline, title: str) -> str:
    """Two panels over print time: temperatures (target, modelled nozzle)
    and flows (demanded, melt capacity at the modelled nozzle)."""
    from ..material import plot
    times = [k * GRID_S for k in range(len(timeline.target_c))]
    end = times[-1] if times else 1.0
    # a point per plotted pixel column is plenty
    stride = max(1, len(times) // 1500)

    def points(values):
        return [(times[k], values[k]) for k in range(0, len(values), stride)
                if values[k] is not None]

    temps = [x for x in timeline.target_c + timeline.nozzle_c if x is not None]
    lo, hi = (min(temps), max(temps)) if temps else (0.0, 1.0)
    flows = timeline.demand_mm3_s + timeline.capacity_mm3_s
    height = 40 + 2 * plot.PANEL_HEIGHT
    time_label, time_ticks = time_axis(end)
    out = plot.svg_open(plot.WIDTH, height)
    out.append(f'<text x="{plot.WIDTH / 2}" y="24" text-anchor="middle" '
               f'font-size="15" font-weight="bold">{_escape(title)}</text>')
    # headroom above the lines for the legend
    temp = plot.Panel(40, (0.0, end), (lo - 5.0, hi + 0.25 * (hi - lo) + 8.0))
    temp.frame("Hotend", time_label, "temperature (°C)", time_ticks)
    temp.polyline(points(timeline.target_c), plot.COLORS["target"], "target")
    temp.polyline(points(timeline.nozzle_c), plot.COLORS["nozzle"], "nozzle",
                  dash="6,3")
    temp.legend([("target (M104 / [autotemp])", plot.COLORS["target"], ""),
                 ("modelled nozzle", plot.COLORS["nozzle"], "6,3")])
    flow = plot.Panel(40 + plot.PANEL_HEIGHT, (0.0, end),
                      (0.0, max(flows, default=1.0) * 1.3 or 1.0))
    flow.frame("Flow", time_label, "flow (mm³/s)", time_ticks)
    flow.polyline(points(timeline.demand_mm3_s), plot.COLORS["demand"], "demand",
                  width=1)
    flow.polyline(points(timeline.capacity_mm3_s), plot.COLORS["capacity"],
                  "capacity")
    flow.legend([("demanded (peak per 0.1 s)", plot.COLORS["demand"], ""),
                 ("melt capacity at the modelled nozzle", plot.COLORS["capacity"],
                  "")])
    out += temp.parts + flow.parts
    out.append("</svg>")
    return "\n".join(out) + "\n"


def _escape(text: str) -> str:
    from xml.sax.saxutils import escape
    return escape(text)
