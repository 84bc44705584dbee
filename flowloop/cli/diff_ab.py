"""`flowloop ab-calibrate` and `flowloop ab-pylons`: the differential A/B
calibration at a desk, from caliper readings to new rotation_distance values,
and the G-code of the part to print and measure.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..calibrate import diff_ab, pylons
from ..errors import FlowloopError
from ..host.klipper_config import check_part_temp
from .flags import with_flags

# --a3/--b3/--d3 ... for rows of more pylons
EXTRA_DISTANCES = tuple(range(3, diff_ab.MAX_DISTANCES + 1))


def register(subparsers) -> None:
    _register_calibrate(subparsers)
    _register_pylons(subparsers)


# --- ab-calibrate ------------------------------------------------------------

def _register_calibrate(subparsers) -> None:
    p = subparsers.add_parser(
        "ab-calibrate", help="new A/B rotation_distance from pylon readings",
        description="Differential A/B (CoreXY) or X/Y (cartesian) rotation_distance "
                    "calibration: scale = (d2 - d1) / (D2 - D1) from caliper "
                    "readings of the pylon print (flowloop ab-pylons), new "
                    "rotation_distance = old x scale. Readings are comma lists; "
                    "each list's median is used.")
    p.add_argument("--rotation-distance-a", required=True, metavar="RD",
                   help="current rotation_distance of [stepper_x] (motor A)")
    p.add_argument("--rotation-distance-b", required=True, metavar="RD",
                   help="current rotation_distance of [stepper_y] (motor B)")
    for axis in ("a", "b"):
        for k in (1, 2):
            p.add_argument(f"--{axis}{k}", required=True, metavar="V[,V...]",
                           help=f"readings of {axis.upper()}{k} in mm (pylon 1 to "
                                f"{k + 1}, outside to outside)")
    d1, d2 = diff_ab.NOMINAL_DISTANCES_MM
    p.add_argument("--d1", type=float, default=d1, help=f"nominal D1 in mm ({d1:g})")
    p.add_argument("--d2", type=float, default=d2, help=f"nominal D2 in mm ({d2:g})")
    for k in EXTRA_DISTANCES:
        p.add_argument(f"--a{k}", metavar="V[,V...]", help=argparse.SUPPRESS)
        p.add_argument(f"--b{k}", metavar="V[,V...]", help=argparse.SUPPRESS)
        p.add_argument(f"--d{k}", type=float, help=argparse.SUPPRESS)
    p.add_argument("--kinematics", choices=diff_ab.KINEMATICS, default="corexy")
    p.add_argument("--force", action="store_true",
                   help=f"accept a scale more than "
                        f"{100 * diff_ab.MAX_SCALE_CHANGE:g} %% from 1")
    b = diff_ab.ErrorBudget()
    for flag, field, text in BUDGET_OPTIONS:
        default = getattr(b, field)
        p.add_argument(f"--{flag}", dest=field, type=float, default=default,
                       metavar="MM", help=f"{text} ({default:g})")
    p.add_argument("--history", type=Path, metavar="FILE",
                   help="JSON file of earlier iterations; this one is appended")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run_calibrate)


# ab-calibrate's error budget options: (flag, ErrorBudget field, help)
BUDGET_OPTIONS = (
    ("caliper-accuracy", "caliper_accuracy_mm",
     "caliper trueness over --caliper-range"),
    ("caliper-range", "caliper_range_mm",
     "length the caliper accuracy is stated for"),
    ("reading-error", "reading_error_mm",
     "3 sigma of one reading, used below 3 readings"),
)


def _axis_sets(args, axis: str):
    ks = (1, 2) + EXTRA_DISTANCES
    nominals = {k: getattr(args, f"d{k}") for k in ks}
    readings = {k: getattr(args, f"{axis}{k}") for k in ks
                if getattr(args, f"{axis}{k}") is not None}
    return diff_ab.numbered_reading_sets(axis, readings, nominals)


def calibration_from_args(args) -> diff_ab.Calibration:
    try:
        budget = diff_ab.ErrorBudget(**{field: getattr(args, field)
                                        for _, field, _ in BUDGET_OPTIONS})
    except FlowloopError as e:
        raise with_flags(e, BUDGET_OPTIONS) from None
    ks = (1, 2) + EXTRA_DISTANCES
    diff_ab.check_nominals_used(
        [k for k in EXTRA_DISTANCES if getattr(args, f"d{k}") is not None],
        [k for k in ks for axis in "ab" if getattr(args, f"{axis}{k}") is not None])
    return diff_ab.calibrate(args.kinematics,
                             diff_ab.check_rotation_distance(
                                 args.rotation_distance_a, "--rotation-distance-a"),
                             diff_ab.check_rotation_distance(
                                 args.rotation_distance_b, "--rotation-distance-b"),
                             _axis_sets(args, "a"), _axis_sets(args, "b"),
                             budget=budget, force=args.force,
                             force_hint="--force")


def _load_history(path: Path):
    if not path.exists():
        return []
    try:
        text = path.read_text()
        if not text.strip():    # a file made ready (touch): no rounds yet
            return []
        history = json.loads(text)
    except (OSError, ValueError) as e:
        raise FlowloopError(f"cannot read history {path}: {e}") from None
    return diff_ab.check_history(history, str(path))


def run_calibrate(args) -> int:
    calibration = calibration_from_args(args)
    history = None
    if args.history is not None:
        history = diff_ab.append_history(_load_history(args.history), calibration)
        args.history.write_text(json.dumps(history, indent=1) + "\n")
    if args.json:
        print(json.dumps(calibration.json_summary()))
        return 0
    for line in calibration.report_lines():
        print(line)
    print("Paste into printer.cfg (or run DIFF_AB_CALIBRATE on the printer):")
    for r in calibration.axes():
        print(f"  [{r.stepper}] rotation_distance: {r.new_rotation_distance:.6f}")
    if history:
        print("History:")
        for line in diff_ab.history_lines(history):
            print("  " + line)
    return 0


# --- ab-pylons -----------------------------------------------------------------

# ab-pylons options: (flag, PylonOptions field, help)
PYLON_OPTIONS = (
    ("pylon-width", "pylon_width_mm", "along the row, mm"),
    ("pylon-depth", "pylon_depth_mm", "across the row, mm"),
    ("pylon-height", "pylon_height_mm", "mm"),
    ("bed-x", "bed_size_x_mm", "bed size X, mm"),
    ("bed-y", "bed_size_y_mm", "bed size Y, mm"),
    ("centre-x", "centre_x_mm", "where the rows cross, default bed middle"),
    ("centre-y", "centre_y_mm", "where the rows cross, default bed middle"),
    ("nozzle", "nozzle_diameter_mm", "mm"),
    ("line-width", "line_width_mm", "mm"),
    ("layer-height", "layer_height_mm", "mm"),
    ("filament-diameter", "filament_diameter_mm", "mm"),
    ("extrusion-multiplier", "extrusion_multiplier", "never over-extrude"),
    ("hotend-temp", "hotend_temp_c", "C"),
    ("bed-temp", "bed_temp_c", "C, kept on after the print"),
    ("speed", "print_speed_mm_s", "mm/s"),
    ("first-layer-speed", "first_layer_speed_mm_s", "mm/s, at most --speed"),
    ("travel-speed", "travel_speed_mm_s", "mm/s"),
    ("accel", "accel_mm_s2", "mm/s^2, left set after the print; default: the "
                             "printer's max_accel"),
    ("retract", "retract_mm", "mm"),
    ("z-hop", "z_hop_mm", "mm"),
)


def _register_pylons(subparsers) -> None:
    d = pylons.PylonOptions()
    p = subparsers.add_parser(
        "ab-pylons", help="G-code of the differential A/B calibration pylons",
        description="Write ready-to-print G-code: two rows of solid, symmetric "
                    "pylons (A and B diagonals on CoreXY, X and Y on cartesian), "
                    "printed outer perimeter first.")
    p.add_argument("-o", "--output", default="ab_pylons.gcode",
                   help="G-code file to write, '-' for stdout (ab_pylons.gcode)")
    p.add_argument("--kinematics", choices=diff_ab.KINEMATICS, default=d.kinematics)
    p.add_argument("--d1", type=float, default=d.distances_mm[0],
                   help="nominal D1 outside to outside, pylon 1 to 2 (10)")
    p.add_argument("--d2", type=float, default=d.distances_mm[1],
                   help="nominal D2 outside to outside, pylon 1 to 3 (150)")
    for k in EXTRA_DISTANCES:
        p.add_argument(f"--d{k}", type=float, help=argparse.SUPPRESS)
    for flag, field, text in PYLON_OPTIONS:
        default = getattr(d, field)
        shown = "" if default is None else f" ({default:g})"
        p.add_argument(f"--{flag}", dest=field, type=float, default=default,
                       help=text + shown)
    p.add_argument("--start-gcode", default=d.start_gcode,
                   help="start G-code, lines split by '\\n' (G28)")
    p.add_argument("--wait-bed-equilibrium", action="store_true",
                   help="add WAIT_BED_EQUILIBRIUM (needs [diff_ab_calibrate])")
    p.add_argument("--printer-cfg", type=Path, metavar="FILE",
                   help="printer.cfg whose [extruder] min_temp..max_temp"
                        " --hotend-temp must be within (refused outside it)")
    p.set_defaults(func=run_pylons)


def pylon_options_from_args(args) -> pylons.PylonOptions:
    distances = [args.d1, args.d2] + [getattr(args, f"d{k}") for k in EXTRA_DISTANCES
                                      if getattr(args, f"d{k}") is not None]
    fields = {f.name for f in pylons.PylonOptions.__dataclass_fields__.values()}
    values = {name: getattr(args, name) for name in fields if hasattr(args, name)}
    values.update(kinematics=args.kinematics, distances_mm=tuple(distances),
                  start_gcode=args.start_gcode,
                  wait_bed_equilibrium=args.wait_bed_equilibrium)
    return pylons.PylonOptions(**values)


def run_pylons(args) -> int:
    try:
        options = pylon_options_from_args(args)
    except FlowloopError as e:
        raise with_flags(e, PYLON_OPTIONS) from None
    note = check_part_temp(args.printer_cfg, options.hotend_temp_c,
                           "--hotend-temp")
    if note is not None:
        print(note, file=sys.stderr)
    text = pylons.render(options)
    if args.output == "-":
        sys.stdout.write(text)
        return 0
    try:
        Path(args.output).write_text(text)
    except OSError as e:
        raise FlowloopError(f"cannot write {args.output}: {e.strerror}") from None
    placed = pylons.pylons(options)
    print(f"wrote {args.output}: {len(placed)} pylons, "
          f"D = {', '.join(f'{v:g}' for v in options.distances_mm)} mm, "
          f"{options.kinematics}")
    return 0
