"""The predictive grip model: grip as a function of flow and temperature.

Above its melt capacity C(T) a hotend passes only C(T) of the flow it is
asked for, so the feeder slips: predicted grip(F, T) = min(1, C(T) / F).
C is a straight line in temperature, C(T) = capacity_mm3_s + slope *
(T - ref_temp_c). It is seeded from the active profile: the profile's line
at the working point is where grip fell to the profile's min_grip, so
C = that line * min_grip (one melt line, flowloop.material's).

It is updated online from the sensor's grip windows: a window that slipped
measured C directly (the measured flow); a window that did not slip at a
flow above C shows C is at least that flow. The fit is least squares over
the most recent windows, pulled toward the seed (a prior worth
`prior_windows` windows on the capacity and a temperature span of
`PRIOR_SPAN_C` on the slope), so a few windows at one temperature move the
capacity but not the slope.

The predictive cap is C(T), the flow at which the model predicts the feeder
starts to slip: it acts before grip falls, where the reactive rule (and
min_grip, its threshold) acts after. Capping at C / min_grip instead would
run every capped move at grip min_grip, under-extruding by design.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass
from typing import Any, Deque, Dict, Optional, Tuple

from ..errors import FlowloopError
from ..material.profile import Line

# A window at grip >= 1 - SLIP_TOLERANCE did not slip (sensor noise).
SLIP_TOLERANCE = 0.02
MAX_OBSERVATIONS = 200
DEFAULT_PRIOR_WINDOWS = 5.0
PRIOR_SPAN_C = 20.0


@dataclass(frozen=True)
class CapacityLine:
    """C(T) = capacity_mm3_s + slope_mm3_s_per_c * (T - ref_temp_c)."""

    ref_temp_c: float
    capacity_mm3_s: float
    slope_mm3_s_per_c: float

    def at(self, temp_c: float) -> float:
        return max(0.0, self.capacity_mm3_s
                   + self.slope_mm3_s_per_c * (temp_c - self.ref_temp_c))

    @classmethod
    def from_profile_line(cls, line: Line, grip: float,
                          ref_temp_c: float) -> CapacityLine:
        """The melt capacity under a profile's line measured at `grip`, as
        the line's tangent at ref_temp_c (the Line may bend at a ceiling)."""
        half = PRIOR_SPAN_C / 2.0
        slope = (line.flow_mm3_s(ref_temp_c + half)
                 - line.flow_mm3_s(ref_temp_c - half)) / (2.0 * half)
        return cls(ref_temp_c, grip * line.flow_mm3_s(ref_temp_c), grip * slope)


def predicted_grip(capacity: CapacityLine, flow_mm3_s: float,
                   temp_c: float) -> float:
    if flow_mm3_s <= 0.0:
        return 1.0
    return min(1.0, capacity.at(temp_c) / flow_mm3_s)


class GripModel:
    def __init__(self, seed: CapacityLine,
                 prior_windows: float = DEFAULT_PRIOR_WINDOWS):
        if prior_windows <= 0:
            raise FlowloopError(f"prior_windows must be above 0, not {prior_windows}")
        self.seed = seed
        self.fitted = seed
        self.prior_windows = prior_windows
        # (temp_c, capacity seen) per informative window
        self.observations: Deque[Tuple[float, float]] = collections.deque(
            maxlen=MAX_OBSERVATIONS)

    def add_window(self, commanded_flow_mm3_s: float, grip: Optional[float],
                   temp_c: Optional[float]) -> bool:
        """Learn from one closed window; True if it changed the fit."""
        if grip is None or temp_c is None or commanded_flow_mm3_s <= 0.0:
            return False
        if grip < 1.0 - SLIP_TOLERANCE:
            seen = grip * commanded_flow_mm3_s
        elif commanded_flow_mm3_s > self.fitted.at(temp_c):
            seen = commanded_flow_mm3_s  # a lower bound: it kept up
        else:
            return False
        self.observations.append((float(temp_c), float(seen)))
        self.fitted = fit_capacity(self.seed, self.observations, self.prior_windows)
        return True

    def cap_mm3_s(self, temp_c: float) -> float:
        """The flow at which the feeder is predicted to start slipping."""
        return self.fitted.at(temp_c)

    def status(self) -> Dict[str, Any]:
        f = self.fitted
        return {"ref_temp_c": round(f.ref_temp_c, 2),
                "capacity_mm3_s": round(f.capacity_mm3_s, 4),
                "slope_mm3_s_per_c": round(f.slope_mm3_s_per_c, 5),
                "windows": len(self.observations)}


def fit_capacity(seed: CapacityLine, observations, prior_windows: float
                 = DEFAULT_PRIOR_WINDOWS) -> CapacityLine:
    """Least squares C(T) through (temp_c, capacity) points, pulled toward seed.

    Minimises sum (c_i - a - b (T_i - T_ref))^2 + w (a - a0)^2
    + w S^2 (b - b0)^2, with w = prior_windows, S = PRIOR_SPAN_C.
    """
    ref = seed.ref_temp_c
    w = prior_windows
    wb = w * PRIOR_SPAN_C ** 2
    # Normal equations of the regularised problem (2x2).
    s00, s01, s11 = w, 0.0, wb
    r0, r1 = w * seed.capacity_mm3_s, wb * seed.slope_mm3_s_per_c
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
