"""A job's figures as Moonraker's job history keeps them: numbers with units
that Mainsail and Fluidd show as they show their own (an auxiliary field
each, provider `flowloop`). Every field holds a finite number from the job's
first moment: a UI renders each value as a number, a string or null breaks
it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Optional, Sequence

from .recorder import Recorder


@dataclass(frozen=True)
class JobFigure:
    """One field of a job's history entry."""

    name: str
    description: str
    units: str
    precision: int
    unknown: float               # held until (or unless) it is measured
    report_total: bool = False   # summed over jobs in the history's totals
    report_maximum: bool = False  # the highest over jobs in the totals


UNDER_EXTRUDED = JobFigure("under_extruded", "Filament under-extruded", "mm",
                           2, 0.0, report_total=True)
# no judged grip (no sensor, faulted throughout): full grip, nothing seen lost
LOWEST_GRIP = JobFigure("lowest_grip", "Lowest grip", "%", 1, 100.0)
LIMITER_SLOWED = JobFigure("limiter_slowed", "Limiter slowed the print", "s",
                           1, 0.0, report_total=True)
PEAK_FLOW = JobFigure("peak_flow", "Peak measured flow", "mm³/s", 2, 0.0,
                      report_maximum=True)
# the nozzle not judged yet for the profile that prints: 0
MELT_RATIO = JobFigure("melt_ratio", "Nozzle melt ratio", "%", 1, 0.0)
FIGURES = (UNDER_EXTRUDED, LOWEST_GRIP, LIMITER_SLOWED, PEAK_FLOW, MELT_RATIO)


def _number(value: Optional[float], figure: JobFigure) -> float:
    if value is None or not math.isfinite(value):
        return figure.unknown
    return round(float(value), figure.precision)


def recorded(rec: Recorder) -> Dict[str, float]:
    """The figures the flow report's recorder knows so far."""
    grip = rec.bins.extreme("grip", "min")
    return {
        UNDER_EXTRUDED.name: _number(rec.under_mm, UNDER_EXTRUDED),
        LOWEST_GRIP.name: _number(None if grip is None else 100.0 * max(0.0, grip),
                                  LOWEST_GRIP),
        LIMITER_SLOWED.name: _number(sum(rec.slowdown_by_reason().values()),
                                     LIMITER_SLOWED),
        PEAK_FLOW.name: _number(
            max(0.0, rec.bins.extreme("measured_flow", "max") or 0.0), PEAK_FLOW),
    }


def melt_ratio(ratios: Sequence[Optional[float]]) -> float:
    """The newest judged melt ratio (capacity against the profile, oldest
    first, None where a print gave no estimate) in percent."""
    known = [r for r in ratios if r is not None and math.isfinite(r)]
    return _number(100.0 * known[-1] if known else None, MELT_RATIO)
