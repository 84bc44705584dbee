"""`flowloop profile show|plot|validate|import|export`: material profiles at a
desk (export: a ddPrint file, or slicer filament settings through
flowloop.material.slicer); `flowloop profile list|store|activate|remove`: the
profiles a printer's Moonraker keeps (flowloop.host.moonraker_api)."""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
from pathlib import Path
from typing import Dict, List, Optional

from ..errors import FlowloopError
from ..host.moonraker_api import DEFAULT_URL, MoonrakerApi
from ..material import ddprint, plot, slicer
from ..material.active import extruder_arg, working_point_arg
from ..material.profile import (
    DEFAULT_WORKING_POINT,
    Profile,
    decode_profile,
    encode_profile,
    flow_at,
    line_warnings,
    temp_for_flow,
)
from .paths import refuse_overwriting


def safe_file_stem(name: str) -> str:
    """A file name for a free-text profile name: no path, no hidden file."""
    stem = re.sub(r"[^A-Za-z0-9_-]+", "_", name).strip("_")
    return stem or "profile"


def load(path: Path) -> Profile:
    """A flowloop profile file; a ddPrint file gets a hint to import it."""
    try:
        data = Path(path).read_bytes()
    except OSError as e:
        raise FlowloopError(f"{path}: cannot read: {e.strerror}") from None
    try:
        return decode_profile(data)
    except FlowloopError as e:
        if b"properties_" in data:
            raise FlowloopError(f"{path}: a ddPrint file, not a flowloop profile: "
                                f"run 'flowloop profile import {path}'") from None
        raise FlowloopError(f"{path}: {e}") from None


def _wp(text: str) -> float:
    try:
        return working_point_arg(text, "")
    except FlowloopError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def describe(profile: Profile, wp: float) -> str:
    ident, lines, b = profile.identity, profile.lines, profile.bounds
    prov = profile.provenance
    out = [
        f"{ident.name}",
        f"  printer {ident.printer or '-'}, nozzle {ident.nozzle_diameter_mm:g} mm, "
        f"filament {ident.filament_name or '-'} ({ident.filament_type or '-'}, "
        f"{ident.filament_vendor or 'vendor -'}, {ident.filament_diameter_mm:g} mm)"
        + (f", Spoolman filament {ident.spoolman_filament_id}"
           if ident.spoolman_filament_id is not None else ""),
        f"  bounds {b.min_temp_c:g} / {b.recommended_temp_c:g} / {b.max_temp_c:g} degC"
        f" (min / recommended / max)",
    ]
    for name, line in (("into air  ", lines.into_air),
                       ("real print", lines.real_print)):
        out.append(f"  {name} {line.slope_mm3_s_per_c:g} mm^3/s per degC through "
                   f"({line.temp_c:g} degC, {line.flow_mm3_s:g} mm^3/s)")
    out.append(f"  measured by {prov.method}"
               + (f" at {prov.measured_at}" if prov.measured_at else "")
               + (f" from {prov.source}" if prov.source else "")
               + f", {len(profile.points)} raw point(s)")
    out += [f"  warning: {warning}" for warning in line_warnings(profile)]
    out.append(f"  at working point {wp:g}:")
    b = profile.bounds
    step = 10.0
    temp = b.min_temp_c
    while temp <= b.max_temp_c + 1e-9:
        out.append(f"    {temp:6.1f} degC -> {flow_at(profile, temp, wp):6.2f} mm^3/s")
        temp += step
    for flow in (5.0, 10.0, 15.0, 20.0):
        temp = temp_for_flow(profile, flow, wp)
        clamped = temp in (b.min_temp_c, b.max_temp_c)
        out.append(f"    {flow:4.1f} mm^3/s needs {temp:.1f} degC"
                   + (" (clamped to the bounds)" if clamped else ""))
    return "\n".join(out)


def cmd_show(args) -> int:
    profile = load(args.file)
    if args.json:
        sys.stdout.write(encode_profile(profile).decode())
    else:
        print(describe(profile, args.wp))
    return 0


def cmd_validate(args) -> int:
    bad = 0
    for path in args.files:
        try:
            profile = load(path)
        except FlowloopError as e:
            print(str(e), file=sys.stderr)
            bad += 1
            continue
        print(f"{path}: ok ({profile.identity.name})")
    return 1 if bad else 0


