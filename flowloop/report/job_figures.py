"""A job's figures as Moonraker's job history keeps them: numbers with units
that Mainsail and Fluidd show as they show their own (an auxiliary field
each, provider PROVIDER). Every field holds a value both UIs render from
the job's first moment: a finite number, or NOT_JUDGED where nothing was
measured (no grip judged: no sensor, a job cancelled in its first second;
a nozzle not judged yet). A string or null breaks Mainsail ("NaN", a
TypeError); an empty list is what both render as their own "--" for no
value (they take lists from Moonraker's spoolman field).

A field summed or maximised in the history's totals is always a number:
Moonraker rebuilds its totals at each job's end from the fields holding a
number (History._update_aux_totals, BasicTracker.has_totals), so one job
with a list would drop the field's running total. Its unknown is 0, which
adds nothing to a sum or a maximum.

Mainsail names a history field, adds it as a history column and counts it
in its statistics only when moonraker.conf's parsed configuration holds it
as a `[sensor NAME]` section's `history_field_FIELD` option (desc, units,
parameter) and the field's provider is `sensor NAME`; every other total it
lists under its raw field name with "undefined" units. It shows a total's
sum only (never Moonraker's maximum), and sums every declared field over the
jobs a user selects. So the provider is `sensor flowloop`, the summed
figures are declared as that section would declare them
(mainsail_history_fields), and no figure whose sum means nothing (a lowest
grip, a peak, a ratio) is in the totals or declared: Fluidd shows every
figure as a history column (it takes names from the jobs), Mainsail the
others in a job's details.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, List, Optional, Union

from .recorder import Recorder

# a [sensor] section's name to Mainsail (no such section exists in
# moonraker.conf: see mainsail_history_fields)
PROVIDER = "sensor flowloop"
HISTORY_FIELD_OPTION = "history_field_"

# "--" in Mainsail's job details and Fluidd's history columns, not a number
# that reads as a measurement (100 % grip, a 0 % melt ratio)
NOT_JUDGED: List[float] = []
Figure = Union[float, List[float]]


@dataclass(frozen=True)
class JobFigure:
    """One field of a job's history entry."""

    name: str
    description: str
    units: str
    precision: int
    unknown: Figure              # held until (or unless) it is measured
    report_total: bool = False   # summed over jobs in the history's totals
    # the highest over jobs in Moonraker's totals: Mainsail would show it as
    # a 0 total, so no figure has it (the module's docstring)
    report_maximum: bool = False


UNDER_EXTRUDED = JobFigure("under_extruded", "Filament under-extruded", "mm",
                           2, 0.0, report_total=True)
LOWEST_GRIP = JobFigure("lowest_grip", "Lowest grip", "%", 1, NOT_JUDGED)
# the limiter's time is known without a sensor: a job it never slowed is 0 s
LIMITER_SLOWED = JobFigure("limiter_slowed", "Limiter slowed the print", "s",
                           1, 0.0, report_total=True)
# a peak summed over jobs means nothing, and Mainsail shows no maximum
PEAK_FLOW = JobFigure("peak_flow", "Peak measured flow", "mm³/s", 2, 0.0)
MELT_RATIO = JobFigure("melt_ratio", "Nozzle melt ratio", "%", 1, NOT_JUDGED)
FIGURES = (UNDER_EXTRUDED, LOWEST_GRIP, LIMITER_SLOWED, PEAK_FLOW, MELT_RATIO)


def mainsail_history_fields() -> Dict[str, Dict[str, str]]:
    """The options of a `[sensor flowloop]` section that would declare the
    summed figures (option -> its dict, as Moonraker parses a sensor's
    history_field_* option): in Moonraker's parsed configuration, Mainsail
    shows them as history columns and statistics with their description
    and units."""
    return {HISTORY_FIELD_OPTION + f.name: {"desc": f.description, "units": f.units,
                                            "parameter": f.name}
            for f in FIGURES if f.report_total}


def _number(value: Optional[float], figure: JobFigure) -> Figure:
    if value is None or not math.isfinite(value):
        return figure.unknown
    return round(float(value), figure.precision)


def recorded(rec: Recorder) -> Dict[str, Figure]:
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


def melt_ratio(ratio: Optional[float]) -> Figure:
    """The newest judged melt ratio (capacity against the profile,
    flowloop.control.nozzle_health.newest_ratio; None: no print judged) in
    percent."""
    known = ratio is not None and math.isfinite(ratio)
    return _number(100.0 * ratio if known else None, MELT_RATIO)
