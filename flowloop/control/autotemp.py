"""Autotemp's temperature plan: heater targets ahead of the announced flow.

Windows of flow are announced ahead of time (AUTOTEMP_FLOW FLOW= LEAD=
DURATION=, flowloop.gcode.annotate). Each window needs the nozzle at the
temperature at which the profile's line melts its flow (`Line.temp_c`),
clamped to the limits (the profile's min and max, the heater's max_temp). The
plan, on a grid of GRID_S in print time:

1. need(t): the highest need of any window within `margin_s` of t (the
   profile's minimum where nothing is extruded or nothing is known);
2. nozzle(t): the lowest trajectory >= need that the hotend can follow, from
   a backward pass: before a rise the nozzle must already be where the
   heater can still reach the later need in time, both as a first-order lag
   toward max_temp (time constant) and within the heater's power left over
   after the loss to the room and the filament's heat (flowloop.control.hotend);
3. target(t): the model inverted, dead time included: the target that, seen
   dead_time_s later, makes the first-order lag follow nozzle(t) exactly;
   clamped to the limits. Where the nozzle may cool, the target drops to the
   need and the hotend cools as fast as it does.

A planner knows only the windows announced so far (`announce`): the printer
and the offline bake (`flowloop annotate --bake`) run the same one, so both
give the same targets for the same file.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from typing import List, NamedTuple, Optional, Tuple

from ..errors import FlowloopError
from ..material.profile import (
    MAX_FLOW_MM3_S,
    Line,
    Profile,
    check_working_point,
    profile_line,
)
from ..numbers import check_result
from .hotend import HotendModel, HotendParams

GRID_S = 0.1
# The need is held this long before and after each window: targets set
# between grid points, flushes and read-ahead land inside it.
DEFAULT_MARGIN_S = 0.5
# Share of the heater's spare power a planned rise may use: the rest absorbs
# what the model does not know (a flow a little above the window's peak).
POWER_SHARE = 0.9
# An announced flow may be this share below the mean flow it stands for
# (flowloop.gcode.melt: its cells carry the higher of the means at their
# ends, and between them the mean moves by up to CELL_S / MELT_TIME_S of
# the flow): the need is that of the flow this much higher.
FLOW_MARGIN = 0.005
# A rise is counted to within this of max_temp (the targets' resolution),
# and at most this many grid steps long (an hour).
RISE_TOP_C = 0.01
MAX_RISE_STEPS = 36000
# The modelled nozzle this far below the plan is behind it.
BEHIND_C = 1.0
# Windows further back than this are forgotten.
KEEP_S = 2.0
DEFAULT_PARAMS = HotendParams()


class TempLimits(NamedTuple):
    min_temp_c: float
    max_temp_c: float

    @classmethod
    def of(cls, profile: Profile, heater_max_temp_c: Optional[float] = None,
           heater_min_temp_c: Optional[float] = None) -> TempLimits:
        """The profile's bounds, within the heater's min_temp..max_temp."""
        b = profile.bounds
        top = b.max_temp_c if heater_max_temp_c is None \
            else min(b.max_temp_c, heater_max_temp_c)
        bottom = b.min_temp_c if heater_min_temp_c is None \
            else max(b.min_temp_c, heater_min_temp_c)
        if top <= bottom:
            lower = (f"the heater's min_temp {bottom:g} degC"
                     if bottom > b.min_temp_c
                     else f"the profile's min_temp_c {bottom:g} degC")
            raise FlowloopError(
                f"the heater's max_temp {top:g} degC is not above {lower}")
        return cls(bottom, top)

    def clamp(self, temp_c: float) -> float:
        return min(self.max_temp_c, max(self.min_temp_c, temp_c))


@dataclass(frozen=True)
class FlowWindow:
    start_s: float
    end_s: float
    flow_mm3_s: float


# AUTOTEMP_FLOW's bounds: more than any hotend melts, further ahead and
# longer than any annotation (flowloop.gcode.annotate: LEAD and DURATION at
# most its MAX_LEAD_S); beyond them the plan's grid would overflow
ANNOUNCED_FLOW_MM3_S = (0.0, MAX_FLOW_MM3_S)
ANNOUNCED_LEAD_S = (0.0, 3600.0)
MAX_ANNOUNCED_DURATION_S = 3600.0


def check_announcement(flow_mm3_s: float, lead_s: float, duration_s: float
                       ) -> None:
    """AUTOTEMP_FLOW's numbers: finite, flow and lead >= 0, duration > 0,
    each within its bound (the bound in the message: "DURATION: must be
    above 0 and at most 3600, got nan")."""
    low, high = ANNOUNCED_FLOW_MM3_S
    check_result(flow_mm3_s, "FLOW", minimum=low, maximum=high)
    low, high = ANNOUNCED_LEAD_S
    check_result(lead_s, "LEAD", minimum=low, maximum=high)
    check_result(duration_s, "DURATION", above=0.0,
                 maximum=MAX_ANNOUNCED_DURATION_S)


class TemperaturePlan:
    """Heater targets over print time from the flow windows announced so far."""

    def __init__(self, line: Line, limits: TempLimits,
                 params: HotendParams = DEFAULT_PARAMS,
                 margin_s: float = DEFAULT_MARGIN_S):
        self.line = line
        self.limits = limits
        self.params = params
        self.margin_s = margin_s
        self.windows: List[FlowWindow] = []     # by start time
        self.capped_windows = 0                 # needing more than max_temp
        self.flow_windows = 0                   # announced with flow
        # print time the modelled nozzle was behind the plan (a rise
        # announced later than it takes)
        self.behind_s = 0.0
        self._behind_from_s = -math.inf
        self.peak_flow_mm3_s = 0.0
        # the planned grid: index of its first point, nozzle temperatures
        self._first = 0
        self._nozzle: List[float] = []
        # the nozzle as the targets set so far move it (the hotend model),
        # dead_time_s ahead of the last target set (at _model_set_s)
        self._model: Optional[HotendModel] = None
        self._model_set_s = -math.inf
        self._first_c: Optional[float] = None

    # --- inputs -------------------------------------------------------------
    def need_c(self, flow_mm3_s: float) -> float:
        """The temperature a flow needs, within the limits (min when idle)."""
        if flow_mm3_s <= 0.0:
            return self.limits.min_temp_c
        return self.limits.clamp(self.line.temp_c(flow_mm3_s * (1.0 + FLOW_MARGIN)))

    def announce(self, now_s: float, flow_mm3_s: float, lead_s: float,
                 duration_s: float) -> FlowWindow:
        """A window of flow_mm3_s from now_s + lead_s, duration_s long."""
        check_announcement(flow_mm3_s, lead_s, duration_s)
        start = now_s + lead_s
        window = FlowWindow(start, start + duration_s, flow_mm3_s)
        if flow_mm3_s > 0.0:
            self.flow_windows += 1
            if self.line.temp_c(flow_mm3_s) > self.limits.max_temp_c:
                self.capped_windows += 1
        self.peak_flow_mm3_s = max(self.peak_flow_mm3_s, flow_mm3_s)
        if self._model is None and self._first_c is None:
            self._first_c = self.nozzle_c(now_s)
        keys = [w.start_s for w in self.windows]
        self.windows.insert(bisect.bisect_right(keys, start), window)
        self._forget(now_s - KEEP_S)
        self._replan(now_s)
        return window

    def set_windows(self, windows: List[FlowWindow], now_s: float) -> None:
        """Plan these windows instead of the ones announced (another plan's,
        when the profile or working point changes; none, to stop)."""
        self.windows = sorted(windows, key=lambda w: w.start_s)
        self._replan(now_s)

    def _forget(self, before_s: float) -> None:
        self.windows = [w for w in self.windows
                        if w.end_s + self.margin_s >= before_s]

    # --- the plan -----------------------------------------------------------
    def _needs(self, first: int, count: int) -> Tuple[List[float], List[float]]:
        """need and flow at grid points first..first+count-1."""
        need = [self.limits.min_temp_c] * count
        flow = [0.0] * count
        for w in self.windows:
            lo = max(first, math.floor((w.start_s - self.margin_s) / GRID_S))
            hi = min(first + count - 1,
                     math.ceil((w.end_s + self.margin_s) / GRID_S))
            if hi < lo:
                continue
            # within RISE_TOP_C of max_temp at most: the lag reaches
            # max_temp itself only asymptotically, so a plan at it would
            # start every rise toward it as early as the windows are known
            temp = min(self.need_c(w.flow_mm3_s),
                       self.limits.max_temp_c - RISE_TOP_C)
            for k in range(lo - first, hi - first + 1):
                if temp > need[k]:
                    need[k] = temp
                if w.flow_mm3_s > flow[k]:
                    flow[k] = w.flow_mm3_s
        return need, flow

    def _replan(self, now_s: float) -> None:
        first = math.floor(now_s / GRID_S)
        horizon = max((w.end_s for w in self.windows), default=now_s)
        last = math.ceil((horizon + self.margin_s) / GRID_S) + 2
        count = max(2, last - first + 1)
        need, flow = self._needs(first, count)
        nozzle = list(need)
        for k in range(count - 2, -1, -1):
            earliest = self._lowest_before(nozzle[k + 1], flow[k])
            if earliest > nozzle[k]:
                nozzle[k] = earliest
        self._first, self._nozzle = first, nozzle

    def _lowest_before(self, later_c: float, flow_mm3_s: float) -> float:
        """The lowest temperature one grid step before from which the heater
        still reaches later_c: as a lag toward max_temp and within its power."""
        p, top = self.params, self.limits.max_temp_c
        if later_c <= self.limits.min_temp_c:
            return self.limits.min_temp_c
        by_lag = top - (top - later_c) * math.exp(GRID_S / p.time_constant_s)
        spare_w = p.max_power_w - p.steady_power_w(later_c, flow_mm3_s)
        by_power = later_c - GRID_S * POWER_SHARE * spare_w / p.heat_capacity_j_per_c
        return min(top, max(by_lag, by_power))

    def longest_rise_s(self) -> float:
        """How long the plan takes to bring the nozzle from min_temp to
        within RISE_TOP_C of max_temp at the flow the line melts there,
        dead time included: announcements must come at least that far ahead
        of a window that needs max_temp, or the nozzle is late for it."""
        limits = self.limits
        flow = self.line.flow_mm3_s(limits.max_temp_c)
        temp, steps = limits.max_temp_c - RISE_TOP_C, 0
        while temp > limits.min_temp_c and steps < MAX_RISE_STEPS:
            earlier = self._lowest_before(temp, flow)
            if earlier >= temp:     # the heater cannot hold it: no rise ends
                return math.inf
            temp, steps = earlier, steps + 1
        return steps * GRID_S + self.params.dead_time_s

    def nozzle_c(self, time_s: float) -> float:
        """The planned nozzle temperature at time_s (>= the need)."""
        k = math.floor(time_s / GRID_S) - self._first
        if k < 0 or not self._nozzle:
            k = 0
        if k >= len(self._nozzle):
            return self.limits.min_temp_c
        return self._nozzle[k]

    def target_at(self, time_s: float, hold_s: float = GRID_S) -> float:
        """The heater target to set at time_s and hold for hold_s: the lowest
        that, seen dead_time_s later, keeps the nozzle at or above the
        planned temperature over the whole hold, from where the hotend model
        run on the targets set so far puts the nozzle then (a nozzle still
        hot from a peak is not pushed as if it were at the plan; one behind
        the plan gets the full target until it is back on it); in 0.01 degC."""
        p = self.params
        seen = time_s + p.dead_time_s
        start_c = self._nozzle_when_seen(time_s)
        if start_c < self.nozzle_c(seen) - BEHIND_C:
            # until the next target (holds of successive targets overlap)
            self.behind_s += min(hold_s, time_s - self._behind_from_s)
        self._behind_from_s = time_s
        best = -math.inf
        # every grid step that ends within the hold (and the one after)
        for j in range(1, max(1, math.ceil(hold_s / GRID_S)) + 2):
            decay = math.exp(-j * GRID_S / p.time_constant_s)
            want = self.nozzle_c(seen + j * GRID_S)
            best = max(best, (want - start_c * decay) / (1.0 - decay))
        # never below what the window the target acts in needs
        best = max(best, self.need_c(self.flow_at(seen)))
        target = round(self.limits.clamp(best), 2)
        self._model.set_target(time_s, target)
        return target

    @property
    def started(self) -> bool:
        """Whether the model runs (start_at, or the first target_at)."""
        return self._model is not None

    def start_at(self, time_s: float, temp_c: float) -> None:
        """The nozzle is at temp_c at time_s, held there until then (the
        start G-code's wait): the model runs on from there."""
        self._model = HotendModel(self.params, temp_c, time_s, temp_c)
        self._model_set_s = time_s
        self._first_c = None

    def applied(self, time_s: float, target_c: float) -> None:
        """The target last planned (at time_s) was set as target_c instead
        (the bake's whole degree, rounded up): the model runs on it."""
        if self._model is not None:
            self._model.set_target(time_s, target_c)

    def _nozzle_when_seen(self, time_s: float) -> float:
        """The modelled nozzle temperature at time_s + dead_time_s, when a
        target set at time_s starts to act: the model runs dead_time_s ahead
        of the targets, on the targets set so far and the announced flow."""
        model = self._model
        seen = time_s + self.params.dead_time_s
        if model is None or seen < model.time_s - 1e-9 \
                or time_s < self._model_set_s:
            # where the plan had the nozzle before its first window (a
            # window announced too late finds it there), else on the plan
            start = self._first_c if self._first_c is not None \
                else self.nozzle_c(seen)
            self._first_c = None
            model = self._model = HotendModel(self.params, start, seen, start)
        self._model_set_s = time_s
        t = model.time_s
        while t < seen - 1e-9:
            step = min(seen, (math.floor(t / GRID_S + 1e-9) + 1) * GRID_S)
            model.advance(step, self.flow_at(t))
            t = step
        return model.temp_c

    def flow_at(self, time_s: float) -> float:
        """The announced flow at time_s (0 where none)."""
        return max((w.flow_mm3_s for w in self.windows
                    if w.start_s <= time_s < w.end_s), default=0.0)

    def status(self) -> dict:
        return {"capped_windows": self.capped_windows,
                "peak_flow": self.peak_flow_mm3_s}


def plan_for(profile: Profile, working_point: float,
             heater_max_temp_c: Optional[float] = None,
             params: HotendParams = DEFAULT_PARAMS,
             margin_s: float = DEFAULT_MARGIN_S,
             heater_min_temp_c: Optional[float] = None) -> TemperaturePlan:
    """The plan for a profile at a working point (the one melt line)."""
    limits = TempLimits.of(profile, heater_max_temp_c, heater_min_temp_c)
    return TemperaturePlan(profile_line(profile, working_point), limits,
                           params, margin_s)


# A line gaining less than this over the whole min..max range: the
# temperature hardly changes what the hotend melts (the bench's ddPrint
# profiles gain 6.3-8.6 mm^3/s over theirs).
FLAT_GAIN_MM3_S = 1.0


def flat_line_note(line: Line, limits: TempLimits) -> Optional[str]:
    """One line when the melt line barely rises over the limits (None
    otherwise): autotemp then plans max_temp wherever the flow is more than
    min_temp melts, and can save little."""
    low = line.flow_mm3_s(limits.min_temp_c)
    high = line.flow_mm3_s(limits.max_temp_c)
    if high - low >= FLAT_GAIN_MM3_S:
        return None
    return (f"the profile's line gains only {high - low:.2f} mm^3/s from"
            f" {limits.min_temp_c:g} to {limits.max_temp_c:g} C ({low:.2f} to"
            f" {high:.2f} mm^3/s): the temperature hardly changes what the"
            f" hotend melts; any flow above {low:.2f} mm^3/s is planned up to"
            f" {limits.max_temp_c:g} C, and autotemp saves little over a fixed"
            f" temperature")


# ---------------------------------------------------------------------------
# The controller [autotemp] and the bake both drive

SOURCES = ("annotation", "lookahead")
# Lookahead (no annotations): moves are gathered into windows this long,
# each lengthened by the host's read-ahead (Klipper's BUFFER_TIME_HIGH, 1 s,
# until the host is known): the moves run up to that much after they are
# queued.
LOOKAHEAD_WINDOW_S = 1.0
DEFAULT_READ_AHEAD_S = 1.0    # host.klipper_config.HOST_BUFFER_TIME_S["Klipper"]
# This long after the last window known, the print is over: the source is
# forgotten and the slicer's M104 obeyed again.
DONE_AFTER_S = 5.0
# A target set at a flush holds until the next one: the plan looks that far
# ahead, as far as the last gap between flushes, at least GRID_S and at most
# MAX_HOLD_S (a longer gap, a pause, says nothing about the next one).
MAX_HOLD_S = 1.0


def motion_start_s(queued_end_s: float, mcu_now_s: float) -> float:
    """The print time the plan counts a LEAD or a move from: where the
    motion queued so far ends (the toolhead's print_time), or the MCU's
    present once it has run past that (an idle toolhead: its next move
    starts after the present, Klipper's BUFFER_TIME_START later, however
    long ago the last one ended). Counted from the stale end, the first
    window announced after a heat-up fell in the past (found on the
    simulated firmware: a target raised and dropped within 1.5 s, the
    window printed 40 C short). Up to the start buffer early, never late."""
    return max(queued_end_s, mcu_now_s)


def start_c(heater_target_c: float, nozzle_c: Optional[float]) -> float:
    """Where the model starts when autotemp takes over: the heater's target
    (the start's M109 waited for it), or the reading where the nozzle is
    cooler than that (a start that did not wait). A reading above the
    target is not taken: the model then starts cooler than the nozzle,
    which only plans more heat."""
    if nozzle_c is None or not math.isfinite(nozzle_c):
        return heater_target_c
    return min(heater_target_c, nozzle_c)


def hold_s(previous_flush_s: Optional[float], flush_s: float) -> float:
    """How long a target set at the flush at flush_s holds (the first
    flush: one GRID_S)."""
    if previous_flush_s is None:
        return GRID_S
    return min(MAX_HOLD_S, max(GRID_S, flush_s - previous_flush_s))


class Autotemp:
    """Which plan is active and why: the profile, the working point, the
    source of the windows (annotations, else the moves as Klipper queues
    them), on or off; the status is rebuilt whenever one of them changes."""

    def __init__(self, params: HotendParams = DEFAULT_PARAMS,
                 heater_max_temp_c: Optional[float] = None,
                 enabled: bool = True, margin_s: float = DEFAULT_MARGIN_S):
        self.params = params
        self.heater_max_temp_c = heater_max_temp_c
        self.heater_min_temp_c: Optional[float] = None
        self.last_flush_s: Optional[float] = None
        self.margin_s = margin_s
        self.enabled = enabled
        self.profile: Optional[Profile] = None
        self.profile_wp: Optional[float] = None
        self.wp_override: Optional[float] = None
        self.plan: Optional[TemperaturePlan] = None
        self.source: Optional[str] = None
        self.target_c: Optional[float] = None
        self.planned_flow_mm3_s: Optional[float] = None
        self._gathered: Optional[List[float]] = None   # lookahead: [s, peak]
        self.why = "no active profile"
        # what the klippy it runs in offers (set_host), None before connect
        self.host: Optional[dict] = None
        self.status = self._status()

    # --- what it plans with -------------------------------------------------
    @property
    def working_point(self) -> Optional[float]:
        return self.wp_override if self.wp_override is not None \
            else self.profile_wp

    @property
    def active(self) -> bool:
        return self.enabled and self.plan is not None

    def set_profile(self, profile: Optional[Profile],
                    working_point: Optional[float], now_s: float = 0.0) -> None:
        self.profile, self.profile_wp = profile, working_point
        self._rebuild(now_s)

    def set_working_point(self, working_point: Optional[float],
                          now_s: float = 0.0) -> None:
        """A WP of its own (None: the active profile's); checked first."""
        if working_point is not None:
            check_working_point(working_point)
        self.wp_override = working_point
        self._rebuild(now_s)

    def set_heater(self, min_temp_c: float, max_temp_c: float) -> None:
        """The heater's own min_temp..max_temp: no target leaves them."""
        self.heater_min_temp_c, self.heater_max_temp_c = min_temp_c, max_temp_c
        self._rebuild(0.0)

    def set_host(self, host: dict) -> None:
        """The host facts (Klipper or Kalico, how far ahead it reads G-code,
        the heater's control) the plan runs on, reported in the status."""
        self.host = dict(host)
        self.status = self._status()

    def set_enabled(self, enabled: bool) -> None:
        self.enabled = enabled
        self.status = self._status()

    def _rebuild(self, now_s: float) -> None:
        windows = self.plan.windows if self.plan is not None else []
        self.plan = None
        if self.profile is None:
            self.why = "no active profile"
        else:
            try:
                self.plan = plan_for(self.profile, self.working_point,
                                     self.heater_max_temp_c, self.params,
                                     self.margin_s, self.heater_min_temp_c)
                self.why = ""
            except FlowloopError as e:
                self.why = str(e)
        if self.plan is not None and windows:
            self.plan.set_windows(windows, now_s)
        self.status = self._status()

    # --- windows ------------------------------------------------------------
    def announce(self, now_s: float, flow_mm3_s: float, lead_s: float,
                 duration_s: float) -> None:
        """An AUTOTEMP_FLOW: from now on the annotations are the source."""
        check_announcement(flow_mm3_s, lead_s, duration_s)
        self.source = "annotation"
        self._gathered = None
        if self.plan is not None:
            self.plan.announce(now_s, flow_mm3_s, lead_s, duration_s)
        self.status = self._status()

    def on_move(self, now_s: float, flow_mm3_s: float, duration_s: float) -> None:
        """A move as Klipper queues it; used while no annotation was seen:
        gathered into LOOKAHEAD_WINDOW_S windows that start now (reactive)."""
        if self.source == "annotation" or self.plan is None:
            return
        g = self._gathered
        if g is None:
            g = self._gathered = [0.0, 0.0]
        g[0] += duration_s
        g[1] = max(g[1], flow_mm3_s)
        if g[0] >= LOOKAHEAD_WINDOW_S:
            self._gathered = None
            self.source = "lookahead"
            # the moves gathered are still in the lookahead queue: they run
            # after now_s, up to the host's read-ahead later
            self.plan.announce(now_s, g[1], 0.0, g[0] + self._read_ahead_s())
            self.status = self._status()

    def _read_ahead_s(self) -> float:
        """How far ahead the host's toolhead reads G-code (set_host's
        buffer_time_s; Klipper's 1 s before the host is known)."""
        if self.host and self.host.get("buffer_time_s") is not None:
            return float(self.host["buffer_time_s"])
        return DEFAULT_READ_AHEAD_S

    def stop(self) -> None:
        """Forget the windows and the source: the heater was turned off, or
        the print is over. The next window starts a new plan."""
        self.source, self._gathered = None, None
        self.target_c = self.planned_flow_mm3_s = None
        if self.plan is not None:
            self.plan.set_windows([], 0.0)
        self.status = self._status()

    # --- targets ------------------------------------------------------------
    def target_at(self, time_s: float, hold_s: float = GRID_S) -> Optional[float]:
        """The target to set at time_s (None: autotemp has nothing to say)."""
        if not self.active or self.source is None:
            return None
        last_end = max((w.end_s for w in self.plan.windows), default=-math.inf)
        if time_s > last_end + DONE_AFTER_S:
            self.stop()
            return None
        target = self.plan.target_at(time_s, hold_s)
        acting = time_s + self.params.dead_time_s
        flow = max((w.flow_mm3_s for w in self.plan.windows
                    if w.start_s <= acting < w.end_s), default=0.0)
        if target != self.target_c or flow != self.planned_flow_mm3_s:
            self.target_c, self.planned_flow_mm3_s = target, flow
            self.status = self._status()
        return target

    def applied(self, time_s: float, target_c: float) -> None:
        """The target from target_at(time_s) was set as target_c (a bake
        rounds it up to a whole degree)."""
        if self.active:
            self.plan.applied(time_s, target_c)

    def on_flush(self, flush_s: float, heater_target_c: float,
                 printing: bool = True,
                 nozzle_c: Optional[float] = None) -> Optional[float]:
        """At each flush of generated motion (flush_s: the print time steps
        are generated to; heater_target_c: the heater's target now;
        nozzle_c: the heater's reading now, None where none arrives): the
        target to set, or None to leave the heater as it is. A tool that
        does not print keeps its user's target; a heater turned off (M104
        S0, TURN_OFF_HEATERS, a fault) while a source was planning makes
        autotemp stand down until the next window: it never turns a heater
        on."""
        hold = hold_s(self.last_flush_s, flush_s)
        self.last_flush_s = flush_s
        if not printing:
            return None
        if self.source is not None and heater_target_c == 0.0:
            self.stop()
            return None
        if self.active and self.source is not None and not self.plan.started:
            # the heater is where its target is when autotemp takes over (the
            # start G-code's M109 waited for it): the model starts there, also
            # below the profile's minimum (clamped up, it believed the nozzle
            # hotter than it is and planned too little heat for the first
            # windows), and never above what the heater reads (a start that
            # did not wait: believed at its target, the nozzle got too
            # little heat for the first windows too). Targets stay within
            # the limits (target_at).
            self.plan.start_at(flush_s, start_c(heater_target_c, nozzle_c))
        target = self.target_at(flush_s, hold)
        return None if target == heater_target_c else target

    def overrides_m104(self) -> bool:
        """While it plans a print, the slicer's M104 is not obeyed."""
        return self.active and self.source is not None

    def _status(self) -> dict:
        plan = self.plan
        return {
            "enabled": self.enabled,
            "active": self.active,
            "source": self.source,
            "planned_flow": self.planned_flow_mm3_s,
            "target": self.target_c,
            "working_point": self.working_point,
            "profile": None if self.profile is None else self.profile.name,
            "min_temp": None if plan is None else plan.limits.min_temp_c,
            "max_temp": None if plan is None else plan.limits.max_temp_c,
            "capped_windows": 0 if plan is None else plan.capped_windows,
            "why": self._why(),
            "host": self.host,
        }

    def _why(self) -> str:
        if not self.enabled:
            return "disabled (SET_AUTOTEMP ENABLE=1 turns it on)"
        if self.why:
            return self.why + ": autotemp is off"
        if self.source == "lookahead":
            return ("no AUTOTEMP_FLOW in this file: reactive, on the moves"
                    " Klipper has queued (about 1 s ahead)")
        if self.source is None:
            return "waiting for AUTOTEMP_FLOW or extruding moves"
        return ""
