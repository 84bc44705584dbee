"""The decisions of an into-air profile measurement (MEASURE_MATERIAL_PROFILE).

Pure: the klippy adapter heats, swaps the heater's control, extrudes and
collects the flow sensor's grip windows; this module says which levels and
flows to run, whether a hotend has settled, what a step of the ramp
measured, and which point a level gives.

The procedure (ddPrint's, on Klipper): for each level (a temperature, or a
heater power), hold the heater at a fixed power, extrude into air at a flow
rising by STEP from START_FLOW, and stop when the grip of a step falls
below MIN_GRIP. The level's point is that step: the flow the sensor
measured (what the hotend really melted while the feeder slipped), the
hotend temperature over the step, and the heater power.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass
from typing import Iterator, Optional, Sequence, Tuple

from ..errors import FlowloopError
from ..window import Window
from .fit import MIN_PWM_SPREAD, MIN_TEMP_SPREAD_C
from .profile import MeasuredPoint

DEFAULT_START_FLOW_MM3_S = 2.0
DEFAULT_STEP_MM3_S = 1.0
DEFAULT_MAX_FLOW_MM3_S = 30.0
# Without START_FLOW a level's ramp starts at this share of the flow the base
# profile expects at the level's settled temperature: most of the ramp below
# the limit is filament spent learning nothing.
START_SHARE = 0.8
MIN_LEVELS = 2
MAX_LEVELS = 10
MAX_STEPS = 200
# TEMPS= levels span at least this: a level's point is read where its grip
# falls, and the heater sags there under the level's flow, the hotter level
# (more flow) further. The fit needs MIN_TEMP_SPREAD_C between the points;
# levels 7 C apart gave points 4.99 apart on the simulated firmware's hotend
# (stop 45's CI), after a run of minutes that then stored nothing.
MIN_LEVEL_SPREAD_C = 2.0 * MIN_TEMP_SPREAD_C
# levels typed as decimals differ by a hair from their span (210.1 - 200.1
# is 9.99999...): a span this close to its least counts as that least
_SPREAD_SLACK = 1e-9
# [measure_profile] options and their limits: the adapter reads them here
DEFAULT_STEP_TIME_S = 2.0
STEP_TIME_RANGE_S = (1.0, 30.0)
DEFAULT_SETTLE_TIME_S = 10.0
SETTLE_TIME_RANGE_S = (2.0, 120.0)
DEFAULT_MAX_SETTLE_TIME_S = 300.0
MAX_SETTLE_TIME_RANGE_S = (30.0, 1800.0)
SETTLE_BAND_C = 1.0
# A step lasts at least this many grip windows (the first ones are the
# transient, and a window straddling the step's start is not judged).
MIN_STEP_WINDOWS = 4
# A step that may be the level's limit lasts at least this many: its
# measured flow is the level's point, and a 4-window step often leaves one
# judged window after the transient (one window's noise in the fit). A step
# may be the limit from min_grip x the flow the base profile expects (every
# step without a base profile).
LIMIT_STEP_WINDOWS = 5
# Windows in the first part of a step are the transient: not judged.
STEP_TRANSIENT_SHARE = 0.3
# A window closes on the first sample past its filament: just after the step.
STEP_END_SLACK_S = 0.25
PWM_MAX = 255.0          # the profile's PWM scale (ddPrint's)
# Where a heater's loss to the room is zero (Klipper's heaters.AMBIENT_TEMP,
# flowloop.control.hotend's default ambient_c).
AMBIENT_C = 25.0


@dataclass(frozen=True)
class Plan:
    """What a MEASURE_MATERIAL_PROFILE runs."""
    by: str                          # "temperature" or "power"
    levels: Tuple[float, ...]        # degC, or heater power 0..1
    start_flow_mm3_s: float
    step_mm3_s: float
    max_flow_mm3_s: float
    min_grip: float
    start_given: bool = True         # False: start near the base profile's limit

    def ramp_start(self, expected_mm3_s: Optional[float]) -> float:
        """Where a level's ramp starts: START_FLOW when it was given (or no
        base profile expects a flow), else START_SHARE of the flow the base
        profile expects at the settled temperature (to 0.01 mm^3/s), never
        below START_FLOW nor above MAX_FLOW. Not floored onto a grid from
        START_FLOW: that started up to a STEP lower, a step of filament
        spent learning nothing."""
        start = self.start_flow_mm3_s
        if self.start_given or expected_mm3_s is None:
            return start
        share = math.floor(START_SHARE * expected_mm3_s * 100.0) / 100.0
        return min(max(share, start), self.max_flow_mm3_s)

    def step_windows(self, flow_mm3_s: float,
                     expected_mm3_s: Optional[float]) -> int:
        """The grip windows a step at flow_mm3_s lasts at least:
        LIMIT_STEP_WINDOWS where it may be the level's limit, else
        MIN_STEP_WINDOWS."""
        if (expected_mm3_s is not None
                and flow_mm3_s < self.min_grip * expected_mm3_s):
            return MIN_STEP_WINDOWS
        return LIMIT_STEP_WINDOWS

    def flows(self, start_mm3_s: Optional[float] = None) -> Iterator[float]:
        """start (default START_FLOW), + STEP, ... up to MAX_FLOW."""
        first = self.start_flow_mm3_s if start_mm3_s is None else start_mm3_s
        i = 0
        while True:
            flow = first + i * self.step_mm3_s
            if flow > self.max_flow_mm3_s + 1e-9:
                return
            yield flow
            i += 1

    def describe_level(self, level: float) -> str:
        if self.by == "temperature":
            return f"{level:g} degC"
        return f"power {level:.0%}"


def _positive(name: str, value: float) -> float:
    if not (math.isfinite(value) and value > 0):
        raise FlowloopError(f"{name}: must be a number above 0, got {value}")
    return value


def make_plan(temps: Optional[Sequence[float]], powers: Optional[Sequence[float]],
              start_flow: Optional[float], step: float, max_flow: float,
              min_grip: float, min_temp_c: float, max_temp_c: float,
              max_power: float = 1.0) -> Plan:
    """The plan, or FlowloopError naming the parameter. Temperatures must lie
    within the profile's bounds (min_temp_c..max_temp_c, the heater's
    max_temp already applied), powers within 0..1 (share of max_power, the
    heater's: their points' PWM is the share of it).
    start_flow None: DEFAULT_START_FLOW_MM3_S, and each level may start
    nearer its expected limit (Plan.ramp_start)."""
    start_given = start_flow is not None
    if not start_given:
        start_flow = DEFAULT_START_FLOW_MM3_S
    if (temps is None) == (powers is None):
        raise FlowloopError("give TEMPS= or POWERS= (one of them)")
    name = "TEMPS" if temps is not None else "POWERS"
    levels = tuple(temps if temps is not None else powers)
    if not MIN_LEVELS <= len(levels) <= MAX_LEVELS:
        raise FlowloopError(f"{name}: needs {MIN_LEVELS} to {MAX_LEVELS} levels,"
                            f" got {len(levels)}")
    if len(set(levels)) != len(levels):
        raise FlowloopError(f"{name}: each level once")
    for level in levels:
        if temps is not None and not min_temp_c <= level <= max_temp_c:
            raise FlowloopError(
                f"TEMPS: {level:g} degC is outside the profile's "
                f"{min_temp_c:g}..{max_temp_c:g} degC")
        if powers is not None and not 0.0 < level <= 1.0:
            raise FlowloopError(f"POWERS: {level:g} must be in 0..1 (share of "
                                f"the heater's max_power)")
    spread = max(levels) - min(levels)
    if temps is not None and spread < MIN_LEVEL_SPREAD_C - _SPREAD_SLACK:
        raise FlowloopError(
            f"TEMPS: the levels span {spread:g} degC; at "
            f"least {MIN_LEVEL_SPREAD_C:g} is needed (the heater sags under a "
            f"level's flow, and the fit needs {MIN_TEMP_SPREAD_C:g} between "
            f"the points)")
    if powers is not None and spread * max_power < MIN_PWM_SPREAD - _SPREAD_SLACK:
        # a fixed power's point is read at that power: no sag, but the fit
        # needs MIN_PWM_SPREAD of full power between them
        raise FlowloopError(
            f"POWERS: the levels span {spread:g} of "
            f"max_power {max_power:g}; at least {MIN_PWM_SPREAD:.0%} of full "
            f"power is needed between them for the fit")
    _positive("START_FLOW", start_flow)
    _positive("STEP", step)
    _positive("MAX_FLOW", max_flow)
    if max_flow < start_flow:
        raise FlowloopError(f"MAX_FLOW: {max_flow:g} is below START_FLOW "
                            f"{start_flow:g}")
    if (max_flow - start_flow) / step + 1 > MAX_STEPS:
        raise FlowloopError(f"STEP: {step:g} mm^3/s from {start_flow:g} to "
                            f"{max_flow:g} is more than {MAX_STEPS} steps")
    if not 0.0 < min_grip < 1.0:
        raise FlowloopError(f"MIN_GRIP: must be in 0..1 (exclusive), got "
                            f"{min_grip:g}")
    return Plan("temperature" if temps is not None else "power",
                tuple(sorted(levels)), start_flow, step, max_flow, min_grip,
                start_given)


# Heatings a POWERS= level may take to find where its power holds, and how
# near that is near enough (the fixed power settles the rest)
POWER_LEVEL_TRIES = 4
POWER_LEVEL_BAND_C = 2.0
# settle_time waits after settling before a POWERS= heating's power is read
# (a TEMPS= level waits one): the rest of the approach in the mean power
# moves the level's temperature by hundreds of times as much
POWER_LEVEL_WAITS = 2


def power_level_target(power: float, holds: Sequence[Tuple[float, float]],
                       min_temp_c: float, max_temp_c: float) -> Optional[float]:
    """Where to heat next (with the heater's own control) so that `power`
    holds the nozzle once it is fixed; None: the last heating is there
    (within POWER_LEVEL_BAND_C). holds: (mean power, temperature) of each
    heating so far, the last one where the nozzle is now.

    A held power alone takes minutes (the block's time constant, C / loss)
    to reach its temperature and the settle test passes long before, so a
    POWERS= level heats there first. The mean power over a settle still
    carries the approach (high after heating up, low after cooling down,
    and a 1 % error moves a 30 % level's temperature by 6 degC), so the
    target is on the line through ambient fitted to all heatings (the
    errors of both signs cancel). Beyond the profile's bounds: the bound, then
    FlowloopError."""
    hold_power, hold_temp_c = holds[-1]
    # the loss through ambient fitted to every heating: P = k (T - ambient),
    # flowloop.control.hotend's balance
    rises = [t - AMBIENT_C for _, t in holds]
    k = (sum(p * r for (p, _), r in zip(holds, rises))
         / sum(r * r for r in rises))
    if not (k > 0.0 and min(rises) > 0.0):
        raise FlowloopError(
            f"POWERS: {hold_power:.1%} power held {hold_temp_c:g} degC: no"
            " power level can be placed from that")
    estimate = AMBIENT_C + power / k
    if abs(estimate - hold_temp_c) <= POWER_LEVEL_BAND_C:
        return None
    target = min(max(estimate, min_temp_c), max_temp_c)
    if target != estimate and abs(target - hold_temp_c) <= POWER_LEVEL_BAND_C:
        raise FlowloopError(
            f"POWERS: {power:.1%} power holds about {estimate:.0f} degC,"
            f" outside the profile's {min_temp_c:g}..{max_temp_c:g} degC"
            f" ({hold_power:.1%} held {hold_temp_c:g} degC)")
    return target


def settled(readings: Sequence[Tuple[float, float]], hold_s: float,
            band_c: float = SETTLE_BAND_C) -> bool:
    """True when the (time_s, temp_c) readings of the last hold_s stay within
    band_c of each other (and cover hold_s)."""
    if not readings:
        return False
    end = readings[-1][0]
    if end - readings[0][0] < hold_s:
        return False
    recent = [temp for t, temp in readings if t >= end - hold_s]
    return max(recent) - min(recent) <= band_c


@dataclass(frozen=True)
class StepResult:
    """One step of the ramp, judged from the sensor's windows in it."""
    commanded_mm3_s: float
    grip: float
    measured_mm3_s: float
    temp_c: Optional[float]
    windows: int
    duration_s: Optional[float] = None   # how long the step extruded

    def describe(self) -> str:
        temp = "" if self.temp_c is None else f" at {self.temp_c:.1f} degC"
        took = ("" if self.duration_s is None
                else f" for {self.duration_s:.1f} s")
        return (f"flow {self.commanded_mm3_s:.2f} mm^3/s{took}: grip"
                f" {self.grip:.3f}, measured {self.measured_mm3_s:.2f}"
                f" mm^3/s{temp}")


def step_duration_s(step_time_s: float, flow_mm3_s: float,
                    filament_area_mm2: float, window_mm: float,
                    windows: int = MIN_STEP_WINDOWS) -> float:
    """How long a step at flow_mm3_s runs: step_time_s, or long enough for
    `windows` grip windows of window_mm filament at a low flow."""
    speed_mm_s = flow_mm3_s / filament_area_mm2
    return max(step_time_s, windows * window_mm / speed_mm_s)


def judge_step(windows: Sequence[Window], start_time: float, end_time: float,
               commanded_mm3_s: float) -> Optional[StepResult]:
    """The step from its judged windows after the transient (None: none)."""
    after = start_time + STEP_TRANSIENT_SHARE * (end_time - start_time)
    judged = [w for w in windows
              if w.grip is not None and w.start_time >= after
              and w.end_time <= end_time + STEP_END_SLACK_S]
    if not judged:
        return None
    temps = [float(w.temp_c) for w in judged if w.temp_c is not None]
    grip = _filament_median(judged)
    measured = _mean_flow(judged)
    if measured is None:
        measured = commanded_mm3_s * grip
    return StepResult(float(commanded_mm3_s), grip, float(measured),
                      statistics.fmean(temps) if temps else None, len(judged))


def _mean_flow(windows: Sequence[Window]) -> Optional[float]:
    """The windows' measured flow over their time (the volume they measured
    over the time they took: a short window's noisy ends count for little);
    None if none has a flow."""
    return _weighted_mean([(float(w.flow_mm3_s), w.end_time - w.start_time)
                           for w in windows if w.flow_mm3_s is not None
                           and w.end_time > w.start_time])


def _weighted_mean(pairs: Sequence[Tuple[float, float]]) -> Optional[float]:
    """The mean of (value, weight) pairs by weight; None without pairs."""
    if not pairs:
        return None
    return sum(v * w for v, w in pairs) / sum(w for _, w in pairs)


def limit_point(step: StepResult, power: Optional[float],
                fallback_temp_c: float, kind: str = "into_air") -> MeasuredPoint:
    """The level's point: the step whose grip fell below MIN_GRIP."""
    temp = float(step.temp_c if step.temp_c is not None else fallback_temp_c)
    return MeasuredPoint(kind=kind, temp_c=round(temp, 2),
                         flow_mm3_s=round(float(step.measured_mm3_s), 4),
                         grip=round(min(2.0, max(0.0, float(step.grip))), 4),
                         heater_pwm=None if power is None else round(
                             min(1.0, max(0.0, float(power))) * PWM_MAX, 2))


# --- the real-print measurement (MEASURE_MATERIAL_PROFILE_PRINT) -----------
# The judged windows over this much commanded filament decide (8 windows at
# the default grip_window; a slip closes windows sooner, so count filament)
PRINT_FILAMENT_MM = 10.0


class PrintWatch:
    """Watches a print of the measurement part: the grip windows as they
    close; `add` returns the point once the median grip (per mm of
    filament) of the judged windows over the last PRINT_FILAMENT_MM falls
    below min_grip (what the hotend melted then, at its temperature), else
    None."""

    def __init__(self, min_grip: float, filament_mm: float = PRINT_FILAMENT_MM):
        if not 0.0 < min_grip < 1.0:
            raise FlowloopError(f"MIN_GRIP: must be in 0..1 (exclusive), got "
                                f"{min_grip:g}")
        self.min_grip = min_grip
        self.filament_mm = filament_mm
        self.recent: list = []
        self.judged = 0

    def add(self, window: Window) -> Optional[StepResult]:
        if window.grip is None or window.flow_mm3_s is None:
            return None
        self.judged += 1
        self.recent.append(window)
        # the fewest newest windows that make up filament_mm
        while sum(w.commanded_mm for w in self.recent[1:]) >= self.filament_mm:
            del self.recent[0]
        if sum(w.commanded_mm for w in self.recent) < self.filament_mm:
            return None
        grip = _filament_median(self.recent)
        if grip >= self.min_grip:
            return None
        temps = [float(w.temp_c) for w in self.recent if w.temp_c is not None]
        flow = _mean_flow(self.recent)
        return StepResult(flow / grip, grip, flow,
                          statistics.fmean(temps) if temps else None,
                          len(self.recent))


def _filament_median(windows: Sequence[Window]) -> float:
    """The grip at half the windows' filament, in order of grip (for windows
    of equal length, statistics.median: between the two middle ones)."""
    ordered = sorted(windows, key=lambda w: float(w.grip))
    half = sum(w.commanded_mm for w in ordered) / 2.0
    below = 0.0
    for i, w in enumerate(ordered):
        below += w.commanded_mm
        if abs(below - half) <= 1e-9 * half and i + 1 < len(ordered):
            return (float(w.grip) + float(ordered[i + 1].grip)) / 2.0
        if below >= half:
            return float(w.grip)
    return float(ordered[-1].grip)


def melted_flow(windows: Sequence[Window],
                layers: Sequence[Tuple[float, float]]) -> Optional[float]:
    """What the hotend melted while extruding, over judged windows: each
    window's grip times the planned flow of the layer it began in
    (layers: (print time the layer starts, planned flow), in order). The
    windows' own flow spans travel and corners and reads low), per mm of
    filament. None: no window began in a known layer."""
    per_mm = []
    for w in windows:
        if w.grip is None:
            continue
        planned = [flow for start, flow in layers if start <= w.start_time]
        if planned:
            per_mm.append((planned[-1] * float(w.grip), float(w.commanded_mm)))
    return _weighted_mean(per_mm)
