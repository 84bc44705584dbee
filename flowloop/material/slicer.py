"""Slicer filament settings from a material profile: the flow the hotend
really melts, as the number a slicer limits its speeds with.

For a temperature and a working point, `slicer_numbers` gives what a slicer's
filament preset holds: the nozzle temperature and the first layer's (whole
degrees, as the slicers store them, within the profile's bounds), the max
volumetric speed (mm^3/s: the profile's melt line at that temperature, rounded
down to 0.01 so a slicer never plans more than the hotend melts), the
filament diameter and a note naming the profile, the working point and this
flowloop. `prusaslicer_ini` and `orcaslicer_json` write them in each slicer's
own format; `export_text` picks one by name.

The key names, units and types are the slicers' own (PrusaSlicer
src/libslic3r/PrintConfig.cpp; OrcaSlicer's PrintConfig.cpp and its
resources/profiles/*/filament/*.json; see docs/material_profiles.md):

* PrusaSlicer / SuperSlicer, a filament `.ini` (File > Import > Import
  Config): `key = value` lines; `temperature` and `first_layer_temperature`
  are integers (degC; 0 would switch temperature control off),
  `filament_max_volumetric_speed` mm^3/s (0 would mean no limit),
  `filament_diameter` mm, `filament_notes` a quoted C-style string.
* OrcaSlicer, a filament preset `.json`: every value a list of strings
  (`"nozzle_temperature": ["215"]`), with `type`, `name`, `from`,
  `inherits`, `instantiation`, `version` and `filament_settings_id` naming
  the preset (its import needs `name`, a `version` and
  `filament_settings_id`, which says it is a filament preset).
"""

from __future__ import annotations

import json
import math
from typing import Dict, NamedTuple, Optional

from .. import __version__
from ..errors import FlowloopError
from .profile import DEFAULT_WORKING_POINT, Profile, check_working_point, profile_line

# Names `export_text` takes; SuperSlicer reads PrusaSlicer's .ini keys.
FORMATS = ("prusaslicer", "orcaslicer")
ALIASES = {"superslicer": "prusaslicer"}
# The file a format is written to beside others: NAME + suffix.
SUFFIX = {"prusaslicer": ".ini", "orcaslicer": ".orcaslicer.json"}
# Below this a slicer's limit means nothing (PrusaSlicer: 0 is "no limit";
# OrcaSlicer: "can't be zero"): such a temperature is refused.
MIN_FLOW_MM3_S = 0.01
# OrcaSlicer's filament_max_volumetric_speed accepts at most this (its def->max).
ORCA_MAX_FLOW_MM3_S = 200.0
# OrcaSlicer imports a preset only with a version that parses (its
# PresetBundle::import_json_presets: `if (!version) return false`); the
# version of the OrcaSlicer the preset is written for, shaped as its own
# user presets' ("1.6.0.66").
ORCA_PRESET_VERSION = "1.6.0.0"


class SlicerNumbers(NamedTuple):
    """What a slicer's filament preset gets from a profile."""

    name: str                      # the preset's name: the profile's
    temp_c: int                    # nozzle temperature, layers after the first
    first_layer_temp_c: int
    min_temp_c: int                # the profile's bounds in whole degrees
    max_temp_c: int
    max_volumetric_speed_mm3_s: float
    filament_diameter_mm: float
    working_point: float
    notes: str



def _quoted(text: str) -> str:
    """text in double quotes as JSON writes it, letters left as they are
    (a slicer shows the notes as text: not 'gr\\u00fcn')."""
    return json.dumps(text, ensure_ascii=False)

def whole_degrees(profile: Profile) -> range:
    """The whole-degree temperatures within the profile's bounds."""
    b = profile.bounds
    lo, hi = math.ceil(b.min_temp_c), math.floor(b.max_temp_c)
    if lo > hi:
        raise FlowloopError(f"the profile's bounds {b.min_temp_c:g}..{b.max_temp_c:g}"
                            f" degC hold no whole degree (slicers store whole degrees)")
    return range(lo, hi + 1)


