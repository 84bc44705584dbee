"""The predictive grip model: grip as a function of flow and temperature.

Above its melt capacity C(T) a hotend passes only C(T) of the flow it is
asked for, so the feeder slips: predicted grip(F, T) = min(1, C(T) / F).
C is a straight line in temperature, C(T) = capacity_mm3_s + slope *
(T - ref_temp_c). It is seeded from the active profile: the profile's line
at the working point is where grip fell to the profile's min_grip, so
C = that line * min_grip (one melt line, flowloop.material's).

It is updated online from the sensor's grip windows. A window mixes fast
and slow moves (and pauses), so grip times its mean commanded flow reads
well below the capacity its fast moves met: a window that slipped measured
C as `melted_capacity`, the C at which min(F(t), C) over its commanded flow
F(t) averages to the flow the sensor measured. A window that kept up while
its commanded flow peaked above C shows C is at least that peak (one that
slipped within SLIP_TOLERANCE: the C its slip gives). The fit is least
squares over the most recent windows, pulled toward the seed: on the slope
by a prior worth `prior_windows` windows over a temperature span of
`PRIOR_SPAN_C`, so windows at one temperature do not tilt it; on the
capacity by one worth only `capacity_prior_windows` (half a window): the
profile's capacity is a guess made on another hotend or day, a window that
slipped measures this one's, so the first slip moves the capacity two
thirds of the way and the seed no longer holds the fit above what the
windows measure (worth 5 windows, it held the bench's twin 1 % above its
capacity for the whole print, every capped move slipping that much).

A window at the cap that reads a slip beyond the noise band (SLIP_TOLERANCE)
counts even when only the sensor's noise made it read so; alone, those
would pull the fit down and never up, and a noisy sensor's model drifted
3.5 % below its hotend over ten layers. So a window at the cap that reads
as far over 1 counts too, at the capacity its excess says
(capacity_read_over). Within the band, a window at the cap teaches nothing.

The predictive cap is C(T), the flow at which the model predicts the feeder
starts to slip: it acts before grip falls, where the reactive rule (and
min_grip, its threshold) acts after. Capping at C / min_grip instead would
run every capped move at grip min_grip, under-extruding by design.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass
from typing import Any, Deque, Dict, Optional, Sequence, Tuple

import numpy as np

from ..errors import FlowloopError
from ..material.profile import Line
from ..window import Window

# A window at grip >= 1 - SLIP_TOLERANCE did not slip (sensor noise).
SLIP_TOLERANCE = 0.02
MAX_OBSERVATIONS = 200
DEFAULT_PRIOR_WINDOWS = 5.0
DEFAULT_CAPACITY_PRIOR_WINDOWS = 0.5
PRIOR_SPAN_C = 20.0
# 1.75 mm filament (mm^2): the area a rule assumes when it is given none
DEFAULT_FILAMENT_AREA_MM2 = 2.405
# A model that knows nothing of its hotend but the profile (a first print)
# starts at CLIMB_FROM of the profile's capacity, as if the profile were
# 30 % high (the envelope a profile measured on another hotend or day is
# held to), and climbs from there: each window that kept up raises the
# seed to CLIMB_STEP times what that window asked for (its peak), up to the
# profile's line; the first window that slips beyond SLIP_TOLERANCE ends
# the climb (it measured the capacity, and the fit takes over from the seed
# where the climb left it). A step of 5 %: the overshoot a climb can cause
# is at most 5 % above a flow the hotend kept up with, 2.5 times the noise
# band.
CLIMB_FROM = 1.0 / 1.3
CLIMB_STEP = 1.05


@dataclass(frozen=True)
class CapacityLine:
    """C(T) = capacity_mm3_s + slope_mm3_s_per_c * (T - ref_temp_c)."""

    ref_temp_c: float
    capacity_mm3_s: float
    slope_mm3_s_per_c: float

    def at(self, temp_c: float) -> float:
        return max(0.0, self.capacity_mm3_s
                   + self.slope_mm3_s_per_c * (temp_c - self.ref_temp_c))

    def scaled(self, ratio: float) -> CapacityLine:
        return CapacityLine(self.ref_temp_c, ratio * self.capacity_mm3_s,
                            ratio * self.slope_mm3_s_per_c)

    @classmethod
    def from_profile_line(cls, line: Line, grip: float, ref_temp_c: float,
                          melt_ratio: float = 1.0) -> CapacityLine:
        """The melt capacity under a profile's line measured at `grip`, as
        the line's tangent at ref_temp_c (the Line may bend at a ceiling),
        times melt_ratio: what this hotend melts against the profile
        (flowloop.control.nozzle_health's ratio, 1: as the profile says)."""
        half = PRIOR_SPAN_C / 2.0
        slope = (line.flow_mm3_s(ref_temp_c + half)
                 - line.flow_mm3_s(ref_temp_c - half)) / (2.0 * half)
        scale = grip * melt_ratio
        return cls(ref_temp_c, scale * line.flow_mm3_s(ref_temp_c), scale * slope)


def predicted_grip(capacity: CapacityLine, flow_mm3_s: float,
                   temp_c: float) -> float:
    if flow_mm3_s <= 0.0:
        return 1.0
    return min(1.0, capacity.at(temp_c) / flow_mm3_s)


def melted_capacity(flows_mm3_s: Sequence[float], melted_mm3_s: float) -> float:
    """The melt capacity C at which a hotend passing min(F, C) of each
    piece's commanded flow F (pieces of equal duration) passes melted_mm3_s
    on average; the highest piece's flow if it passed them all."""
    f = np.sort(np.asarray(flows_mm3_s, dtype=np.float64))
    n = len(f)
    if not n or melted_mm3_s >= f.mean():
        return float(f[-1]) if n else float(melted_mm3_s)
    if melted_mm3_s <= 0.0:
        return 0.0
    # mean(min(f, C)) = (sum of the pieces below C + C * the rest) / n: for
    # C in [f[k-1], f[k]], C = (n * melted - sum(f[:k])) / (n - k)
    below = np.concatenate(([0.0], np.cumsum(f)[:-1]))
    k = np.arange(n)
    c = (n * melted_mm3_s - below) / (n - k)
    low = np.concatenate(([0.0], f[:-1]))
    fits = (c >= low - 1e-12) & (c <= f + 1e-12)
    return float(c[np.argmax(fits)])


def capacity_read_over(flows_mm3_s: np.ndarray, melted_mm3_s: float,
                       melted_capacity_mm3_s: float) -> float:
    """melted_capacity's mirror for a window that read more than it was
    asked (melted above the mean, which only the sensor's noise gives): the
    capacity as far above its peak as melted_capacity would put it below for
    as much less (the pieces at the peak, within SLIP_TOLERANCE of it, take
    the difference); melted_capacity_mm3_s where it read no more."""
    mean = float(flows_mm3_s.mean()) if len(flows_mm3_s) else 0.0
    if not len(flows_mm3_s) or melted_mm3_s <= mean:
        return melted_capacity_mm3_s
    peak = float(flows_mm3_s.max())
    share = float(np.mean(flows_mm3_s >= peak * (1.0 - SLIP_TOLERANCE)))
    return peak + (melted_mm3_s - mean) / share


def duration_s(window: Window) -> float:
    """How long a window lasted (a plain float: windows may carry numpy
    numbers, the limiter's status is JSON)."""
    return float(window.end_time - window.start_time)


def judged_flow_mm3_s(window: Window,
                      filament_area_mm2: float) -> Optional[float]:
    """The mean flow a window asked for, if a grip rule may judge it; None
    if not: the sensor was faulted (Window.faulted: a fault reaches the
    rules only this way), the window was not judged (grip None), or it
    lasted no time or asked for no forward flow."""
    if window.faulted or window.grip is None:
        return None
    duration = duration_s(window)
    if duration <= 0.0:
        return None
    flow = filament_area_mm2 * float(window.commanded_mm) / duration
    return flow if flow > 0.0 else None


@dataclass(frozen=True)
class WindowFlow:
    """What one judged grip window says about the melt capacity."""
    commanded_mm3_s: float  # mean commanded flow
    grip: float
    melted_mm3_s: float     # melted_capacity: what the hotend melted when asked more
    peak_mm3_s: float       # the highest commanded flow in it
    # where it read more than it was asked (grip over 1): the capacity that
    # excess says, above the peak (capacity_read_over); melted_mm3_s if not
    over_mm3_s: float

    @classmethod
    def of(cls, commanded_mm3_s: float, grip: float,
           flows_mm3_s: Sequence[float] = ()) -> WindowFlow:
        """From the window's mean commanded flow, its grip, and its commanded
        flow over time (equal pieces, scaled to the mean: the planned motion
        leaves out pressure advance); without them, a window at one flow."""
        flows = np.asarray(flows_mm3_s, dtype=np.float64)
        mean = flows.mean() if len(flows) else 0.0
        if mean <= 0.0:
            flows, mean = np.array([commanded_mm3_s]), commanded_mm3_s
        flows = flows * (commanded_mm3_s / mean)
        melted = melted_capacity(flows, grip * commanded_mm3_s)
        return cls(float(commanded_mm3_s), float(grip), melted,
                   float(flows.max()),
                   capacity_read_over(flows, grip * commanded_mm3_s, melted))

    @classmethod
    def of_window(cls, window: Window,
                  filament_area_mm2: float) -> Optional[WindowFlow]:
        """The one place a grip window becomes flows: None for a window no
        rule may judge (judged_flow_mm3_s)."""
        flow = judged_flow_mm3_s(window, filament_area_mm2)
        if flow is None:
            return None
        return cls.of(flow, float(window.grip), window.commanded_flows)


class GripModel:
    def __init__(self, seed: CapacityLine,
                 prior_windows: float = DEFAULT_PRIOR_WINDOWS,
                 filament_area_mm2: float = DEFAULT_FILAMENT_AREA_MM2,
                 capacity_prior_windows: float = DEFAULT_CAPACITY_PRIOR_WINDOWS,
                 climb_from: Optional[float] = None):
        """climb_from: climb to seed from this share of it (CLIMB_FROM: a
        model that knows nothing of its hotend but the profile; 1: none)."""
        for name, value in (("prior_windows", prior_windows),
                            ("capacity_prior_windows", capacity_prior_windows)):
            if not value > 0:
                raise FlowloopError(f"{name} must be above 0, not {value}")
        if climb_from is not None and not 0.0 < climb_from <= 1.0:
            raise FlowloopError(f"climb_from must be above 0 and at most 1,"
                                f" not {climb_from}")
        self.capacity_prior_windows = capacity_prior_windows
        self.filament_area_mm2 = filament_area_mm2
        # the line climbed to, and how far up it the climb is (None: not
        # climbing; the seed is then where it stopped)
        self.line = seed
        self.climb_ratio = climb_from if climb_from is not None \
            and climb_from < 1.0 else None
        if self.climb_ratio is not None:
            seed = seed.scaled(self.climb_ratio)
        self.seed = seed
        self.fitted = seed
        self.prior_windows = prior_windows
        # (temp_c, capacity seen) per informative window
        self.observations: Deque[Tuple[float, float]] = collections.deque(
            maxlen=MAX_OBSERVATIONS)

    def learn(self, window: Window) -> bool:
        """Learn from one closed grip window (at its temperature, with its
        commanded flow over time); True if it changed the fit."""
        if window.temp_c is None:
            return False
        flow = WindowFlow.of_window(window, self.filament_area_mm2)
        if flow is None:
            return False
        temp_c = float(window.temp_c)
        kept_up = flow.grip >= 1.0 - SLIP_TOLERANCE
        if self.climb_ratio is not None and kept_up:
            # climbing: a window that kept up is a step, not a measurement
            # (kept as one, its peak would hold the fit down after the climb)
            return self._climb(flow.peak_mm3_s, temp_c)
        self.climb_ratio = None       # (a slip measured the hotend: no more climb)
        cap = self.fitted.at(temp_c)
        # what it melted when asked for more (its peak if it kept up whole)
        seen = flow.melted_mm3_s
        if flow.grip >= 1.0 + SLIP_TOLERANCE \
                and flow.peak_mm3_s >= (1.0 - SLIP_TOLERANCE) * cap:
            # at the cap, read over the noise band: the mirror of a window
            # that noise alone reads as a slip (counted, it pulls the fit
            # down), so that the noise pulls it both ways
            seen = flow.over_mm3_s
        elif kept_up and flow.peak_mm3_s <= cap:
            return False  # kept up where the fit said it would: nothing new
        self.observations.append((float(temp_c), float(seen)))
        self.fitted = fit_capacity(self.seed, self.observations,
                                   self.prior_windows, self.capacity_prior_windows)
        return True

    def _climb(self, peak_mm3_s: float, temp_c: float) -> bool:
        """A climb's step for a window that kept up (CLIMB_FROM); True if
        the seed rose."""
        line = self.line.at(temp_c)
        if line <= 0.0:
            return False
        ratio = min(1.0, peak_mm3_s / line * CLIMB_STEP)
        if ratio <= self.climb_ratio:
            return False
        self.climb_ratio = None if ratio >= 1.0 else ratio
        self.seed = self.line.scaled(ratio)
        self.fitted = fit_capacity(self.seed, self.observations,
                                   self.prior_windows, self.capacity_prior_windows)
        return True

    def cap_mm3_s(self, temp_c: float) -> float:
        """The flow at which the feeder is predicted to start slipping."""
        return self.fitted.at(temp_c)

    def ratio_to(self, line: CapacityLine) -> float:
        """The fitted capacity against `line` at the seed's temperature."""
        ref = self.seed.ref_temp_c
        return self.fitted.at(ref) / line.at(ref)

    def status(self) -> Dict[str, Any]:
        f = self.fitted
        return {"ref_temp_c": round(f.ref_temp_c, 2),
                "capacity_mm3_s": round(f.capacity_mm3_s, 4),
                "slope_mm3_s_per_c": round(f.slope_mm3_s_per_c, 5),
                "windows": len(self.observations),
                "climb_ratio": None if self.climb_ratio is None
                else round(self.climb_ratio, 4)}


def fit_capacity(seed: CapacityLine, observations, prior_windows: float
                 = DEFAULT_PRIOR_WINDOWS, capacity_prior_windows: float
                 = DEFAULT_CAPACITY_PRIOR_WINDOWS) -> CapacityLine:
    """Least squares C(T) through (temp_c, capacity) points, pulled toward seed.

    Minimises sum (c_i - a - b (T_i - T_ref))^2 + wa (a - a0)^2
    + w S^2 (b - b0)^2, with wa = capacity_prior_windows,
    w = prior_windows, S = PRIOR_SPAN_C.
    """
    ref = seed.ref_temp_c
    wa = capacity_prior_windows
    wb = prior_windows * PRIOR_SPAN_C ** 2
    # Normal equations of the regularised problem (2x2).
    s00, s01, s11 = wa, 0.0, wb
    r0, r1 = wa * seed.capacity_mm3_s, wb * seed.slope_mm3_s_per_c
    for temp_c, seen in observations:
        x = temp_c - ref
        s00 += 1.0
        s01 += x
        s11 += x * x
        r0 += seen
        r1 += seen * x
    det = s00 * s11 - s01 * s01
    a = (r0 * s11 - r1 * s01) / det
    b = (s00 * r1 - s01 * r0) / det
    return CapacityLine(ref, a, b)
