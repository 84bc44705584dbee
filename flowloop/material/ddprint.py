"""ddPrint material files: read them into profiles, write profiles back.

ddPrint's files are JSON with two additions: lines starting with `#` are
comments, and so are entries like `"# text",` inside objects. ddPrint's loader
drops every line whose stripped text starts with `#` or `"#`; so does this one.

A generic file (`pla.json`) holds the temperature bounds and one
`properties_NN` object per nozzle (NN = diameter x 100). A printer-specific
file (`UM2-1/herz-pla-red.json`) replaces whole top-level keys of a generic
one; `find_generic_base` finds that generic file beside the printer folder.
Numbers flowloop does not use (bed temperatures, kAdvance, slippage...) are
kept in `Profile.ddprint` so an export writes every number it read.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Dict, List, NamedTuple, Optional, Tuple

from .. import __version__
from ..errors import FlowloopError
from .profile import (
    Bounds,
    DdprintExtras,
    FlowLine,
    Identity,
    Lines,
    PowerLine,
    Profile,
    Provenance,
)

DDPRINT_VERSION = 5
# Top-level keys that become schema fields; every other number is kept as is.
TOP_FIELDS = ("material_diameter", "hotendBaseTemp", "hotendGoodTemp",
              "hotendMaxTemp")
NOZZLE_FIELDS = ("Ktemp", "P0temp", "FR0pwm", "P0tempPrint", "FR0pwmPrint",
                 "Kpwm", "P0pwm", "P0pwmPrint")
PROPERTIES_PREFIX = "properties_"


def strip_comments(text: str) -> str:
    """ddPrint's rule: drop lines whose stripped text starts with # or "#."""
    return "\n".join("" if line.strip().startswith(("#", '"#')) else line
                     for line in text.splitlines())


def parse_text(text: str, source: str = "<text>") -> Dict[str, Any]:
    try:
        data = json.loads(strip_comments(text))
    except json.JSONDecodeError as e:
        raise FlowloopError(f"{source}: not a ddPrint file: line {e.lineno}: "
                            f"{e.msg}") from None
    if not isinstance(data, dict):
        raise FlowloopError(f"{source}: not a ddPrint file: the top level is not "
                            f"an object")
    return data


def read_file(path: Path) -> Dict[str, Any]:
    return parse_text(_read_text(path), str(path))


def _read_text(path: Path) -> str:
    try:
        return Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise FlowloopError(f"{path}: cannot read: {e}") from None


# Who a profile belongs to, in a comment ddPrint skips: `flowloop profile
# export` writes it and import reads it back, so an exported profile imports
# as the same profile (name, printer, filament) and not as its file's name.
IDENTITY_COMMENT = "# flowloop identity: "
_IDENTITY_STRINGS = ("name", "printer", "filament_name", "filament_vendor",
                     "filament_type")


def identity_comment(ident: Identity) -> str:
    fields: Dict[str, Any] = {k: getattr(ident, k) for k in _IDENTITY_STRINGS}
    if ident.spoolman_filament_id is not None:
        fields["spoolman_filament_id"] = ident.spoolman_filament_id
    return IDENTITY_COMMENT + json.dumps(fields, ensure_ascii=True)


def read_identity(text: str, source: str) -> Dict[str, Any]:
    """The identity fields an exported file carries ({} for ddPrint's own)."""
    for n, line in enumerate(text.splitlines(), 1):
        if not line.startswith(IDENTITY_COMMENT):
            continue
        try:
            fields = json.loads(line[len(IDENTITY_COMMENT):])
        except json.JSONDecodeError as e:
            raise FlowloopError(f"{source}: line {n}: the flowloop identity is not"
                                f" JSON: {e.msg}") from None
        if not isinstance(fields, dict):
            raise FlowloopError(f"{source}: line {n}: the flowloop identity is not"
                                f" an object")
        for key, value in fields.items():
            ok = (isinstance(value, str) if key in _IDENTITY_STRINGS else
                  key == "spoolman_filament_id" and isinstance(value, int)
                  and not isinstance(value, bool))
            if not ok:
                raise FlowloopError(f"{source}: line {n}: flowloop identity field"
                                    f" {key!r} is not valid")
        return fields
    return {}


def _is_number(value: Any) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value))


def is_specific(data: Dict[str, Any]) -> bool:
    """A printer-specific file: nozzle properties without temperature bounds."""
    return not any(key in data for key in TOP_FIELDS[1:])


def find_generic_base(path: Path) -> Optional[Path]:
    """The generic file a printer-specific one overrides: ../<type>.json whose
    stem is a word of this file's name (herz-pla-red -> pla.json), else whose
    stem begins a word (biofila_platec -> pla.json; the longest stem wins)."""
    path = Path(path)
    words = [w for w in path.stem.lower().replace("-", "_").split("_") if w]
    generics = {p.stem.lower(): p for p in sorted(path.parent.parent.glob("*.json"))
                if p.is_file()}
    for word in words:
        if word in generics:
            return generics[word]
    for word in words:
        for stem in sorted(generics, key=len, reverse=True):
            if word.startswith(stem):
                return generics[stem]
    return None


