"""The real-print measurement part: a tall solid bar printed ever faster.

ddPrint's real-print measurement prints a part whose speed rises a few
percent per layer until the feeder slips; the flow and temperature at the
layer where grip fell below the limit give the real-print line. The part:
a solid bar (long walls, full infill in lines along its length, thin
layers), each layer `rise` faster than the one before, from the speed that
gives start_flow up to the speed that gives max_flow (then held there).

Each layer begins with `SET_PRINT_STATS_INFO CURRENT_LAYER=n` and a comment
with its speed and volumetric flow, so a watcher (MEASURE_MATERIAL_PROFILE
_PRINT, or a person at the console) knows the flow of the layer printing.
The geometry is computed here; templates/measure_part.gcode.j2 writes it.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import List, Tuple

import jinja2

from .. import __version__
from ..errors import FlowloopError
from . import bounds

TEMPLATE_DIR = Path(__file__).resolve().parent / "templates"
TEMPLATE_NAME = "measure_part.gcode.j2"
MAX_LAYERS = 1000
BED_MARGIN_MM = 5.0

@dataclasses.dataclass(frozen=True)
class PartOptions:
    length_mm: float = 100.0        # the bar's long walls
    width_mm: float = 8.0
    height_mm: float = 40.0
    nozzle_diameter_mm: float = 0.4
    line_width_mm: float = 0.45
    layer_height_mm: float = 0.15   # thin: flow comes from speed, not section
    filament_diameter_mm: float = 1.75
    start_flow_mm3_s: float = 3.0
    max_flow_mm3_s: float = 30.0
    rise: float = 0.04              # each layer this much faster
    first_layer_speed_mm_s: float = 20.0
    max_speed_mm_s: float = 300.0   # the printer's: flow stops rising there
    travel_speed_mm_s: float = 150.0
    hotend_temp_c: float = 210.0
    bed_temp_c: float = 60.0
    bed_size_x_mm: float = 220.0
    bed_size_y_mm: float = 220.0

    def __post_init__(self):
        bounds.check_options(self)
        # the rest (flows, the rise) only need to be above 0
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if field.name not in bounds.OPTIONS \
                    and not (math.isfinite(value) and value > 0):
                raise FlowloopError(f"{field.name} must be a number above 0, "
                                    f"got {value}")
        if self.layer_height_mm > 0.8 * self.nozzle_diameter_mm:
            raise FlowloopError(
                f"layer_height_mm {self.layer_height_mm:g} is more than 80 % "
                f"of the nozzle ({self.nozzle_diameter_mm:g} mm)")
        if not self.nozzle_diameter_mm <= self.line_width_mm \
                <= 2 * self.nozzle_diameter_mm:
            raise FlowloopError(f"line_width_mm {self.line_width_mm:g} must be "
                                f"within 1..2 nozzle diameters")
        if self.max_flow_mm3_s < self.start_flow_mm3_s:
            raise FlowloopError("max_flow_mm3_s must not be below "
                                "start_flow_mm3_s")
        if self.rise > 0.5:
            raise FlowloopError(f"rise {self.rise:g} is more than 50 % per layer")
        if self.width_mm < 2 * self.line_width_mm:
            raise FlowloopError("width_mm must hold at least two lines")
        if self.length_mm + 2 * BED_MARGIN_MM > self.bed_size_x_mm \
                or self.width_mm + 2 * BED_MARGIN_MM > self.bed_size_y_mm:
            raise FlowloopError(f"a {self.length_mm:g} x {self.width_mm:g} mm "
                                f"part does not fit the bed")
        if self.layers() > MAX_LAYERS:
            raise FlowloopError(f"{self.layers()} layers: at most {MAX_LAYERS}"
                                f" (a thicker layer or a lower part)")

    def layers(self) -> int:
        return max(1, round(self.height_mm / self.layer_height_mm))

    def section_mm2(self) -> float:
        """The extruded line's cross-section (a rounded rectangle, as slicers
        compute it)."""
        h, w = self.layer_height_mm, self.line_width_mm
        return (w - h) * h + math.pi * (h / 2) ** 2

    def e_per_mm(self) -> float:
        return self.section_mm2() / (math.pi * (self.filament_diameter_mm / 2) ** 2)


@dataclasses.dataclass(frozen=True)
class Layer:
    number: int
    z_mm: float
    speed_mm_s: float
    flow_mm3_s: float


def layer_plan(o: PartOptions) -> List[Layer]:
    """Every layer's height, speed and flow: the first at the first-layer
    speed, then from start_flow rising by `rise` per layer, held at max_flow
    (or at max_speed_mm_s, if that comes first)."""
    section = o.section_mm2()
    out = []
    for n in range(1, o.layers() + 1):
        if n == 1:
            speed = min(o.first_layer_speed_mm_s, o.start_flow_mm3_s / section)
        else:
            flow = min(o.max_flow_mm3_s,
                       o.start_flow_mm3_s * (1 + o.rise) ** (n - 2))
            speed = min(o.max_speed_mm_s, flow / section)
        out.append(Layer(n, round(n * o.layer_height_mm, 4), speed,
                         speed * section))
    return out


def _lines(o: PartOptions, layer: int) -> List[Tuple[Tuple[float, float],
                                                    Tuple[float, float]]]:
    """The layer's extrusion as (start, end) segments: a perimeter loop,
    then infill lines along the length, alternating direction."""
    x0 = (o.bed_size_x_mm - o.length_mm) / 2
    y0 = (o.bed_size_y_mm - o.width_mm) / 2
    half = o.line_width_mm / 2
    a, b = (x0 + half, y0 + half), (x0 + o.length_mm - half, y0 + o.width_mm - half)
    loop = [a, (b[0], a[1]), b, (a[0], b[1]), a]
    segments = list(zip(loop[:-1], loop[1:]))
    # Lines as far apart as their section fills (a slicer's spacing), evenly
    # between the perimeter's long sides: the bar is solid.
    spacing = o.section_mm2() / o.layer_height_mm
    count = max(0, round((b[1] - a[1]) / spacing) - 1)
    left, right = a[0] + spacing, b[0] - spacing
    for i in range(count):
        y = a[1] + (b[1] - a[1]) * (i + 1) / (count + 1)
        start, end = ((left, y), (right, y)) if (i + layer) % 2 else \
            ((right, y), (left, y))
        segments.append((start, end))
    return segments


def render(o: PartOptions) -> str:
    """The part's G-code."""
    layers = []
    for layer in layer_plan(o):
        moves = []
        for start, end in _lines(o, layer.number):
            length = math.dist(start, end)
            moves.append((start, end, length * o.e_per_mm()))
        layers.append((layer, moves))
    env = jinja2.Environment(loader=jinja2.FileSystemLoader(str(TEMPLATE_DIR)),
                             keep_trailing_newline=True, trim_blocks=True,
                             lstrip_blocks=True, undefined=jinja2.StrictUndefined)
    return env.get_template(TEMPLATE_NAME).render(
        o=o, layers=layers, version=__version__,
        total_layers=len(layers))


def write(o: PartOptions, path: Path) -> int:
    """Write the part to path (whole or not at all); the number of layers."""
    text = render(o)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)
    return o.layers()