def cmd_plot(args) -> int:
    profile = load(args.file)
    out: Path = args.output or Path(safe_file_stem(profile.identity.name) + ".svg")
    refuse_overwriting([("-o", out)], [("FILE", args.file)])
    if out.suffix.lower() == ".png":
        plot.png(profile, out, args.wp)
    elif out.suffix.lower() == ".svg":
        out.write_text(plot.svg(profile, args.wp), encoding="utf-8")
    else:
        raise FlowloopError(f"{out}: the plot file must end in .svg or .png")
    print(f"wrote {out}")
    return 0


def cmd_import(args) -> int:
    out_dir: Path = args.output_dir
    if not out_dir.is_dir():
        raise FlowloopError(f"{out_dir}: no such directory")
    profiles, problems = ddprint.import_paths(args.files, args.nozzle, args.base,
                                              args.printer)
    written = set()
    for profile in profiles:
        path = out_dir / (safe_file_stem(profile.identity.name) + ".json")
        if path in written:
            problems.append(f"{profile.provenance.source}: {path} was written above "
                            f"from another file (import them one at a time)")
            continue
        written.add(path)
        path.write_bytes(encode_profile(profile))
        print(f"wrote {path} ({json.dumps(profile.identity.name)}, nozzle "
              f"{profile.identity.nozzle_diameter_mm:g} mm)")
        for warning in line_warnings(profile):
            print(f"flowloop profile import: warning: {profile.identity.name}: "
                  f"{warning}", file=sys.stderr)
    for problem in problems:
        print(f"flowloop profile import: skipped {problem}", file=sys.stderr)
    return 1 if problems else 0


EXPORT_FORMATS = ("ddprint",) + slicer.FORMATS
# The file each format is written to in --output-dir: NAME + suffix.
EXPORT_SUFFIX = {"ddprint": ".ddprint.json", **slicer.SUFFIX}


def _formats(text: str) -> List[str]:
    """--format's comma-separated list: each format once, in the order given."""
    out: List[str] = []
    for part in text.split(","):
        name = part.strip().lower()
        if name != "ddprint":
            try:
                name = slicer.check_format(name)
            except FlowloopError:
                raise FlowloopError(
                    f"--format: unknown format {part.strip()!r} (one of "
                    f"{', '.join(EXPORT_FORMATS + tuple(slicer.ALIASES))})") from None
        if name not in out:
            out.append(name)
    return out


def _number_option(option: str, text: Optional[str]) -> Optional[float]:
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        raise FlowloopError(f"{option}: not a number: {text!r}") from None
    if not math.isfinite(value):
        raise FlowloopError(f"{option}: not a number: {text!r}")
    return value


def _temp_option(profile: Profile, option: str, text: Optional[str]) -> Optional[int]:
    value = _number_option(option, text)
    if value is None:
        return None
    try:
        return slicer.check_temp(profile, value)
    except FlowloopError as e:
        raise FlowloopError(f"{option}: {e}") from None


def _export_texts(args, profile: Profile, formats: List[str]) -> Dict[str, str]:
    """{format: file text}, every refusal made before anything is written."""
    slicer_formats = [f for f in formats if f != "ddprint"]
    given = [option for option, value in (
        ("--temp", args.temp), ("--first-layer-temp", args.first_layer_temp),
        ("--wp", args.wp), ("--inherits", args.inherits)) if value is not None]
    if given and not slicer_formats:
        raise FlowloopError(f"{given[0]}: only for a slicer format "
                            f"(--format {','.join(slicer.FORMATS)})")
    if args.inherits is not None and "orcaslicer" not in slicer_formats:
        raise FlowloopError("--inherits: only for --format orcaslicer")
    texts: Dict[str, str] = {}
    if slicer_formats:
        try:
            wp = working_point_arg(args.wp, "") if args.wp is not None \
                else DEFAULT_WORKING_POINT
        except FlowloopError as e:
            raise FlowloopError(f"--wp: {e}") from None
        temp = _temp_option(profile, "--temp", args.temp)
        first = _temp_option(profile, "--first-layer-temp", args.first_layer_temp)
        numbers = slicer.slicer_numbers(profile, temp, first, wp)
    for fmt in formats:
        texts[fmt] = (ddprint.export_text(profile) if fmt == "ddprint" else
                      slicer.format_text(numbers, fmt, args.inherits or ""))
    return texts


