"""Fitting a profile's lines to measured points, with their uncertainty.

A measurement (MEASURE_MATERIAL_PROFILE, into air; or the printed test part)
gives points: the flow at which grip fell to the limit, the hotend
temperature there and the heater power. The profile's lines are straight
(ddPrint's model): flow against temperature (`FlowLine`) and flow against
heater PWM (`PowerLine`). Both are ordinary least squares; the standard
errors of slope and intercept say how far to trust them.

A fit the points do not support is refused with one line (FlowloopError):
fewer than two points, points too close together to give a slope, a slope
that is not positive (a hotend melts more when hotter), or, with three or
more points, a slope less certain than MAX_RELATIVE_SLOPE_ERROR. With
exactly two points the line goes through both and its uncertainty is
unknown (None): the result says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import List, Optional, Sequence

import msgspec

from ..errors import FlowloopError
from .profile import (
    Bounds,
    FlowLine,
    Identity,
    Lines,
    MeasuredPoint,
    PointKind,
    PowerLine,
    Profile,
    Provenance,
)

# A slope known to worse than this (standard error / slope) is refused.
MAX_RELATIVE_SLOPE_ERROR = 0.25
# The least spread of the levels that can give a slope.
MIN_TEMP_SPREAD_C = 5.0
MIN_PWM_SPREAD = 0.05      # as a share of full scale
MIN_POINTS = 2
# A base profile's name as quoted in the provenance note (a note is short).
MAX_NOTE_NAME_CHARS = 60


@dataclass(frozen=True)
class LineFit:
    """flow = slope * x + intercept, fitted to n points (x: degC or PWM)."""
    slope: float
    intercept: float
    slope_stderr: Optional[float]       # None: two points, no estimate
    intercept_stderr: Optional[float]
    rms_residual_mm3_s: float
    n: int
    x_mean: float

    def flow_at(self, x: float) -> float:
        return self.slope * x + self.intercept

    def flow_line(self) -> FlowLine:
        """The profile's FlowLine (x is degC), through the points' centre."""
        return FlowLine(slope_mm3_s_per_c=self.slope, temp_c=self.x_mean,
                        flow_mm3_s=self.flow_at(self.x_mean))

    def power_line(self) -> PowerLine:
        """The profile's PowerLine (x is PWM), through the points' centre."""
        return PowerLine(slope_mm3_s_per_pwm=self.slope, pwm=self.x_mean,
                         flow_mm3_s=self.flow_at(self.x_mean))

    def describe(self, x_unit: str) -> str:
        if self.slope_stderr is None:
            error = "uncertainty unknown (2 points)"
        else:
            error = (f"+/- {self.slope_stderr:.3g} (slope), +/- "
                     f"{self.intercept_stderr:.3g} mm^3/s (intercept)")
        return (f"flow = {self.slope:.4g} mm^3/s per {x_unit} * x "
                f"{'+' if self.intercept >= 0 else '-'} "
                f"{abs(self.intercept):.4g} mm^3/s, {error}, rms residual "
                f"{self.rms_residual_mm3_s:.3g} mm^3/s over {self.n} points")


def fit_line(xs: Sequence[float], flows: Sequence[float], what: str,
             min_spread: float) -> LineFit:
    """Least-squares line of flow against x; refused unless the points
    support it. what: the x in messages ("temperature", "heater power")."""
    n = len(xs)
    if n != len(flows):
        raise FlowloopError(f"{what} fit: {n} {what}s but {len(flows)} flows")
    if n < MIN_POINTS:
        raise FlowloopError(f"{what} fit: needs at least {MIN_POINTS} points, "
                            f"got {n}")
    for value in list(xs) + list(flows):
        if not math.isfinite(value):
            raise FlowloopError(f"{what} fit: the points must be finite numbers,"
                                f" got {value}")
    spread = max(xs) - min(xs)
    if spread < min_spread:
        raise FlowloopError(f"{what} fit: the points span {spread:.3g}, at least "
                            f"{min_spread:g} is needed for a slope")
    x_mean = math.fsum(xs) / n
    y_mean = math.fsum(flows) / n
    sxx = math.fsum((x - x_mean) ** 2 for x in xs)
    sxy = math.fsum((x - x_mean) * (y - y_mean) for x, y in zip(xs, flows))
    slope = sxy / sxx
    intercept = y_mean - slope * x_mean
    residuals = [y - (slope * x + intercept) for x, y in zip(xs, flows)]
    sse = math.fsum(r * r for r in residuals)
    rms = math.sqrt(sse / n)
    if not slope > 0:
        raise FlowloopError(f"{what} fit: the flow does not rise with {what} "
                            f"(slope {slope:.3g}); the points do not give a line")
    slope_err = intercept_err = None
    if n > 2:
        sigma2 = sse / (n - 2)
        slope_err = math.sqrt(sigma2 / sxx)
        intercept_err = math.sqrt(sigma2 * (1.0 / n + x_mean ** 2 / sxx))
        if slope_err > MAX_RELATIVE_SLOPE_ERROR * slope:
            raise FlowloopError(
                f"{what} fit: the slope {slope:.3g} is uncertain by "
                f"{slope_err:.2g} (more than {MAX_RELATIVE_SLOPE_ERROR:.0%}); "
                f"the points scatter too much for a line")
    return LineFit(slope, intercept, slope_err, intercept_err, rms, n, x_mean)


def fit_temperature_line(points: Sequence[MeasuredPoint]) -> LineFit:
    """Flow against hotend temperature (the profile's FlowLine)."""
    return fit_line([p.temp_c for p in points], [p.flow_mm3_s for p in points],
                    "temperature", MIN_TEMP_SPREAD_C)


def fit_power_line(points: Sequence[MeasuredPoint],
                   pwm_max: float = 255.0) -> LineFit:
    """Flow against heater PWM (the profile's PowerLine); every point needs
    its heater_pwm."""
    if any(p.heater_pwm is None for p in points):
        raise FlowloopError("heater power fit: a point has no heater power")
    return fit_line([p.heater_pwm for p in points],
                    [p.flow_mm3_s for p in points], "heater power",
                    MIN_PWM_SPREAD * pwm_max)


@dataclass(frozen=True)
class MeasuredLines:
    """What a measurement gives: the temperature line (always), the power
    line (None when its points do not support one, with the reason)."""
    kind: PointKind
    temperature: LineFit
    power: Optional[LineFit]
    power_refused: str = ""

    def lines(self) -> List[str]:
        out = [f"{self.kind} line: {self.temperature.describe('degC')}"]
        if self.power is not None:
            out.append(f"{self.kind} power line: {self.power.describe('PWM')}")
        else:
            out.append(f"{self.kind} power line not fitted: {self.power_refused}")
        return out


def fit_points(kind: PointKind, points: Sequence[MeasuredPoint],
               pwm_max: float = 255.0) -> MeasuredLines:
    """Both lines of one kind of measurement; refused when the temperature
    line is not supported (the power line is then optional)."""
    chosen = [p for p in points if p.kind == kind]
    temperature = fit_temperature_line(chosen)
    try:
        power, refused = fit_power_line(chosen, pwm_max), ""
    except FlowloopError as e:
        power, refused = None, str(e)
    return MeasuredLines(kind, temperature, power, refused)


def one_point_lines(kind: PointKind, point: MeasuredPoint,
                    slope_mm3_s_per_c: float) -> MeasuredLines:
    """A line from one point with a known slope (ddPrint's real-print
    line: its slope is the into-air line's)."""
    if not slope_mm3_s_per_c > 0:
        raise FlowloopError(f"{kind} line: the slope {slope_mm3_s_per_c:g} "
                            f"must be above 0")
    intercept = point.flow_mm3_s - slope_mm3_s_per_c * point.temp_c
    temperature = LineFit(slope_mm3_s_per_c, intercept, None, None, 0.0, 1,
                          point.temp_c)
    return MeasuredLines(kind, temperature, None,
                         "one point: no power line")


def measured_profile(name: str, base: Optional[Profile], fitted: MeasuredLines,
                     points: Sequence[MeasuredPoint], bounds: Bounds,
                     nozzle_diameter_mm: float, filament_diameter_mm: float,
                     min_grip: float, source: str,
                     measured_at: Optional[str] = None) -> Profile:
    """The profile a measurement stores: the fitted lines of its kind, the
    base profile's other line (or, with no base, the same line, noted), the
    base's earlier points of the other kind plus the new points."""
    line = fitted.temperature.flow_line()
    if base is not None:
        identity = msgspec.structs.replace(base.identity, name=name)
        other = (base.lines.real_print if fitted.kind == "into_air"
                 else base.lines.into_air)
        other_power = (base.lines.real_print_power if fitted.kind == "into_air"
                       else base.lines.into_air_power)
        kept = [p for p in base.points if p.kind != fitted.kind]
        note = (f"{fitted.kind} measured; the other line from "
                f"'{base.name[:MAX_NOTE_NAME_CHARS]}'")
    else:
        identity = Identity(name=name, nozzle_diameter_mm=nozzle_diameter_mm,
                            filament_diameter_mm=filament_diameter_mm)
        other, other_power, kept = line, None, []
        note = (f"{fitted.kind} measured; the other line is not measured "
                f"(a copy of this one)")
    power = None if fitted.power is None else fitted.power.power_line()
    if fitted.kind == "into_air":
        lines = Lines(into_air=line, real_print=other, into_air_power=power,
                      real_print_power=other_power)
    else:
        lines = Lines(into_air=other, real_print=line, into_air_power=other_power,
                      real_print_power=power)
    when = measured_at or datetime.now(timezone.utc).strftime(
        "%Y-%m-%dT%H:%M:%SZ")
    err = fitted.temperature.slope_stderr
    if fitted.temperature.n == 1:
        note += "; one point, the slope is the other line's"
    else:
        note += ("; slope uncertainty unknown (2 points)" if err is None
                 else f"; slope +/- {err:.3g} mm^3/s per degC")
    return Profile(identity=identity, lines=lines, bounds=bounds,
                   points=kept + list(points),
                   provenance=Provenance(method=fitted.kind, measured_at=when,
                                         source=source, min_grip=min_grip,
                                         note=note))
