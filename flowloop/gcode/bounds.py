"""What a G-code file flowloop writes may ask of a printer.

One range for each kind of number the generated parts (measure_part, the
calibration pylons) write into G-code: temperatures, speeds, acceleration,
sizes. The generators check their options against these (check_options),
so the `flowloop` command and any other caller are refused alike, with the
option named first.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Dict

from ..errors import FlowloopError


@dataclasses.dataclass(frozen=True)
class Bound:
    low: float
    high: float
    unit: str
    low_included: bool = True   # False: above low (a speed of 0 never ends)

    def check(self, name: str, value: Any) -> float:
        """value as a float, or a one-line error naming `name`."""
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if not (number and math.isfinite(value) and value <= self.high
                and (value >= self.low if self.low_included else value > self.low)):
            shown = f"{value:g}" if number else repr(value)
            raise FlowloopError(f"{name} must be {self.text()}, got {shown}")
        return float(value)

    def text(self) -> str:
        if self.low_included:
            return f"a number from {self.low:g} to {self.high:g} {self.unit}"
        return f"a number above {self.low:g} and at most {self.high:g} {self.unit}"


HOTEND_TEMP_C = Bound(150.0, 320.0, "C")    # what a PLA..PC hotend prints at
BED_TEMP_C = Bound(0.0, 130.0, "C")         # 0: off
SPEED_MM_S = Bound(0.0, 1000.0, "mm/s", low_included=False)
ACCEL_MM_S2 = Bound(0.0, 100000.0, "mm/s^2", low_included=False)
NOZZLE_DIAMETER_MM = Bound(0.1, 2.0, "mm")
FILAMENT_DIAMETER_MM = Bound(1.0, 3.5, "mm")   # 1.75, 2.85 and 3 mm filament
# A length on the bed or up Z: a part, a bed, a line, a layer.
SIZE_MM = Bound(0.0, 2000.0, "mm", low_included=False)
RETRACT_MM = Bound(0.0, 10.0, "mm")         # a retraction or a Z hop; 0: none

# Every option a generator writes into G-code, by its name (the same name
# means the same thing in every generator's options).
OPTIONS: Dict[str, Bound] = {
    **{name: SIZE_MM for name in (
        "length_mm", "width_mm", "height_mm", "pylon_width_mm", "pylon_depth_mm",
        "pylon_height_mm", "bed_size_x_mm", "bed_size_y_mm", "line_width_mm",
        "layer_height_mm")},
    **{name: SPEED_MM_S for name in (
        "print_speed_mm_s", "first_layer_speed_mm_s", "max_speed_mm_s",
        "travel_speed_mm_s", "retract_speed_mm_s")},
    "nozzle_diameter_mm": NOZZLE_DIAMETER_MM,
    "filament_diameter_mm": FILAMENT_DIAMETER_MM,
    "accel_mm_s2": ACCEL_MM_S2,
    "retract_mm": RETRACT_MM, "z_hop_mm": RETRACT_MM,
    "hotend_temp_c": HOTEND_TEMP_C, "bed_temp_c": BED_TEMP_C,
}


def check_options(options: Any) -> None:
    """Every field of a generator's options (a dataclass) that OPTIONS bounds,
    checked; a field left None (the printer's own value) is not written."""
    for field in dataclasses.fields(options):
        value = getattr(options, field.name)
        if field.name in OPTIONS and value is not None:
            OPTIONS[field.name].check(field.name, value)