def nozzles(data: Dict[str, Any]) -> Dict[float, str]:
    """{nozzle diameter mm: key} of every properties_NN object."""
    out = {}
    for key, value in data.items():
        suffix = key[len(PROPERTIES_PREFIX):]
        if key.startswith(PROPERTIES_PREFIX) and suffix.isdigit() \
                and isinstance(value, dict):
            out[int(suffix) / 100.0] = key
    return out


def properties_key(nozzle_mm: float) -> str:
    return f"{PROPERTIES_PREFIX}{round(nozzle_mm * 100)}"


def _need(obj: Dict[str, Any], key: str, where: str) -> float:
    if key not in obj:
        raise FlowloopError(f"{where} has no {key}")
    if not _is_number(obj[key]):
        raise FlowloopError(f"{where}: {key} is not a number: {obj[key]!r}")
    return float(obj[key])


def _extras(obj: Dict[str, Any], used) -> Dict[str, Any]:
    return {k: v for k, v in obj.items() if k not in used and _is_number(v)}


def to_profile(data: Dict[str, Any], nozzle_mm: float, *, name: str,
               printer: str = "", filament_name: str = "", filament_type: str = "",
               source: str = "", filament_vendor: str = "",
               spoolman_filament_id: Optional[int] = None) -> Profile:
    """The profile for one nozzle of a merged (generic + specific) ddPrint dict."""
    key = properties_key(nozzle_mm)
    where = f"{source} {key}".strip()
    props = data.get(key)
    if not isinstance(props, dict):
        raise FlowloopError(f"{source}: no {key} (nozzle {nozzle_mm:g} mm)")
    for field in ("P0tempPrint", "FR0pwmPrint"):
        if field not in props:
            raise FlowloopError(f"{where}: no real-print point ({field} missing); "
                                f"flowloop needs both lines")
    slope = _need(props, "Ktemp", where)
    flow_air, flow_print = _need(props, "FR0pwm", where), _need(
        props, "FR0pwmPrint", where)
    air_power = print_power = None
    if "Kpwm" in props and "P0pwm" in props:
        kpwm = _need(props, "Kpwm", where)
        air_power = PowerLine(slope_mm3_s_per_pwm=kpwm,
                              pwm=_need(props, "P0pwm", where), flow_mm3_s=flow_air)
        if "P0pwmPrint" in props:
            print_power = PowerLine(slope_mm3_s_per_pwm=kpwm,
                                    pwm=_need(props, "P0pwmPrint", where),
                                    flow_mm3_s=flow_print)
    top_where = source or "ddPrint file"
    extras = DdprintExtras(
        top=_extras({k: v for k, v in data.items()
                     if not k.startswith(PROPERTIES_PREFIX)}, TOP_FIELDS),
        nozzle=_extras(props, NOZZLE_FIELDS))
    try:
        return Profile(
            identity=Identity(
                name=name, printer=printer, nozzle_diameter_mm=nozzle_mm,
                filament_name=filament_name, filament_type=filament_type,
                filament_vendor=filament_vendor,
                spoolman_filament_id=spoolman_filament_id,
                filament_diameter_mm=_need(data, "material_diameter", top_where)),
            lines=Lines(
                into_air=FlowLine(slope_mm3_s_per_c=slope,
                                  temp_c=_need(props, "P0temp", where),
                                  flow_mm3_s=flow_air),
                real_print=FlowLine(slope_mm3_s_per_c=slope,
                                    temp_c=_need(props, "P0tempPrint", where),
                                    flow_mm3_s=flow_print),
                into_air_power=air_power, real_print_power=print_power),
            bounds=Bounds(min_temp_c=_need(data, "hotendBaseTemp", top_where),
                          recommended_temp_c=_need(data, "hotendGoodTemp", top_where),
                          max_temp_c=_need(data, "hotendMaxTemp", top_where)),
            provenance=Provenance(method="ddprint_import", source=source,
                                  note="imported from a ddPrint material file"),
            ddprint=extras)
    except FlowloopError as e:
        raise FlowloopError(f"{where}: {e}") from None


class ImportResult(NamedTuple):
    profiles: List[Profile]
    problems: List[str]  # one line each: what could not be imported and why


