"""What a G-code file flowloop writes may ask of a printer.

One range for each kind of number the generated parts (measure_part, the
calibration pylons) write into G-code: temperatures, speeds, acceleration,
sizes. The generators check their options against these, so the `flowloop`
command and any other caller are refused alike, with the option named first.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

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
