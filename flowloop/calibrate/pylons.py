"""The differential A/B calibration part: rows of solid, symmetric pylons.

Each row holds one pylon per nominal distance plus the first: pylon 1 and
pylon k+1 measure D_k outside to outside along the row. On CoreXY the A row
lies on the x = y diagonal and the B row on x = -y (through the centre, the
middle left empty so the rows never touch); on a cartesian printer the rows
lie along X and Y. A pylon is a rectangle W (along the row) by depth
(across it), filled solid with concentric loops printed outer loop first,
seams on the side faces (never on the measured faces), alternating side
every layer so the pylon stays symmetric.

The geometry is computed here; flowloop/calibrate/templates/ab_pylons.gcode.j2 lays
out the G-code.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import jinja2

from .. import __version__
from ..errors import FlowloopError
from ..gcode import bounds
from . import diff_ab

TEMPLATE_DIR = Path(__file__).resolve().parent / "templates"
TEMPLATE_NAME = "ab_pylons.gcode.j2"
MIN_GAP_LINES = 2.0      # free space between neighbouring pylons, in line widths
BED_MARGIN_MM = 5.0

Point = Tuple[float, float]

@dataclasses.dataclass(frozen=True)
class PylonOptions:
    kinematics: str = "corexy"
    distances_mm: Tuple[float, ...] = diff_ab.NOMINAL_DISTANCES_MM  # D1, D2[, D3..]
    pylon_width_mm: float = 4.0      # W: along the row, the measured size
    pylon_depth_mm: float = 10.0     # across the row
    pylon_height_mm: float = 10.0
    bed_size_x_mm: float = 250.0
    bed_size_y_mm: float = 250.0
    centre_x_mm: Optional[float] = None   # default: middle of the bed
    centre_y_mm: Optional[float] = None
    nozzle_diameter_mm: float = 0.4
    line_width_mm: float = 0.5
    layer_height_mm: float = 0.2
    filament_diameter_mm: float = 1.75
    extrusion_multiplier: float = 0.95  # never over-extrude the pylons
    hotend_temp_c: float = 215.0
    bed_temp_c: float = 60.0
    print_speed_mm_s: float = 60.0
    first_layer_speed_mm_s: float = 20.0   # capped at print_speed_mm_s
    travel_speed_mm_s: float = 150.0
    # None: the printer's own max_accel. Klipper accepts a SET_VELOCITY_LIMIT
    # above the configured max_accel, so the file sets one only when asked.
    accel_mm_s2: Optional[float] = None
    retract_mm: float = 0.8
    retract_speed_mm_s: float = 35.0
    z_hop_mm: float = 0.4
    start_gcode: str = "G28"
    wait_bed_equilibrium: bool = False

    def __post_init__(self):
        validate(self)

    @property
    def first_layer_speed(self) -> float:
        """First layer and prime line: never faster than the print speed."""
        return min(self.first_layer_speed_mm_s, self.print_speed_mm_s)

    @property
    def centre(self) -> Point:
        cx = self.bed_size_x_mm / 2 if self.centre_x_mm is None else self.centre_x_mm
        cy = self.bed_size_y_mm / 2 if self.centre_y_mm is None else self.centre_y_mm
        return (cx, cy)


def _positive(name: str, value: float, maximum: float = math.inf) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value)
            and 0.0 < value <= maximum):
        limit = ("a finite number above 0" if maximum == math.inf
                 else f"a number in (0, {maximum:g}]")
        raise FlowloopError(f"{name} must be {limit}, got {value}")


def validate(o: PylonOptions) -> None:
    if o.kinematics not in diff_ab.KINEMATICS:
        raise FlowloopError(
            f"kinematics must be corexy or cartesian, not '{o.kinematics}'")
    bounds.check_options(o)
    for name in ("centre_x_mm", "centre_y_mm"):
        value = getattr(o, name)
        if value is not None and not math.isfinite(value):
            raise FlowloopError(f"{name} must be a finite number, got {value}")
    _positive("extrusion_multiplier", o.extrusion_multiplier, 1.5)
    if o.layer_height_mm > 0.8 * o.nozzle_diameter_mm:
        raise FlowloopError("layer height must be at most 0.8 x nozzle diameter")
    if not o.nozzle_diameter_mm <= o.line_width_mm <= 2.0 * o.nozzle_diameter_mm:
        raise FlowloopError("line width must be between 1 and 2 nozzle diameters")
    if o.pylon_width_mm < 2 * o.line_width_mm:
        raise FlowloopError("pylon width must be at least two line widths")
    if o.pylon_depth_mm < o.pylon_width_mm:
        raise FlowloopError("pylon depth must be at least the pylon width")
    if o.pylon_height_mm < 2 * o.layer_height_mm:
        raise FlowloopError("pylon height must be at least two layers")
    if len(o.distances_mm) < 2:
        raise FlowloopError("need at least two distances (D1 and D2)")
    distances = list(o.distances_mm)
    for k, d in enumerate(distances, 1):
        _positive(f"D{k}", d, 1000.0)
    if distances != sorted(set(distances)):
        raise FlowloopError("distances must increase: D1 < D2 < ...")
    gap = distances[0] - 2 * o.pylon_width_mm
    if gap < MIN_GAP_LINES * o.line_width_mm:
        raise FlowloopError(
            f"D1 = {distances[0]:g} mm leaves a gap of {gap:g} mm between two "
            f"{o.pylon_width_mm:g} mm pylons; make D1 at least "
            f"{2 * o.pylon_width_mm + MIN_GAP_LINES * o.line_width_mm:g} mm")
    for low, high in zip(distances, distances[1:]):
        if high - low - o.pylon_width_mm < MIN_GAP_LINES * o.line_width_mm:
            raise FlowloopError(f"distances {low:g} and {high:g} mm put two pylons "
                                f"too close together")


# --- geometry --------------------------------------------------------------

def row_directions(kinematics: str) -> Dict[str, Point]:
    """Unit vectors of the A and B rows."""
    if kinematics == "corexy":
        r = math.sqrt(0.5)
        return {"a": (r, r), "b": (r, -r)}
    return {"a": (1.0, 0.0), "b": (0.0, 1.0)}


def along_row_positions(distances_mm: Sequence[float], width_mm: float) -> List[float]:
    """Centre of each pylon along the row, 0 in the middle of its widest gap.

    The two rows cross at 0, so the crossing falls where no pylon stands.
    """
    s = [0.0] + [d - width_mm for d in distances_mm]
    gaps = [(high - low, (low + high) / 2) for low, high in zip(s, s[1:])]
    middle = max(gaps, key=lambda g: g[0])[1]
    return [v - middle for v in s]


@dataclasses.dataclass(frozen=True)
class Pylon:
    name: str           # "A1", "A2", ..., "B1", ...
    axis: str
    centre: Point
    along: Point        # unit vector along the row
    across: Point

    def corners(self, width: float, depth: float) -> List[Point]:
        return [self.at(sa * width / 2, sb * depth / 2)
                for sa, sb in ((1, 1), (1, -1), (-1, -1), (-1, 1))]

    def at(self, u: float, v: float) -> Point:
        return (self.centre[0] + u * self.along[0] + v * self.across[0],
                self.centre[1] + u * self.along[1] + v * self.across[1])


def pylons(o: PylonOptions) -> List[Pylon]:
    cx, cy = o.centre
    out = []
    for axis, (ux, uy) in row_directions(o.kinematics).items():
        across = (-uy, ux)
        for i, s in enumerate(along_row_positions(o.distances_mm, o.pylon_width_mm)):
            out.append(Pylon(f"{axis.upper()}{i + 1}", axis, (cx + s * ux, cy + s * uy),
                             (ux, uy), across))
    _check_layout(o, out)
    return out


def _check_layout(o: PylonOptions, placed: List[Pylon]) -> None:
    for p in placed:
        for x, y in p.corners(o.pylon_width_mm, o.pylon_depth_mm):
            if not (BED_MARGIN_MM <= x <= o.bed_size_x_mm - BED_MARGIN_MM
                    and BED_MARGIN_MM <= y <= o.bed_size_y_mm - BED_MARGIN_MM):
                raise FlowloopError(
                    f"pylon {p.name} at ({p.centre[0]:.1f}, {p.centre[1]:.1f}) does "
                    f"not fit on a {o.bed_size_x_mm:g} x {o.bed_size_y_mm:g} mm bed "
                    f"(5 mm margin); lower D2 or move the centre")
    # Pylons of the two rows must stay apart: compare bounding circles.
    radius = math.hypot(o.pylon_width_mm, o.pylon_depth_mm) / 2
    clearance = 2 * radius + MIN_GAP_LINES * o.line_width_mm
    rows_a = [p for p in placed if p.axis == "a"]
    rows_b = [p for p in placed if p.axis == "b"]
    for pa in rows_a:
        for pb in rows_b:
            if math.dist(pa.centre, pb.centre) < clearance:
                raise FlowloopError(f"pylons {pa.name} and {pb.name} would touch "
                                    f"where the rows cross; use larger gaps between "
                                    f"the distances or smaller pylons")


def pylon_loops(o: PylonOptions) -> Tuple[List[Tuple[float, float]], Optional[float]]:
    """Concentric loop half-sizes (along, across) outer first, and the
    width of a centre line filling what is left (None when nothing is)."""
    lw = o.line_width_mm
    loops = []
    a = o.pylon_width_mm / 2 - lw / 2
    b = o.pylon_depth_mm / 2 - lw / 2
    while a >= lw / 2 - 1e-9:
        loops.append((a, b))
        a -= lw
        b -= lw
    left = (loops[-1][0] - lw / 2) * 2   # unfilled width inside the last loop
    centre_line = left if left > 0.05 * lw else None
    return loops, centre_line


@dataclasses.dataclass(frozen=True)
class Path2D:
    """One extruded path: reach start, then extrude to each point by e_mm."""
    start: Point
    moves: Tuple[Tuple[Point, float], ...]   # (end point, filament mm)


def _path(points: Sequence[Point], e_mm_per_mm: float) -> Path2D:
    moves = []
    for here, there in zip(points, points[1:]):
        moves.append((there, e_mm_per_mm * math.dist(here, there)))
    return Path2D(points[0], tuple(moves))


def layer_paths(o: PylonOptions, pylon: Pylon, layer: int) -> List[Path2D]:
    e_line = e_per_mm(o, o.line_width_mm)
    loops, centre_width = pylon_loops(o)
    side = 1.0 if layer % 2 == 0 else -1.0      # seam side alternates
    paths = []
    for a, b in loops:
        seq = [(0.0, side * b), (a, side * b), (a, -side * b), (-a, -side * b),
               (-a, side * b), (0.0, side * b)]
        paths.append(_path([pylon.at(u, v) for u, v in seq], e_line))
    if centre_width is not None:
        a, b = loops[-1]
        half = b - o.line_width_mm / 2
        paths.append(_path([pylon.at(0.0, side * half), pylon.at(0.0, -side * half)],
                           e_per_mm(o, centre_width)))
    return paths


def e_per_mm(o: PylonOptions, width_mm: float) -> float:
    area = math.pi * (o.filament_diameter_mm / 2) ** 2
    return width_mm * o.layer_height_mm * o.extrusion_multiplier / area


# --- rendering ---------------------------------------------------------------

def _environment() -> jinja2.Environment:
    # Plain Environment features only: the template renders the same under
    # Klipper's Jinja2 2.11.3 and Moonraker's 3.x.
    return jinja2.Environment(loader=jinja2.FileSystemLoader(str(TEMPLATE_DIR)),
                              trim_blocks=True, lstrip_blocks=True,
                              keep_trailing_newline=True,
                              undefined=jinja2.StrictUndefined)


def render(o: PylonOptions) -> str:
    placed = pylons(o)
    layer_count = max(2, int(round(o.pylon_height_mm / o.layer_height_mm)))
    layers = []
    for i in range(layer_count):
        layers.append({
            "index": i,
            "z": (i + 1) * o.layer_height_mm,
            "speed_mm_s": o.first_layer_speed if i == 0 else o.print_speed_mm_s,
            "pylons": [{"name": p.name, "paths": layer_paths(o, p, i)} for p in placed],
        })
    measure = []
    for axis in ("a", "b"):
        for k, d in enumerate(o.distances_mm, start=1):
            measure.append({"name": f"{axis.upper()}{k}",
                            "between": f"{axis.upper()}1 and {axis.upper()}{k + 1}",
                            "nominal": d})
    labels = {"corexy": {"a": "A diagonal (x = y, motor A)",
                         "b": "B diagonal (x = -y, motor B)"},
              "cartesian": {"a": "X axis", "b": "Y axis"}}[o.kinematics]
    prime_y = BED_MARGIN_MM / 2
    prime_x = (max(BED_MARGIN_MM, o.centre[0] - 40.0),
               min(o.bed_size_x_mm - BED_MARGIN_MM, o.centre[0] + 40.0))
    template = _environment().get_template(TEMPLATE_NAME)
    return template.render(
        o=o, version=__version__, layers=layers, pylons=placed, measure=measure,
        labels=labels, centre=o.centre, prime_y=prime_y, prime_x=prime_x,
        prime_e=e_per_mm(o, o.line_width_mm) * 1.5 * (prime_x[1] - prime_x[0]),
        start_lines=start_lines(o.start_gcode))


def start_lines(start_gcode: str) -> List[str]:
    """Start G-code lines; a literal '\\n' (from a shell) also splits."""
    text = start_gcode.replace("\\n", "\n")
    return [line.strip() for line in text.splitlines() if line.strip()]