def check_temp(profile: Profile, temp_c: float) -> int:
    """A slicer temperature: a whole degree within the profile's bounds."""
    b = profile.bounds
    if isinstance(temp_c, bool) or not isinstance(temp_c, (int, float)) \
            or not math.isfinite(temp_c):
        raise FlowloopError(f"the temperature must be a number, got {temp_c!r}")
    if not b.min_temp_c <= temp_c <= b.max_temp_c:
        raise FlowloopError(f"{temp_c:g} degC is outside the profile's bounds "
                            f"{b.min_temp_c:g}..{b.max_temp_c:g} degC")
    if temp_c != int(temp_c):
        raise FlowloopError(f"{temp_c:g} degC is not a whole degree (slicers store "
                            f"whole degrees)")
    return int(temp_c)


def default_temp(profile: Profile) -> int:
    """The recommended temperature to the nearest whole degree in bounds."""
    degrees = whole_degrees(profile)
    return min(degrees[-1], max(degrees[0],
                                math.floor(profile.bounds.recommended_temp_c + 0.5)))


def max_volumetric_speed(profile: Profile, temp_c: float,
                         working_point: float = DEFAULT_WORKING_POINT) -> float:
    """The melt line's flow at temp_c, rounded down to 0.01 mm^3/s."""
    flow = profile_line(profile, working_point).flow_mm3_s(temp_c)
    # floor, with a guard against 11.65 being held as 11.649999...
    return math.floor(round(flow * 100, 6)) / 100


def slicer_numbers(profile: Profile, temp_c: Optional[float] = None,
                   first_layer_temp_c: Optional[float] = None,
                   working_point: float = DEFAULT_WORKING_POINT) -> SlicerNumbers:
    """The numbers for a slicer preset; temp_c defaults to the recommended
    temperature, first_layer_temp_c to temp_c. Refused (FlowloopError, one
    line) where a temperature is outside the bounds or not a whole degree, or
    the hotend melts nothing at temp_c."""
    wp = check_working_point(working_point)
    temp = default_temp(profile) if temp_c is None else check_temp(profile, temp_c)
    first = temp if first_layer_temp_c is None else check_temp(profile,
                                                                first_layer_temp_c)
    flow = max_volumetric_speed(profile, temp, wp)
    if flow < MIN_FLOW_MM3_S:
        raise FlowloopError(f"at {temp} degC and working point {wp:g} the profile "
                            f"melts no flow (a slicer would read 0 as no limit): "
                            f"choose a higher temperature")
    degrees = whole_degrees(profile)
    ident = profile.identity
    notes = (f"flowloop {__version__}: profile {_quoted(ident.name)}"
             + (f" (printer {_quoted(ident.printer)})" if ident.printer else "")
             + f", nozzle {ident.nozzle_diameter_mm:g} mm, working point {wp:g}"
             f" (0 real print, 1 into air): {flow:.2f} mm^3/s at {temp} degC")
    return SlicerNumbers(
        name=ident.name, temp_c=temp, first_layer_temp_c=first,
        min_temp_c=degrees[0], max_temp_c=degrees[-1],
        max_volumetric_speed_mm3_s=flow,
        filament_diameter_mm=ident.filament_diameter_mm, working_point=wp,
        notes=notes)


def _number(value: float) -> str:
    """A number as the slicers write it: 11.65, 1.75, 12 (no exponent)."""
    text = f"{value:.6f}".rstrip("0").rstrip(".")
    return text or "0"


def c_string(text: str) -> str:
    """PrusaSlicer's quoted string (escape_string_cstyle): \\, " and newlines
    escaped, in double quotes."""
    out = text.replace("\\", "\\\\").replace('"', '\\"')
    return '"' + out.replace("\r", "\\r").replace("\n", "\\n") + '"'


