"""`flowloop annotate`: write the flow a G-code file will demand into it, ahead
of time, as AUTOTEMP_FLOW commands (flowloop.gcode.annotate)."""

from __future__ import annotations

from pathlib import Path

from ..gcode.annotate import (
    DEFAULT_LEAD_S,
    DEFAULT_WINDOW_S,
    READAHEAD_S,
    AnnotateSettings,
    annotate_file,
)
from ..gcode.planner import PrinterLimits, limits_from_config
from ..host.klipper_config import read_config


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "annotate", help="write the flow a G-code file will demand into it",
        description="Plan a G-code file as Klipper runs it and insert "
                    "AUTOTEMP_FLOW commands announcing the peak flow of each "
                    "window of print time, early enough for a hotend to heat "
                    "before the flow arrives. Profile-independent. A file "
                    "annotated already is left as it is.")
    p.add_argument("gcode", type=Path, metavar="IN.gcode", help="G-code file")
    p.add_argument("-o", "--output", type=Path, metavar="OUT.gcode",
                   help="write here (default: annotate IN.gcode in place)")
    p.add_argument("--printer-cfg", type=Path, metavar="FILE",
                   help="printer.cfg whose [printer], [extruder], "
                        "[firmware_retraction] and [gcode_arcs] limits the plan "
                        "uses (default: Klipper's defaults, max_velocity 300, "
                        "max_accel 3000)")
    p.add_argument("--lead", type=float, default=DEFAULT_LEAD_S, metavar="S",
                   help=f"seconds before a flow that Klipper reads its "
                        f"announcement (placed {READAHEAD_S:g} s less ahead in "
                        f"print time; default {DEFAULT_LEAD_S:g})")
    p.add_argument("--window", type=float, default=DEFAULT_WINDOW_S, metavar="S",
                   help=f"length of the windows whose peak flow is announced "
                        f"(default {DEFAULT_WINDOW_S:g})")
    p.set_defaults(func=run)


def run(args) -> int:
    settings = AnnotateSettings(lead_s=args.lead, window_s=args.window)
    limits = (limits_from_config(read_config(args.printer_cfg))
              if args.printer_cfg else PrinterLimits())
    out = args.output if args.output is not None else args.gcode
    summary = annotate_file(args.gcode, out, limits, settings)
    if not summary.annotated:
        peak = (f", peak flow {summary.peak_flow_mm3_s:.1f} mm^3/s"
                if summary.windows else "")
        print(f"{args.gcode}: annotated already{peak}, unchanged"
              + (f" (copied to {out})" if out != args.gcode else ""))
        return 0
    minutes, seconds = divmod(round(summary.print_time_s), 60)
    print(f"{out}: {summary.windows} {'window' if summary.windows == 1 else 'windows'}"
          f", peak flow {summary.peak_flow_mm3_s:.1f} mm^3/s, print time "
          f"{minutes // 60}:{minutes % 60:02d}:{seconds:02d} (lead {settings.lead_s:g}"
          f" s, window {settings.window_s:g} s)")
    return 0
