"""The temperatures a printer's hotend heater accepts.

Klipper refuses a heater target outside `[extruder]` `min_temp`..`max_temp`
(heaters.py set_temp: "Requested temperature (260.0) out of range
(0.0:250.0)", 0 switches off and is always accepted), and a file's first
refused M109 stops the print. `HeaterRange.accepts` is the one rule: the
G-code flowloop writes (flowloop.gcode.heater), the test parts' temperatures
(flowloop.host.klipper_config.check_part_temp) and klippy's M104 take-over
(flowloop.control.tools) all judge a target with it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import FlowloopError


@dataclass(frozen=True)
class HeaterRange:
    """[extruder] min_temp..max_temp, and where they were read."""
    min_temp_c: float
    max_temp_c: float
    source: str

    def __post_init__(self):
        if not (math.isfinite(self.min_temp_c) and math.isfinite(self.max_temp_c)
                and self.min_temp_c < self.max_temp_c):
            raise FlowloopError(f"{self.source}: max_temp {self.max_temp_c:g} must"
                                f" be above min_temp {self.min_temp_c:g}")

    def whole(self, temp_c: float) -> int:
        """temp_c as a whole-degree target Klipper accepts: rounded up, then
        within min_temp..max_temp (max_temp 249.5 takes 249)."""
        top = math.floor(self.max_temp_c + 1e-9)
        bottom = math.ceil(self.min_temp_c - 1e-9)
        return min(top, max(bottom, math.ceil(temp_c - 1e-6)))

    def accepts(self, temp_c: float) -> bool:
        """As Klipper's heater judges a target: 0 (off), or within the range."""
        return temp_c == 0 or self.min_temp_c <= temp_c <= self.max_temp_c

    def limit(self, temp_c: float) -> str:
        """The limit a target Klipper refuses is beyond: "max_temp 250"."""
        if temp_c > self.max_temp_c:
            return f"max_temp {self.max_temp_c:g}"
        return f"min_temp {self.min_temp_c:g}"

    def check(self, temp_c: float, name: str) -> float:
        """A temperature the user asked for (a test part's), refused in one
        line naming the option and the limit where Klipper would refuse it,
        as typed or as the whole degree the part writes."""
        for value in (temp_c, round(temp_c)):
            if not self.accepts(value):
                written = "" if value == temp_c else f" (written as {value})"
                side = "above" if value > self.max_temp_c else "below"
                raise FlowloopError(
                    f"{name} {temp_c:g} C{written} is {side} the printer's"
                    f" {self.limit(value)} C ({self.source}): Klipper would"
                    f" refuse it")
        return temp_c
