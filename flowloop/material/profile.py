"""Material profiles: how much melt flow a hotend delivers at each temperature.

A profile holds two straight lines measured with the flow sensor (ddPrint's
model): "into air" (the best case, extruding into air) and "real print" (the
worst case, printing a hard part). A working point WP in 0..1 picks a line
between them: 0 is the real-print line (hotter, stronger parts), 1 the
into-air line (cooler, nicer surfaces), 0.5 the default.

Everything here is pure: the schema (versioned, strict, msgspec), its
validation, and the functions over the two lines that autotemp, the limiters
and the measurement commands use:

- `profile_line(profile, wp)` / `working_line(into_air, real_print, wp)` -> the
  `Line` at WP, the one melt line everything uses (`Line.flow_mm3_s(temp_c)`,
  `Line.temp_c(flow_mm3_s)`),
- `flow_at(profile, temp_c, wp)`, `temp_for_flow(profile, flow, wp)` (clamped
  to the profile's bounds), `max_flow_at(profile, measured_temp_c, wp)`,
- `capped_to_heater(profile, heater_max_temp_c)`: bounds within a heater's
  max_temp, for klippy to keep,
- `line_warnings(profile)`: what is implausible about the two lines. Real
  ddPrint files have a real-print line above the into-air line; such a profile
  is kept as it is, and no working line ever gives more flow than the into-air
  line (there, the lower of the two), which is the conservative side for
  autotemp (hotter) and the limiters (slower).
"""

from __future__ import annotations

import math
import re
import unicodedata
from typing import Any, Dict, List, Literal, NamedTuple, Optional, Union

import msgspec

from .. import __version__
from ..errors import FlowloopError

SCHEMA_VERSION = 1
DEFAULT_WORKING_POINT = 0.5
MIN_TEMP_C = 0.0
MAX_TEMP_C = 500.0
# more than any hotend melts: the bound of every flow a command is given
MAX_FLOW_MM3_S = 1000.0
MAX_NAME_CHARS = 128
MAX_TEXT_CHARS = 256
# Size limits: validation, encoding and storage stay cheap (Moonraker and
# klippy validate on their event loops). A measurement has tens of points.
MAX_POINTS = 1000
MAX_DDPRINT_NUMBERS = 256
# Characters XML 1.0 cannot carry even escaped; names end up in SVG plots.
NON_XML_CHARS = "\ufffe\uffff"
# Sanity limits far beyond any hotend (real ones: ~0.1-0.2 and < 100).
MAX_SLOPE_MM3_S_PER_C = 10.0
MAX_FLOW_MM3_S = 1000.0
# Two lines closer than this (mm^3/s) count as touching, not crossing.
LINE_TOLERANCE_MM3_S = 1e-9

Number = Union[int, float]
PointKind = Literal["into_air", "real_print"]
Method = Literal["ddprint_import", "into_air", "real_print", "manual"]


