"""G-code kept within the temperatures a printer's hotend heater accepts.

A file's first M109 that Klipper refuses (outside `[extruder]`
`min_temp`..`max_temp`, flowloop.control.heater_range) stops the print.
Every target flowloop writes into G-code is a whole degree within the
`HeaterRange` (`whole`), and `cap_line` brings a file's own M104/M109 within
it. The range is read from a printer.cfg by
flowloop.host.klipper_config.heater_range.
"""

from __future__ import annotations

import re
from typing import Tuple

from ..control.heater_range import HeaterRange

# M104/M109 for the first extruder (no T, or T0), its S (or R) value
_SET_TEMP = re.compile(rb"^(\s*M10[49])(?=\s|;|$)([^;\r\n]*)", re.IGNORECASE)
_VALUE = re.compile(rb"(\s[SR]\s*)([-+]?[0-9]*\.?[0-9]+)", re.IGNORECASE)
_TOOL = re.compile(rb"\sT\s*([-+]?[0-9]+)", re.IGNORECASE)


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