def cmd_export(args) -> int:
    formats = _formats(args.format)
    if args.output is not None and args.output_dir is not None:
        raise FlowloopError("-o and --output-dir: give one")
    if len(formats) > 1 and args.output is not None:
        raise FlowloopError(f"-o: {len(formats)} formats are written to "
                            f"{len(formats)} files: give --output-dir DIR")
    profile = load(args.file)
    texts = _export_texts(args, profile, formats)
    if args.output_dir is not None:
        if not args.output_dir.is_dir():
            raise FlowloopError(f"--output-dir: {args.output_dir}: no such directory")
        stem = safe_file_stem(profile.identity.name)
        outputs = [("--output-dir", args.output_dir / (stem + EXPORT_SUFFIX[fmt]))
                   for fmt in formats]
    elif args.output is not None:
        outputs = [("-o", args.output)]
    elif len(formats) == 1:
        sys.stdout.write(texts[formats[0]])
        return 0
    else:
        raise FlowloopError(f"{len(formats)} formats are written to "
                            f"{len(formats)} files: give --output-dir DIR")
    refuse_overwriting(outputs, [("FILE", args.file)])
    if not args.force:
        for option, path in outputs:
            if path.exists():
                raise FlowloopError(f"{option}: {path} exists: not overwritten "
                                    f"(--force overwrites it)")
    for (option, path), fmt in zip(outputs, formats):
        try:
            path.write_text(texts[fmt], encoding="utf-8")
        except OSError as e:
            raise FlowloopError(f"{option}: {path}: cannot write: "
                                f"{e.strerror}") from None
        print(f"wrote {path} ({fmt})")
    return 0


# --- on a printer, through its Moonraker -------------------------------------

def _printer(args) -> MoonrakerApi:
    return MoonrakerApi(args.moonraker, args.api_key)


def cmd_list(args) -> int:
    api = _printer(args)
    answer = api.profiles()
    active = answer.get("active", {})
    if not answer.get("profiles"):
        print(f"{api.url}: no profiles stored (flowloop profile store FILE)")
    for summary in answer.get("profiles", []):
        name = summary.get("name")
        on = [f"{ext} at working point {entry.get('working_point'):g}"
              for ext, entry in sorted(active.items()) if entry.get("name") == name]
        print(f"{json.dumps(name)}" + (f": active on {', '.join(on)}" if on else ""))
    return 0


def cmd_store(args) -> int:
    profile = load(args.file)
    if args.activate is not None:   # refused before anything is stored
        try:
            extruder_arg(args.activate)
        except FlowloopError as e:
            raise FlowloopError(f"--activate: {e}") from None
    api = _printer(args)
    api.store(json.loads(encode_profile(profile)))
    print(f"stored {json.dumps(profile.name)} on {api.url}")
    if args.activate is not None:
        try:
            _activate(api, profile.name, args.activate, args.wp)
        except FlowloopError as e:
            raise FlowloopError(f"stored, but not active: {e}") from None
    return 0


def cmd_activate(args) -> int:
    _activate(_printer(args), args.name, args.extruder, args.wp)
    return 0


def _activate(api: MoonrakerApi, name: str, extruder: str, wp) -> None:
    answer = api.activate(name, extruder, wp)
    wp = answer.get("working_point", wp)
    print(f"{json.dumps(name)} active on {extruder}"
          + (f" at working point {wp:g}" if isinstance(wp, (int, float)) else "")
          + ("" if answer.get("sent_to_klippy", True)
             else " (klippy is not connected: sent when it is, and dropped"
                  " if klippy refuses it then)"))


def cmd_remove(args) -> int:
    api = _printer(args)
    api.remove(args.name)
    print(f"removed {json.dumps(args.name)} from {api.url}")
    return 0


