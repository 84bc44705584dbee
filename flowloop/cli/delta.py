"""`flowloop delta-endstops`: delta tower endstops from probe heights, at a desk.

Reads the delta geometry from printer.cfg the way klippy does (SAVE_CONFIG
block included) and solves the three position_endstop values that put every
probed point on the bed (flowloop.calibrate.delta.solve_endstops).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import List

from ..calibrate import delta
from ..errors import FlowloopError
from ..host.klipper_config import read_config
from ..numbers import parse_numbers


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "delta-endstops", help="delta tower endstops from probes near each tower",
        description="Solve the three delta position_endstop values from probed "
                    "points: X,Y is where the toolhead was (as the printer "
                    "believed), Z the toolhead height at which the nozzle touched "
                    "the bed (or the probe triggered). Probe near each tower, and "
                    "the centre; probes opposite the towers also reveal wrong "
                    "tower angles.")
    p.add_argument("--printer-cfg", required=True, type=Path, metavar="FILE",
                   help="printer.cfg of the delta (its [include]s and SAVE_CONFIG "
                        "block are read as klippy reads them)")
    p.add_argument("--probe", action="append", default=[], metavar="X,Y,Z",
                   help="one probed point; give at least 3")
    p.add_argument("--z-offset", default="0", metavar="MM",
                   help="the Z each probe should read on a perfect printer: your "
                        "probe's z_offset, 0 for the nozzle or paper (0)")
    p.add_argument("--json", action="store_true",
                   help="print position_endstop, residual_mm, spread_before_mm "
                        "and spread_after_mm as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    probes = [parse_numbers(text, f"--probe {text}", what="coordinate", count=3)
              for text in args.probe]
    z_offset, = parse_numbers(args.z_offset, "--z-offset", count=1,
                              decimal_comma_refused=True)
    if len(probes) < 3:
        raise FlowloopError(f"need at least 3 --probe points (near each tower),"
                            f" got {len(probes)}")
    geometry = delta.geometry_from_config(read_config(args.printer_cfg))
    solution = delta.solve_endstops(geometry, probes, [z_offset] * len(probes))
    if args.json:
        print(json.dumps(solution.to_json()))
        if solution.geometry_warning:
            print(f"warning: {solution.geometry_warning}", file=sys.stderr)
        return 0
    print("\n".join(report_lines(geometry, probes, solution)))
    return 0


def report_lines(geometry: delta.DeltaGeometry, probes, solution) -> List[str]:
    lines = [f"{len(probes)} probes, delta_radius {geometry.radius:g},"
             f" tower angles {', '.join(f'{a:g}' for a in geometry.angles_deg)}"]
    for i, name in enumerate(delta.TOWERS):
        k = solution.tower_probe_index[i]
        lines.append(
            f"[{name}] position_endstop: {solution.position_endstop[i]:.4f}"
            f"   (was {solution.position_endstop_before[i]:.4f},"
            f" {solution.corrections_mm[i]:+.4f}; probe {k + 1} near it"
            f" {solution.heights_before_mm[k]:+.4f} -> "
            f"{solution.heights_after_mm[k]:+.4f} mm)")
    lines.append(f"spread {solution.spread_before_mm:.4f} mm before, "
                 f"{solution.spread_after_mm:.4f} mm predicted after "
                 f"(residual {solution.residual_mm:.4f} mm)")
    if solution.geometry_warning:
        lines.append(f"warning: {solution.geometry_warning}")
    return lines