def import_file(path: Path, nozzle_mm: Optional[float] = None,
                base: Optional[Path] = None,
                printer: Optional[str] = None) -> ImportResult:
    """Every nozzle of a ddPrint file (or just nozzle_mm) as profiles.

    A file that cannot be read at all raises FlowloopError; a nozzle that
    cannot be imported is listed in problems and the others still are.
    """
    path = Path(path)
    text = _read_text(path)
    data = parse_text(text, str(path))
    identity = read_identity(text, str(path))
    source = path.name
    generic_type = path.stem
    if base is None and is_specific(data):
        base = find_generic_base(path)
        if base is None:
            raise FlowloopError(
                f"{path}: a printer-specific file without temperature bounds and "
                f"no generic base file found beside its folder (use --base FILE)")
    found = nozzles(data)  # a specific file's own nozzles, not its base's
    if base is not None:
        merged = read_file(base)
        merged.update(data)  # ddPrint: specific keys replace whole generic keys
        data = merged
        source = f"{path.parent.name}/{path.name} + {Path(base).name}"
        generic_type = Path(base).stem
        if printer is None:
            printer = path.parent.name
    if not found:
        raise FlowloopError(f"{path}: no properties_NN object (only measured "
                            f"ddPrint profiles can be imported)")
    wanted = sorted(found)
    if nozzle_mm is not None:
        wanted = [n for n in wanted if abs(n - nozzle_mm) < 1e-6]
        if not wanted:
            have = ", ".join(f"{n:g}" for n in sorted(found))
            raise FlowloopError(f"{path}: no profile for nozzle {nozzle_mm:g} mm "
                                f"(has {have})")
    profiles, problems = [], []
    for n in wanted:
        # an exported profile's own identity; a ddPrint file's from its names
        own = {"name": f"{path.stem}_{round(n * 100)}", "filament_name": path.stem,
               "filament_type": generic_type.upper(), **identity}
        own["printer"] = printer if printer is not None else own.get("printer", "")
        try:
            profiles.append(to_profile(data, n, source=source, **own))
        except FlowloopError as e:
            problems.append(str(e))
    return ImportResult(profiles, problems)


def to_ddprint(profile: Profile) -> Dict[str, Any]:
    """The ddPrint dict for a profile: every number it holds, ddPrint's names."""
    # An imported profile writes back exactly the numbers it read (version
    # included or not); one flowloop made gets ddPrint's current version.
    extras = profile.ddprint or DdprintExtras(top={"version": DDPRINT_VERSION},
                                              nozzle={"version": DDPRINT_VERSION})
    lines, b = profile.lines, profile.bounds
    out: Dict[str, Any] = dict(extras.top)
    out.update({"material_diameter": profile.identity.filament_diameter_mm,
                "hotendBaseTemp": b.min_temp_c, "hotendGoodTemp": b.recommended_temp_c,
                "hotendMaxTemp": b.max_temp_c})
    props: Dict[str, Any] = dict(extras.nozzle)
    air, real = lines.into_air, lines.real_print
    props["Ktemp"] = air.slope_mm3_s_per_c
    props.update({"P0temp": air.temp_c, "FR0pwm": air.flow_mm3_s})
    props.update({"P0tempPrint": real.temp_c, "FR0pwmPrint": real.flow_mm3_s})
    for name, key_pwm, flow in (("into_air_power", "P0pwm", air.flow_mm3_s),
                                ("real_print_power", "P0pwmPrint", real.flow_mm3_s)):
        power: Optional[PowerLine] = getattr(lines, name)
        if power is None:
            continue
        props.setdefault("Kpwm", power.slope_mm3_s_per_pwm)
        # ddPrint ties the PWM point to the temperature point's flow.
        props[key_pwm] = power.pwm + (flow - power.flow_mm3_s) / \
            power.slope_mm3_s_per_pwm
    out[properties_key(profile.identity.nozzle_diameter_mm)] = props
    return out


def export_text(profile: Profile) -> str:
    """A ddPrint-readable material file (comments first, then JSON)."""
    ident = profile.identity
    header = [
        f"# ddPrint material profile written by flowloop {__version__}",
        f"# name: {json.dumps(ident.name)}",
        f"# printer: {json.dumps(ident.printer)}, nozzle {ident.nozzle_diameter_mm:g}"
        f" mm, filament {json.dumps(ident.filament_name)}",
        identity_comment(ident),
    ]
    lines = profile.lines
    if lines.real_print.slope_mm3_s_per_c != lines.into_air.slope_mm3_s_per_c:
        # ddPrint has one slope (Ktemp) for both lines.
        header.append(f"# note: the real-print slope "
                      f"{lines.real_print.slope_mm3_s_per_c!r} is not kept: ddPrint "
                      f"uses Ktemp for both lines")
    return "\n".join(header) + "\n" + json.dumps(to_ddprint(profile), indent=2) + "\n"


def import_paths(paths: List[Path], nozzle_mm: Optional[float] = None,
                 base: Optional[Path] = None,
                 printer: Optional[str] = None) -> Tuple[List[Profile], List[str]]:
    """import_file over many paths: (profiles, one-line problems)."""
    profiles: List[Profile] = []
    problems: List[str] = []
    for path in paths:
        try:
            result = import_file(path, nozzle_mm, base, printer)
        except FlowloopError as e:
            problems.append(str(e))
            continue
        profiles += result.profiles
        problems += result.problems
    return profiles, problems
