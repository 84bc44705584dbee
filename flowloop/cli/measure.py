"""`flowloop measure-part`: the real-print measurement part as a G-code file."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

from ..errors import FlowloopError
from ..gcode import measure_part
from ..host.klipper_config import check_part_temp
from .flags import with_flags

# flag -> PartOptions field, help
OPTIONS = (
    ("nozzle", "nozzle_diameter_mm", "nozzle diameter, mm"),
    ("filament-diameter", "filament_diameter_mm", "filament diameter, mm"),
    ("line-width", "line_width_mm", "line width, mm"),
    ("layer-height", "layer_height_mm", "layer height, mm (thin: flow from speed)"),
    ("start-flow", "start_flow_mm3_s", "flow of layer 2, mm^3/s"),
    ("max-flow", "max_flow_mm3_s", "flow where the rise stops, mm^3/s"),
    ("rise", "rise", "speed rise per layer (0.04 = 4 %%)"),
    ("max-speed", "max_speed_mm_s", "the printer's max_velocity, mm/s"),
    ("temp", "hotend_temp_c", "hotend temperature, degC"),
    ("bed-temp", "bed_temp_c", "bed temperature, degC"),
    ("length", "length_mm", "bar length, mm"),
    ("width", "width_mm", "bar width, mm"),
    ("height", "height_mm", "bar height, mm"),
    ("bed-x", "bed_size_x_mm", "bed size in X, mm"),
    ("bed-y", "bed_size_y_mm", "bed size in Y, mm"),
)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "measure-part", help="G-code of the real-print measurement part",
        description="A tall solid bar printed a few percent faster each layer; "
                    "the layer where the flow sensor's grip falls below the "
                    "limit gives the real-print line (docs/measure_profile.md).")
    p.add_argument("-o", "--output", required=True, type=Path, metavar="FILE",
                   help="the G-code file to write")
    defaults = measure_part.PartOptions()
    for flag, field, text in OPTIONS:
        default = getattr(defaults, field)
        p.add_argument(f"--{flag}", dest=field, type=float, default=default,
                       help=f"{text} ({default:g})")
    p.add_argument("--printer-cfg", type=Path, metavar="FILE",
                   help="printer.cfg whose [extruder] min_temp..max_temp --temp"
                        " must be within (refused outside it)")
    p.set_defaults(func=run)


def run(args) -> int:
    fields = {f.name for f in dataclasses.fields(measure_part.PartOptions)}
    try:
        options = measure_part.PartOptions(
            **{k: v for k, v in vars(args).items() if k in fields})
    except FlowloopError as e:
        raise with_flags(e, OPTIONS) from None
    note = check_part_temp(args.printer_cfg, options.hotend_temp_c, "--temp")
    if note is not None:
        print(note, file=sys.stderr)
    layers = measure_part.write(options, args.output)
    plan = measure_part.layer_plan(options)
    print(f"wrote {args.output}: {layers} layers, flow {plan[1].flow_mm3_s:.2f}"
          f" to {plan[-1].flow_mm3_s:.2f} mm^3/s" if len(plan) > 1 else
          f"wrote {args.output}: {layers} layer")
    return 0