def prusaslicer_settings(numbers: SlicerNumbers) -> Dict[str, str]:
    """{key: value as the .ini writes it} for PrusaSlicer / SuperSlicer."""
    return {
        "filament_diameter": _number(numbers.filament_diameter_mm),
        "filament_max_volumetric_speed": _number(numbers.max_volumetric_speed_mm3_s),
        "filament_notes": c_string(numbers.notes),
        "first_layer_temperature": str(numbers.first_layer_temp_c),
        "temperature": str(numbers.temp_c),
    }


def prusaslicer_ini(numbers: SlicerNumbers) -> str:
    """A PrusaSlicer / SuperSlicer filament config (.ini)."""
    header = [f"# PrusaSlicer filament settings written by flowloop {__version__}",
              f"# profile {_quoted(numbers.name)}, working point "
              f"{numbers.working_point:g}"]
    body = [f"{key} = {value}"
            for key, value in sorted(prusaslicer_settings(numbers).items())]
    return "\n".join(header + body) + "\n"


def orcaslicer_preset(numbers: SlicerNumbers, inherits: str = "") -> Dict[str, object]:
    """An OrcaSlicer filament user preset: every setting a list of strings.
    inherits: the preset it is based on (its other settings come from
    there); "" for a preset of its own."""
    if numbers.max_volumetric_speed_mm3_s > ORCA_MAX_FLOW_MM3_S:
        raise FlowloopError(f"{numbers.max_volumetric_speed_mm3_s:g} mm^3/s is above "
                            f"OrcaSlicer's most, {ORCA_MAX_FLOW_MM3_S:g} mm^3/s")
    one = lambda value: [value]  # noqa: E731 - one extruder's value
    return {
        "type": "filament",
        "name": numbers.name,
        "from": "User",
        "inherits": inherits,
        "instantiation": "true",
        "version": ORCA_PRESET_VERSION,
        "filament_settings_id": one(numbers.name),
        "nozzle_temperature": one(str(numbers.temp_c)),
        "nozzle_temperature_initial_layer": one(str(numbers.first_layer_temp_c)),
        "nozzle_temperature_range_low": one(str(numbers.min_temp_c)),
        "nozzle_temperature_range_high": one(str(numbers.max_temp_c)),
        "filament_max_volumetric_speed": one(_number(
            numbers.max_volumetric_speed_mm3_s)),
        "filament_diameter": one(_number(numbers.filament_diameter_mm)),
        "filament_notes": one(numbers.notes),
    }


def orcaslicer_json(numbers: SlicerNumbers, inherits: str = "") -> str:
    return json.dumps(orcaslicer_preset(numbers, inherits), indent=4,
                      ensure_ascii=False) + "\n"


def check_format(name: str) -> str:
    """A format's name (any case; superslicer is prusaslicer)."""
    fmt = name.strip().lower()
    fmt = ALIASES.get(fmt, fmt)
    if fmt not in FORMATS:
        raise FlowloopError(f"unknown slicer format {name!r} (one of "
                            f"{', '.join(FORMATS + tuple(ALIASES))})")
    return fmt


def export_text(profile: Profile, fmt: str, temp_c: Optional[float] = None,
                first_layer_temp_c: Optional[float] = None,
                working_point: float = DEFAULT_WORKING_POINT,
                inherits: str = "") -> str:
    """The file for one slicer format (see FORMATS)."""
    fmt = check_format(fmt)
    numbers = slicer_numbers(profile, temp_c, first_layer_temp_c, working_point)
    return format_text(numbers, fmt, inherits)


def format_text(numbers: SlicerNumbers, fmt: str, inherits: str = "") -> str:
    """The file of a checked format (check_format) for these numbers."""
    if fmt == "orcaslicer":
        return orcaslicer_json(numbers, inherits)
    return prusaslicer_ini(numbers)
