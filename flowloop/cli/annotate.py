"""`flowloop annotate`: write the flow a G-code file will demand into it, ahead
of time, as AUTOTEMP_FLOW commands (flowloop.gcode.annotate)."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import List

from ..control.hotend import HotendParams
from ..errors import FlowloopError
from ..gcode.annotate import (
    DEFAULT_LEAD_S,
    DEFAULT_WINDOW_S,
    READAHEAD_S,
    AnnotateSettings,
    annotate_file,
)
from ..gcode.melt_window import MELT_TIME_S, melt_window_from_config
from ..gcode.reference_planner import PrinterLimits, limits_from_config
from .flags import with_flags
from .paths import refuse_overwriting

DEFAULT_HOTEND = HotendParams()
# material.profile.DEFAULT_WORKING_POINT, for --working-point's help: that
# module (and msgspec) is imported only for --bake, not at every upload's
# start-up (tests/unit/test_annotate.py checks that they agree)
DEFAULT_WORKING_POINT = 0.5
# --bake's hotend options: (flag, HotendParams field)
HOTEND_FLAGS = (("time-constant", "time_constant_s"), ("dead-time", "dead_time_s"),
                ("heater-power", "max_power_w"))


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
                        "max_accel 3000); with --bake, every target stays "
                        "within its [extruder] min_temp..max_temp")
    p.add_argument("--lead", type=float, default=DEFAULT_LEAD_S, metavar="S",
                   help=f"seconds before a flow that Klipper reads its "
                        f"announcement (placed {READAHEAD_S:g} s less ahead in "
                        f"print time; default {DEFAULT_LEAD_S:g})")
    p.add_argument("--window", type=float, default=DEFAULT_WINDOW_S, metavar="S",
                   help=f"length of the windows whose peak flow is announced "
                        f"(default {DEFAULT_WINDOW_S:g})")
    p.add_argument("--melt-window", type=float, default=None, metavar="S",
                   help=f"the time the flow is averaged over: bursts shorter"
                        f" than it are announced as their mean (your hotend's"
                        f" melt lag; docs/autotemp.md; default: --printer-cfg's"
                        f" [autotemp] melt_window, else {MELT_TIME_S:g})")
    p.add_argument("--bake", type=Path, metavar="PROFILE.json",
                   help="write autotemp's targets for this material profile as"
                        " plain M104 S<target> instead of AUTOTEMP_FLOW (for a"
                        " printer without [autotemp]); needs -o")
    p.add_argument("--working-point", type=float, default=None, metavar="WP",
                   help=f"with --bake: 0 (real print) to 1 (into air), "
                        f"default {DEFAULT_WORKING_POINT:g}")
    p.add_argument("--time-constant", type=float, metavar="S",
                   default=DEFAULT_HOTEND.time_constant_s,
                   help=f"with --bake: the hotend's time constant "
                        f"(default {DEFAULT_HOTEND.time_constant_s:g})")
    p.add_argument("--dead-time", type=float, metavar="S",
                   default=DEFAULT_HOTEND.dead_time_s,
                   help=f"with --bake: the hotend's dead time "
                        f"(default {DEFAULT_HOTEND.dead_time_s:g})")
    p.add_argument("--heater-power", type=float, metavar="W",
                   default=DEFAULT_HOTEND.max_power_w,
                   help=f"with --bake: the heater's power "
                        f"(default {DEFAULT_HOTEND.max_power_w:g})")
    p.add_argument("--plot", type=Path, metavar="TIMELINE.svg", nargs="?",
                   const=True, default=None,
                   help="with --bake: draw the timeline (targets, modelled "
                        "nozzle, demanded flow and melt capacity) as SVG "
                        "(default: OUT.gcode with .svg)")
    p.set_defaults(func=run)


def run(args) -> int:
    config = None
    melt_s = args.melt_window
    if args.printer_cfg:
        from ..host.klipper_config import read_config
        config = read_config(args.printer_cfg)
        limits = limits_from_config(config)
        if melt_s is None:
            # the printer's own window, where its [autotemp] sets one
            try:
                melt_s = melt_window_from_config(config)
            except FlowloopError as e:
                raise FlowloopError(f"{args.printer_cfg}: {e}") from None
    else:
        limits = PrinterLimits()
    settings = AnnotateSettings(lead_s=args.lead, window_s=args.window,
                                melt_s=MELT_TIME_S if melt_s is None else melt_s)
    if args.bake is not None:
        return run_bake(args, settings, limits, config)
    if args.plot is not None or args.working_point is not None:
        raise FlowloopError("--plot and --working-point need --bake PROFILE.json")
    # -o IN.gcode itself is the default: annotate in place
    refuse_overwriting([("-o", args.output)],
                       [("--printer-cfg", args.printer_cfg)])
    out = args.output if args.output is not None else args.gcode
    summary = annotate_file(args.gcode, out, limits, settings)
    if not summary.annotated:
        peak = (f", peak flow {summary.peak_flow_mm3_s:.1f} mm^3/s"
                if summary.windows else "")
        print(f"{args.gcode}: annotated already{peak}, unchanged"
              + (f" (copied to {out})" if out != args.gcode else ""))
        return 0
    if summary.windows == 0:
        _warn_nothing_extrudes(args.gcode)
    minutes, seconds = divmod(round(summary.print_time_s), 60)
    print(f"{out}: {summary.windows} {'window' if summary.windows == 1 else 'windows'}"
          f", peak flow {summary.peak_flow_mm3_s:.1f} mm^3/s, print time "
          f"{minutes // 60}:{minutes % 60:02d}:{seconds:02d} (lead {settings.lead_s:g}"
          f" s, window {settings.window_s:g} s, melt window {settings.melt_s:g} s)")
    return 0


def _warn_nothing_extrudes(path: Path) -> None:
    # an empty file, or the wrong one (a start script): say so, not just "0"
    print(f"flowloop annotate: warning: {path}: no move extrudes: nothing to"
          f" announce", file=sys.stderr)


def run_bake(args, settings: AnnotateSettings, limits: PrinterLimits,
             config=None) -> int:
    # imported here: plain annotation needs neither profiles nor plots
    from ..cli.profile import load
    from ..gcode.bake import bake_file, timeline_svg
    from ..host.klipper_config import heater_range
    from ..material.active import working_point_arg
    from ..material.profile import DEFAULT_WORKING_POINT
    if args.output is None:
        raise FlowloopError("--bake needs -o OUT.gcode (a baked file is for one"
                            " profile; the slicer's file stays as it is)")
    plot = (args.output.with_suffix(".svg") if args.plot is True else args.plot)
    refuse_overwriting([("-o", args.output), ("--plot", plot)],
                       [("IN.gcode", args.gcode), ("--bake", args.bake),
                        ("--printer-cfg", args.printer_cfg)])
    try:
        params = HotendParams(time_constant_s=args.time_constant,
                              dead_time_s=args.dead_time,
                              max_power_w=args.heater_power)
    except FlowloopError as e:
        raise with_flags(e, HOTEND_FLAGS) from None
    wp = working_point_arg(DEFAULT_WORKING_POINT if args.working_point is None
                           else args.working_point, "--working-point")
    profile = load(args.bake)
    heater = None if config is None else heater_range(config,
                                                      str(args.printer_cfg))
    result, timeline = bake_file(args.gcode, args.output, profile, wp, params,
                                 limits, settings, heater)
    if result.peak_flow_mm3_s == 0:
        _warn_nothing_extrudes(args.gcode)
    lo = "none" if result.min_target_c is None else f"{result.min_target_c:.0f}"
    hi = "none" if result.max_target_c is None else f"{result.max_target_c:.0f}"
    print(f"{args.output}: {result.commands} M104 for {profile.name} at working"
          f" point {wp:g}, {lo} to {hi} C, peak flow"
          f" {result.peak_flow_mm3_s:.1f} mm^3/s; {result.overridden} slicer M104"
          f" commented out")
    if result.start is not None:
        if result.start.heat_fix is not None:   # what the message below judges
            print(f"  {result.start.heat_fix.message}")
        print(f"  {result.start.message}")
    for line in bake_notes(result, args.printer_cfg, profile, wp):
        print(f"  {line}")
    if result.under_capacity_s > 0:
        print(f"  the modelled hotend melts less than demanded for"
              f" {result.under_capacity_s:.1f} s of the print")
    if plot is not None:
        plot.write_text(timeline_svg(timeline, f"{args.gcode.name}: autotemp"
                                     f" for {profile.name}, WP {wp:g}"))
        print(f"  timeline: {plot}")
    return 0


def bake_notes(result, printer_cfg, profile, wp: float) -> List[str]:
    """What the summary says of the temperature limits: which one bound the
    plan, what to do when the file asks for more than the hotend melts
    there, the file's own targets brought within the heater's range."""
    from ..material.slicer import max_volumetric_speed
    notes = []
    if result.heater is None:
        notes.append("targets not checked against the printer's min_temp/max_temp:"
                     " give --printer-cfg" if printer_cfg is None else
                     f"{printer_cfg} has no [extruder]: targets not checked"
                     f" against its min_temp/max_temp")
    cap = (f"the printer's max_temp {result.cap_c:g} C" if result.capped_by_heater
           else f"the profile's max_temp_c {result.cap_c:g} C")
    if result.capped_by_heater:
        notes.append(f"targets capped at {cap} ({result.heater.source}), below"
                     f" the profile's {profile.bounds.max_temp_c:g} C")
    if result.flat_line is not None:
        notes.append(result.flat_line)
    if result.capped_windows:
        flow = max_volumetric_speed(profile, result.cap_c, wp)
        which = (f"every window with flow ({result.capped_windows}) needs"
                 if result.capped_windows >= result.flow_windows
                 else f"{result.capped_windows} windows need")
        notes.append(f"{which} more than {cap}:"
                     f" clamped there; the hotend melts {flow:.2f} mm^3/s there:"
                     f" slice with a max volumetric speed of {flow:.2f} mm^3/s,"
                     f" or let [flowrate_limiter] hold the flow")
    if result.travel_tail_s:
        from ..report.recorder import duration_text
        notes.append(f"nothing is extruded in the last"
                     f" {duration_text(result.travel_tail_s)} of the print (after"
                     f" {duration_text(result.last_extrusion_s)}): the baked"
                     f" targets fall to their minimum there")
    if result.behind_s > 0.0:
        from ..report.recorder import duration_text
        rise = (f"up to {result.longest_rise_s:.0f} s"
                if math.isfinite(result.longest_rise_s) else "longer")
        notes.append(f"the modelled nozzle is behind the plan for"
                     f" {duration_text(result.behind_s)} of the print: windows"
                     f" are announced {result.lead_s:g} s ahead, and a rise from"
                     f" the profile's minimum to {result.cap_c:g} C takes this"
                     f" hotend {rise}: annotate"
                     f" with --lead {result.lead_needed_s:g}")
    if result.brought_within:
        h = result.heater
        notes.append(f"{result.brought_within} of the file's own M104/M109"
                     f" outside {h.min_temp_c:g}..{h.max_temp_c:g} C"
                     f" ({h.source}) brought within it")
    return notes