class _Strict(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    pass


class FlowLine(_Strict, kw_only=True):
    """flow = slope * (temp - temp_c) + flow_mm3_s: a slope through a point."""

    slope_mm3_s_per_c: float
    temp_c: float
    flow_mm3_s: float

    def line(self) -> Line:
        return Line.through(self.slope_mm3_s_per_c, self.temp_c, self.flow_mm3_s)


class PowerLine(_Strict, kw_only=True):
    """The same melt flow against heater PWM (ddPrint's "energy" view)."""

    slope_mm3_s_per_pwm: float
    pwm: float
    flow_mm3_s: float


class Lines(_Strict, kw_only=True):
    into_air: FlowLine
    real_print: FlowLine
    into_air_power: Optional[PowerLine] = None
    real_print_power: Optional[PowerLine] = None
    # Full scale of the PWM numbers above (ddPrint: 255).
    pwm_max: float = 255.0


class Identity(_Strict, kw_only=True):
    name: str
    printer: str = ""
    nozzle_diameter_mm: float
    filament_name: str = ""
    filament_vendor: str = ""
    filament_type: str = ""
    filament_diameter_mm: float = 1.75
    spoolman_filament_id: Optional[int] = None


class Bounds(_Strict, kw_only=True):
    min_temp_c: float
    recommended_temp_c: float
    max_temp_c: float


class MeasuredPoint(_Strict, kw_only=True):
    """One raw measurement: the flow at which grip fell to the limit."""

    kind: PointKind
    temp_c: float
    flow_mm3_s: float
    grip: float
    heater_pwm: Optional[float] = None


class Provenance(_Strict, kw_only=True):
    method: Method
    measured_at: str = ""
    flowloop_version: str = __version__
    source: str = ""
    min_grip: Optional[float] = None
    note: str = ""


class DdprintExtras(_Strict, kw_only=True):
    """Numbers from a ddPrint file that flowloop does not use, kept for export."""

    top: Dict[str, Number] = {}
    nozzle: Dict[str, Number] = {}


class Profile(_Strict, kw_only=True):
    schema_version: int = SCHEMA_VERSION
    identity: Identity
    lines: Lines
    bounds: Bounds
    points: List[MeasuredPoint] = []
    provenance: Provenance
    ddprint: Optional[DdprintExtras] = None

    def __post_init__(self) -> None:
        check_profile(self)

    @property
    def name(self) -> str:
        return self.identity.name


class Line(NamedTuple):
    """Melt capacity against hotend temperature: flow = slope * temp +
    intercept, held at or below `ceiling` (another Line) when one is set, and
    never below 0. The one melt line of flowloop: autotemp, the limiters, the
    plots and the simulated twin all ask a Line (`profile_line`)."""

    slope_mm3_s_per_c: float
    intercept_mm3_s: float
    ceiling: Optional[Line] = None

    @classmethod
    def through(cls, slope_mm3_s_per_c: float, temp_c: float,
                flow_mm3_s: float) -> Line:
        """The line with this slope through (temp_c, flow_mm3_s)."""
        return cls(slope_mm3_s_per_c, flow_mm3_s - slope_mm3_s_per_c * temp_c)

    def flow_mm3_s(self, temp_c: float) -> float:
        """The most flow (mm^3/s) the hotend melts at temp_c; 0 below the zero."""
        flow = self.slope_mm3_s_per_c * temp_c + self.intercept_mm3_s
        if self.ceiling is not None:
            flow = min(flow, self.ceiling.flow_mm3_s(temp_c))
        return max(0.0, flow)

    def temp_c(self, flow_mm3_s: float) -> float:
        """The lowest temperature at which the hotend melts flow_mm3_s."""
        temp = (flow_mm3_s - self.intercept_mm3_s) / self.slope_mm3_s_per_c
        if self.ceiling is not None:
            temp = max(temp, self.ceiling.temp_c(flow_mm3_s))
        return temp

    def knee_temp_c(self) -> Optional[float]:
        """Where the line meets its ceiling (None: no ceiling, or parallel)."""
        if self.ceiling is None:
            return None
        slope_gap = self.slope_mm3_s_per_c - self.ceiling.slope_mm3_s_per_c
        if slope_gap == 0:
            return None
        return (self.ceiling.intercept_mm3_s - self.intercept_mm3_s) / slope_gap

    def to_dict(self) -> Dict[str, Any]:
        """JSON-able: slope, intercept and the ceiling's (or None)."""
        return {"slope_mm3_s_per_c": self.slope_mm3_s_per_c,
                "intercept_mm3_s": self.intercept_mm3_s,
                "ceiling": None if self.ceiling is None else self.ceiling.to_dict()}

    @classmethod
    def from_dict(cls, data: Dict[str, Any]) -> Line:
        ceiling = data.get("ceiling")
        return cls(data["slope_mm3_s_per_c"], data["intercept_mm3_s"],
                   None if ceiling is None else cls.from_dict(ceiling))


# ---------------------------------------------------------------------------
# Validation


# The grip below which the feeder is taken to slip, where neither the user
# nor the profile's measurement says otherwise.
DEFAULT_MIN_GRIP = 0.9


def min_grip_of(profile: Optional[Profile],
                override: Optional[float] = None) -> float:
    """The min grip that applies: the user's (a MIN_GRIP or config value),
    else the one the profile was measured with, else DEFAULT_MIN_GRIP."""
    if override is not None:
        return override
    if profile is not None and profile.provenance.min_grip:
        return profile.provenance.min_grip
    return DEFAULT_MIN_GRIP


def _bad(msg: str) -> FlowloopError:
    return FlowloopError(msg)


def _walk_numbers(obj: Any, path: str):
    if isinstance(obj, msgspec.Struct):
        for field in obj.__struct_fields__:
            yield from _walk_numbers(getattr(obj, field), f"{path}.{field}")
    elif isinstance(obj, dict):
        for key, val in obj.items():
            yield from _walk_numbers(val, f"{path}.{key}")
    elif isinstance(obj, (list, tuple)):
        for i, val in enumerate(obj):
            yield from _walk_numbers(val, f"{path}[{i}]")
    elif isinstance(obj, float):
        yield path, obj


def _walk_strings(obj: Any, path: str):
    if isinstance(obj, msgspec.Struct):
        for field in obj.__struct_fields__:
            yield from _walk_strings(getattr(obj, field), f"{path}.{field}")
    elif isinstance(obj, dict):
        for key in obj:
            yield f"{path} key", key
    elif isinstance(obj, str):
        yield path, obj


def check_text(value: str, what: str, limit: int = MAX_TEXT_CHARS) -> str:
    """One line of printable text: no control characters or line breaks."""
    if len(value) > limit:
        raise _bad(f"{what} is longer than {limit} characters")
    for ch in value:
        if unicodedata.category(ch) in ("Cc", "Cs", "Zl", "Zp") \
                or ch in NON_XML_CHARS:
            raise _bad(f"{what} contains the control character {ch!r}; "
                       f"use one line of printable text")
    return value


def check_name(name: str) -> str:
    """A profile name: free text on one line, not blank, shown as it is.

    Leading or trailing whitespace is refused (an HTTP query strips it, so
    such a name could be stored but never found), and so are invisible format
    characters (Unicode Cf: U+200B, the bidirectional overrides U+202E,
    U+2066..U+2069, ...), which can make one name display as another.
    """
    if not isinstance(name, str):
        raise _bad("profile name must be a string")
    if not name.strip():
        raise _bad("profile name is empty")
    if name != name.strip():
        raise _bad(f"profile name {name[:MAX_NAME_CHARS]!r} begins or ends with "
                   f"whitespace; remove it")
    for ch in name:
        if unicodedata.category(ch) == "Cf":
            raise _bad(f"profile name contains the invisible format character "
                       f"U+{ord(ch):04X}; use visible text")
    return check_text(name, "profile name", MAX_NAME_CHARS)


def is_extruder_name(name: Any) -> bool:
    """Klipper's extruder sections: extruder, extruder1, extruder2, ..."""
    return isinstance(name, str) and re.fullmatch(r"extruder\d*", name) is not None


def check_working_point(wp: float) -> float:
    if isinstance(wp, bool) or not isinstance(wp, (int, float)):
        raise _bad(f"working point must be a number in 0..1, got {wp!r}")
    if not 0.0 <= wp <= 1.0:  # also refuses NaN
        raise _bad(f"working point must be in 0..1, got {wp}")
    return float(wp)


def _check_range(path: str, value: float, lo: float, hi: float) -> None:
    if not lo <= value <= hi:
        raise _bad(f"{path} must be in {lo:g}..{hi:g}, got {value:g}")


def _check_positive(path: str, value: float) -> None:
    if not value > 0:
        raise _bad(f"{path} must be > 0, got {value:g}")


def check_profile(p: Profile) -> None:
    """Raise FlowloopError (one line) unless the profile is usable."""
    if p.schema_version != SCHEMA_VERSION:
        raise _bad(f"schema_version {p.schema_version} is not supported "
                   f"(this flowloop {__version__} reads {SCHEMA_VERSION})")
    if len(p.points) > MAX_POINTS:
        raise _bad(f"points has {len(p.points)} entries, at most {MAX_POINTS}")
    if p.ddprint is not None:
        for part in ("top", "nozzle"):
            if len(getattr(p.ddprint, part)) > MAX_DDPRINT_NUMBERS:
                raise _bad(f"ddprint.{part} has more than {MAX_DDPRINT_NUMBERS} "
                           f"entries")
    for path, value in _walk_numbers(p, "profile"):
        if not math.isfinite(value):
            raise _bad(f"{path[len('profile.'):]} must be a finite number, got {value}")
    check_name(p.identity.name)
    for path, value in _walk_strings(p, "profile"):
        check_text(value, path[len("profile."):])
    ident = p.identity
    _check_range("identity.nozzle_diameter_mm", ident.nozzle_diameter_mm, 0.05, 5.0)
    _check_range("identity.filament_diameter_mm", ident.filament_diameter_mm,
                 0.5, 5.0)
    if ident.spoolman_filament_id is not None and ident.spoolman_filament_id < 1:
        raise _bad("identity.spoolman_filament_id must be >= 1, "
                   f"got {ident.spoolman_filament_id}")
    b = p.bounds
    for field in ("min_temp_c", "recommended_temp_c", "max_temp_c"):
        _check_range(f"bounds.{field}", getattr(b, field), MIN_TEMP_C, MAX_TEMP_C)
    if not b.min_temp_c < b.max_temp_c:
        raise _bad(f"bounds.min_temp_c ({b.min_temp_c:g}) must be below "
                   f"bounds.max_temp_c ({b.max_temp_c:g})")
    if not b.min_temp_c <= b.recommended_temp_c <= b.max_temp_c:
        raise _bad(f"bounds.recommended_temp_c ({b.recommended_temp_c:g}) must be "
                   f"within {b.min_temp_c:g}..{b.max_temp_c:g}")
    lines = p.lines
    _check_positive("lines.pwm_max", lines.pwm_max)
    for name in ("into_air", "real_print"):
        line: FlowLine = getattr(lines, name)
        _check_positive(f"lines.{name}.slope_mm3_s_per_c", line.slope_mm3_s_per_c)
        if line.slope_mm3_s_per_c > MAX_SLOPE_MM3_S_PER_C:
            raise _bad(f"lines.{name}.slope_mm3_s_per_c must be <= "
                       f"{MAX_SLOPE_MM3_S_PER_C:g}, got {line.slope_mm3_s_per_c:g}")
        _check_range(f"lines.{name}.temp_c", line.temp_c, MIN_TEMP_C, MAX_TEMP_C)
        _check_range(f"lines.{name}.flow_mm3_s", line.flow_mm3_s, 0.0, MAX_FLOW_MM3_S)
        power: Optional[PowerLine] = getattr(lines, f"{name}_power")
        if power is not None:
            _check_positive(f"lines.{name}_power.slope_mm3_s_per_pwm",
                            power.slope_mm3_s_per_pwm)
            _check_range(f"lines.{name}_power.flow_mm3_s", power.flow_mm3_s, 0.0,
                         MAX_FLOW_MM3_S)
            _check_range(f"lines.{name}_power.pwm", power.pwm, 0.0, lines.pwm_max)
    for i, point in enumerate(p.points):
        where = f"points[{i}]"
        _check_range(f"{where}.temp_c", point.temp_c, MIN_TEMP_C, MAX_TEMP_C)
        _check_range(f"{where}.flow_mm3_s", point.flow_mm3_s, 0.0, MAX_FLOW_MM3_S)
        _check_range(f"{where}.grip", point.grip, 0.0, 2.0)
        if point.heater_pwm is not None:
            _check_range(f"{where}.heater_pwm", point.heater_pwm, 0.0, lines.pwm_max)
    if p.provenance.min_grip is not None:
        _check_range("provenance.min_grip", p.provenance.min_grip, 0.0, 1.0)


def line_warnings(profile: Profile) -> List[str]:
    """What is implausible about the two lines, one line each (none: []).

    Real print should need more heat than into air, so the real-print line
    should lie below the into-air line over the bounds. Real ddPrint files do
    not always (measurement scatter); they are kept and used as they are, and
    `working_line` then holds every working point at the into-air line.
    """
    b = profile.bounds
    air = profile.lines.into_air.line()
    real = profile.lines.real_print.line()
    gaps = [(air.flow_mm3_s(t) - real.flow_mm3_s(t), t)
            for t in (b.min_temp_c, b.max_temp_c)]
    below = [(gap, t) for gap, t in gaps if gap < -LINE_TOLERANCE_MM3_S]
    if not below:
        return []
    used = "every working point uses the into-air line (the lower one)"
    if len(below) == 2:
        gap, temp = min(below)
        return [f"the real-print line lies above the into-air line (by {-gap:.3g} "
                f"mm^3/s at {temp:g} degC; real print should need more heat): "
                f"{used}"]
    slope_gap = air.slope_mm3_s_per_c - real.slope_mm3_s_per_c
    cross_c = (real.intercept_mm3_s - air.intercept_mm3_s) / slope_gap
    side = "below" if below[0][1] == b.min_temp_c else "above"
    return [f"the into-air and real-print lines cross at {cross_c:.1f} degC, "
            f"inside the bounds {b.min_temp_c:g}..{b.max_temp_c:g} degC: {side} "
            f"it the real-print line lies above and {used}"]


# ---------------------------------------------------------------------------
# Encoding


_AT_PATH = re.compile(r" - at `\$\.?([^`]*)`$")


def _one_line(err: Exception) -> str:
    msg = str(err).splitlines()[0] if str(err) else type(err).__name__
    return _AT_PATH.sub(lambda m: f" (at {m.group(1) or 'top level'})", msg)


def profile_from_dict(obj: Any) -> Profile:
    """A validated Profile from decoded JSON (dicts, lists, numbers, strings)."""
    if not isinstance(obj, dict):
        raise _bad(f"a profile must be a JSON object, got {type(obj).__name__}")
    try:
        return msgspec.convert(obj, Profile)
    except msgspec.ValidationError as e:
        raise _bad(f"invalid profile: {_one_line(e)}") from None


def decode_profile(data: Union[bytes, str]) -> Profile:
    """A validated Profile from JSON text."""
    if not data.strip():    # msgspec would say "Input data was truncated"
        raise _bad("empty: no profile in it")
    try:
        return msgspec.json.decode(data, type=Profile)
    except msgspec.ValidationError as e:
        raise _bad(f"invalid profile: {_one_line(e)}") from None
    except msgspec.DecodeError as e:
        raise _bad(f"not a JSON profile: {_one_line(e)}") from None


def profile_to_dict(profile: Profile) -> Dict[str, Any]:
    return msgspec.to_builtins(profile)


def encode_profile(profile: Profile, indent: int = 2) -> bytes:
    data = msgspec.json.encode(profile)
    return msgspec.json.format(data, indent=indent) + b"\n" if indent else data


def summary(profile: Profile) -> Dict[str, Any]:
    """The identity fields and a few facts, for lists."""
    out = msgspec.to_builtins(profile.identity)
    out["method"] = profile.provenance.method
    out["measured_at"] = profile.provenance.measured_at
    out["min_temp_c"] = profile.bounds.min_temp_c
    out["max_temp_c"] = profile.bounds.max_temp_c
    out["warnings"] = line_warnings(profile)
    return out


# ---------------------------------------------------------------------------
# The functions over the two lines


def working_line(into_air: FlowLine, real_print: FlowLine,
                 working_point: float = DEFAULT_WORKING_POINT) -> Line:
    """The line at WP: 0 = real print, 1 = into air, linear in between, and
    never above the into-air line (the best case): where the real-print line
    lies above it, every WP uses the into-air line, the lower of the two."""
    wp = check_working_point(working_point)
    air, real = into_air.line(), real_print.line()
    line = Line(
        real.slope_mm3_s_per_c + wp * (air.slope_mm3_s_per_c - real.slope_mm3_s_per_c),
        real.intercept_mm3_s + wp * (air.intercept_mm3_s - real.intercept_mm3_s))
    if wp == 1.0 or (line.slope_mm3_s_per_c == air.slope_mm3_s_per_c
                     and line.intercept_mm3_s <= air.intercept_mm3_s):
        return line  # nowhere above the into-air line
    return line._replace(ceiling=air)


def profile_line(profile: Profile,
                 working_point: float = DEFAULT_WORKING_POINT) -> Line:
    """The profile's melt line at a working point (see `working_line`)."""
    return working_line(profile.lines.into_air, profile.lines.real_print,
                        working_point)


def _finite(value: float, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value):
        raise _bad(f"{what} must be a finite number, got {value!r}")
    return float(value)


def flow_at(profile: Profile, temp_c: float,
            working_point: float = DEFAULT_WORKING_POINT) -> float:
    """Melt flow (mm^3/s) the WP line gives at temp_c; never below 0."""
    temp_c = _finite(temp_c, "temperature")
    return profile_line(profile, working_point).flow_mm3_s(temp_c)


def temp_for_flow(profile: Profile, flow_mm3_s: float,
                  working_point: float = DEFAULT_WORKING_POINT) -> float:
    """Hotend temperature for a flow at WP, clamped to min..max_temp_c."""
    flow_mm3_s = _finite(flow_mm3_s, "flow")
    if flow_mm3_s < 0:
        raise _bad(f"flow must be >= 0 mm^3/s, got {flow_mm3_s:g}")
    temp = profile_line(profile, working_point).temp_c(flow_mm3_s)
    b = profile.bounds
    return min(b.max_temp_c, max(b.min_temp_c, temp))


def max_flow_at(profile: Profile, measured_temp_c: float,
                working_point: float = DEFAULT_WORKING_POINT) -> float:
    """The most flow the hotend melts at a measured temperature (for limiters).

    Above max_temp_c the line is not trusted: the flow there is capped at the
    flow at max_temp_c. Below the line's zero the answer is 0.
    """
    temp = min(_finite(measured_temp_c, "temperature"), profile.bounds.max_temp_c)
    return profile_line(profile, working_point).flow_mm3_s(temp)


def capped_to_heater(profile: Profile, heater_max_temp_c: float) -> Profile:
    """The profile with its bounds capped at a heater's max_temp, so that
    temp_for_flow never asks for more than the heater allows; refused when
    the heater cannot reach the profile's min_temp_c."""
    b = profile.bounds
    cap = _finite(heater_max_temp_c, "heater max_temp")
    if cap >= b.max_temp_c:
        return profile
    if cap <= b.min_temp_c:
        raise _bad(f"the heater's max_temp {cap:g} degC is not above the profile's "
                   f"min_temp_c {b.min_temp_c:g} degC")
    return msgspec.structs.replace(profile, bounds=msgspec.structs.replace(
        b, max_temp_c=cap, recommended_temp_c=min(b.recommended_temp_c, cap)))


def active_status(profile: Profile, working_point: float) -> Dict[str, Any]:
    """The small JSON-able view klippy shows for an active profile."""
    line = profile_line(profile, working_point)

    def flow_line(fl: FlowLine) -> Dict[str, float]:
        return {"slope_mm3_s_per_c": fl.slope_mm3_s_per_c, "temp_c": fl.temp_c,
                "flow_mm3_s": fl.flow_mm3_s}

    b = profile.bounds
    return {
        "name": profile.identity.name,
        "working_point": working_point,
        "into_air": flow_line(profile.lines.into_air),
        "real_print": flow_line(profile.lines.real_print),
        "working_line": line.to_dict(),
        "warnings": line_warnings(profile),
        "min_temp_c": b.min_temp_c,
        "recommended_temp_c": b.recommended_temp_c,
        "max_temp_c": b.max_temp_c,
    }