def _printer_options(p) -> None:
    p.add_argument("--moonraker", default=DEFAULT_URL, metavar="URL",
                   help=f"the printer's Moonraker: a URL or HOST[:PORT] "
                        f"(default {DEFAULT_URL})")
    p.add_argument("--api-key", default=os.environ.get("MOONRAKER_API_KEY"),
                   help="Moonraker API key (default: $MOONRAKER_API_KEY)")


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "profile", help="material profiles: show, plot, validate, import, export;"
                        " list, store, activate, remove on a printer",
        description="Material profiles (flow the hotend melts at each temperature).")
    sub = parser.add_subparsers(dest="profile_command", metavar="ACTION",
                                required=True)

    p = sub.add_parser("show", help="print a profile and its flow table")
    p.add_argument("file", type=Path)
    p.add_argument("--wp", type=_wp, default=DEFAULT_WORKING_POINT,
                   help="working point 0..1 (0 real print, 1 into air; default 0.5)")
    p.add_argument("--json", action="store_true", help="print the profile JSON")
    p.set_defaults(func=cmd_show)

    p = sub.add_parser("validate", help="check profile files, one line each")
    p.add_argument("files", type=Path, nargs="+")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("plot", help="plot a profile as SVG (PNG with matplotlib)")
    p.add_argument("file", type=Path)
    p.add_argument("-o", "--output", type=Path,
                   help="output .svg or .png (default: NAME.svg here)")
    p.add_argument("--wp", type=_wp, default=DEFAULT_WORKING_POINT,
                   help="working point 0..1 (default 0.5)")
    p.set_defaults(func=cmd_plot)

    p = sub.add_parser("import", help="ddPrint material files -> flowloop profiles")
    p.add_argument("files", type=Path, nargs="+")
    p.add_argument("-o", "--output-dir", type=Path, default=Path("."),
                   help="where to write the profiles (default: here)")
    p.add_argument("--nozzle", type=float, help="only this nozzle diameter (mm)")
    p.add_argument("--base", type=Path,
                   help="the generic ddPrint file a printer-specific file overrides "
                        "(default: ../<type>.json, e.g. pla.json for herz-pla-red)")
    p.add_argument("--printer", help="printer name (default: the file's folder for "
                                     "printer-specific files)")
    p.set_defaults(func=cmd_import)

    p = sub.add_parser(
        "export", help="a flowloop profile -> a ddPrint material file, or slicer "
                       "filament settings (PrusaSlicer .ini, OrcaSlicer .json)")
    p.add_argument("file", type=Path)
    p.add_argument("-f", "--format", default="ddprint", metavar="LIST",
                   help="comma-separated: ddprint, prusaslicer (superslicer), "
                        "orcaslicer (default ddprint)")
    p.add_argument("-o", "--output", type=Path,
                   help="output file, one format (default: stdout)")
    p.add_argument("-d", "--output-dir", type=Path, metavar="DIR",
                   help="write each format to DIR/NAME.ddprint.json, NAME.ini, "
                        "NAME.orcaslicer.json")
    p.add_argument("--force", action="store_true",
                   help="overwrite output files that exist (default: refused)")
    p.add_argument("--temp", metavar="DEGC",
                   help="slicer: nozzle temperature, a whole degree within the "
                        "profile's bounds (default: its recommended)")
    p.add_argument("--first-layer-temp", metavar="DEGC",
                   help="slicer: first-layer nozzle temperature (default: --temp)")
    p.add_argument("--wp", metavar="WP",
                   help="slicer: working point 0..1 the max volumetric speed is "
                        "read at (0 real print, 1 into air; default 0.5)")
    p.add_argument("--inherits", metavar="PRESET",
                   help="orcaslicer: the preset this one is based on (default: "
                        "none, a preset of its own)")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("list", help="the profiles a printer keeps, and where active")
    _printer_options(p)
    p.set_defaults(func=cmd_list)

    p = sub.add_parser("store", help="store a profile file on a printer")
    p.add_argument("file", type=Path)
    p.add_argument("--activate", nargs="?", const="extruder", default=None,
                   metavar="EXTRUDER",
                   help="and make it active on EXTRUDER (default extruder)")
    p.add_argument("--wp", type=_wp, default=None,
                   help="with --activate: working point 0..1 (default: the "
                        "printer's [flowloop] working_point)")
    _printer_options(p)
    p.set_defaults(func=cmd_store)

    p = sub.add_parser("activate",
                       help="make a stored profile the one an extruder prints with")
    p.add_argument("name", help="the profile's name (flowloop profile list)")
    p.add_argument("--extruder", default="extruder",
                   help="extruder, extruder1, ... (default extruder)")
    p.add_argument("--wp", type=_wp, default=None,
                   help="working point 0..1 (default: the extruder's current, "
                        "else the printer's [flowloop] working_point)")
    _printer_options(p)
    p.set_defaults(func=cmd_activate)

    p = sub.add_parser("remove", help="delete a stored profile from a printer")
    p.add_argument("name")
    _printer_options(p)
    p.set_defaults(func=cmd_remove)

