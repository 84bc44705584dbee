"""The temperatures a printer's hotend heater accepts, and G-code kept within them.

Klipper refuses a heater target outside `[extruder]` `min_temp`..`max_temp`
(heaters.py set_temp: "Requested temperature (260.0) out of range
(0.0:250.0)", 0 switches off and is always accepted), and a file's first
refused M109 stops the print. Both options are required: klippy does not
start without them, so a printer.cfg that lacks one is refused here the same
way. Every target flowloop writes into G-code is a whole degree within
`HeaterRange` (`whole`), `cap_line` brings a file's own M104/M109 within
it, and a temperature the user asks of a test part outside it is refused
(`check`). `accepts` is the one rule: klippy's M104 take-over
(flowloop.control.tools) checks with it too.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Tuple, Union

from ..errors import FlowloopError

# M104/M109 for the first extruder (no T, or T0), its S (or R) value
_SET_TEMP = re.compile(rb"^(\s*M10[49])(?=\s|;|$)([^;\r\n]*)", re.IGNORECASE)
_VALUE = re.compile(rb"(\s[SR]\s*)([-+]?[0-9]*\.?[0-9]+)", re.IGNORECASE)
_TOOL = re.compile(rb"\sT\s*([-+]?[0-9]+)", re.IGNORECASE)


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


def heater_range(config, source: str, section: str = "extruder"
                 ) -> Optional[HeaterRange]:
    """The range from a printer.cfg (a host.klipper_config KlipperConfig);
    None without the section; an option missing is refused, as klippy
    refuses it."""
    if not config.has_section(section):
        return None
    min_c = config.getfloat(section, "min_temp")
    max_c = config.getfloat(section, "max_temp", above=min_c)
    return HeaterRange(min_c, max_c, f"{source} [{section}]")


def printer_heater(printer_cfg: Union[str, Path]) -> Optional[HeaterRange]:
    """The [extruder] range of a printer.cfg file, read as klippy reads it
    ([include]s, CRLF); None without [extruder]."""
    from ..host.klipper_config import read_config
    return heater_range(read_config(printer_cfg), str(printer_cfg))


def check_part_temp(printer_cfg: Optional[Union[str, Path]], temp_c: float,
                    name: str) -> Optional[str]:
    """A test part's temperature (option `name`) checked against the
    printer.cfg's [extruder] range (refused outside it); a note for the user
    when it could not be checked, else None."""
    if printer_cfg is None:
        return None
    heater = printer_heater(printer_cfg)
    if heater is None:
        return (f"{printer_cfg} has no [extruder]: {name} not checked against"
                f" its min_temp/max_temp")
    heater.check(temp_c, name)
    return None


def bake_note(was: str, temp_c: float, heater: HeaterRange) -> str:
    """The comment a target brought within the range carries."""
    return f" ; flowloop bake: was {was}, outside {heater.limit(temp_c)}"


def cap_line(line: bytes, heater: HeaterRange, newline: bytes
             ) -> Tuple[bytes, bool]:
    """An M104/M109 line for the first extruder with its target brought within
    the heater's range, the original kept in a comment; (line, changed)."""
    m = _SET_TEMP.match(line)
    if m is None:
        return line, False
    tool = _TOOL.search(b" " + m[2])
    if tool is not None and int(tool[1]) != 0:
        return line, False
    value = _VALUE.search(m[2])
    if value is None:
        return line, False
    try:
        temp = float(value[2])
    except ValueError:
        return line, False
    if heater.accepts(temp):
        return line, False
    new = heater.whole(temp)
    args = m[2][:value.start(2)] + str(new).encode() + m[2][value.end(2):]
    was = m[0].strip()     # the command, without the slicer's comment
    note = bake_note(was.decode(errors="replace"), temp, heater).encode()
    return m[1] + args.rstrip() + note + newline, True
