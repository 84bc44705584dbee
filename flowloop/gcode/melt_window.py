"""The melt window: the time the flow to melt is averaged over
(flowloop.gcode.melt), a setting of the printer's hotend.

It should be the hotend's melt lag (docs/autotemp.md, The flow to melt):
bursts shorter than it are announced as their mean. Its default, its bounds
and where a printer sets it live here, without numpy, so klippy's [autotemp]
checks the option as the annotator reads it:

- `flowloop annotate --melt-window S` wins;
- else `[autotemp] melt_window` of the printer.cfg the annotator is given
  (`--printer-cfg`, and so Moonraker's upload processor with
  `annotate_printer_cfg`); on a toolchanger, the shortest of the
  `[autotemp NAME]` sections' (a file is annotated once for every tool, and
  a shorter window announces more of a burst, never less);
- else MELT_TIME_S.
"""

from __future__ import annotations

import math
from typing import Optional

from ..errors import FlowloopError, option_message

MELT_TIME_S = 0.5
# The bounds: below MIN_MELT_S the 10 ms cells' error grows past the plan's
# FLOW_MARGIN (flowloop.control.autotemp), beyond MAX_MELT_S no hotend holds
# a burst's heat (docs/autotemp.md, The flow to melt).
MIN_MELT_S = 0.25
MAX_MELT_S = 2.0
SECTION = "autotemp"
OPTION = "melt_window"


def check_melt_window(melt_s: object) -> float:
    """melt_s if it is a number within MIN_MELT_S..MAX_MELT_S, else
    FlowloopError "must be 0.25 to 2 s, not nan" (the caller names it)."""
    if not (isinstance(melt_s, (int, float)) and not isinstance(melt_s, bool)
            and math.isfinite(melt_s) and MIN_MELT_S <= melt_s <= MAX_MELT_S):
        raise FlowloopError(f"must be {MIN_MELT_S:g} to {MAX_MELT_S:g} s,"
                            f" not {melt_s!r}")
    return float(melt_s)


def autotemp_sections(config) -> list:
    """The [autotemp] and [autotemp NAME] sections of a printer.cfg (a
    host.klipper_config.KlipperConfig)."""
    return [s for s in config.sections()
            if s == SECTION or s.startswith(SECTION + " ")]


def melt_window_from_config(config) -> Optional[float]:
    """The melt window a printer.cfg sets: the shortest `melt_window` of its
    [autotemp] sections, None where none sets it; a bad value is refused
    naming its section and option."""
    found = []
    for section in autotemp_sections(config):
        if not config.has_option(section, OPTION):
            continue
        raw = config.get(section, OPTION)
        try:
            value = float(raw)
        except ValueError:
            value = raw
        try:
            found.append(check_melt_window(value))
        except FlowloopError as e:
            raise FlowloopError(option_message(section, OPTION, str(e))) from None
    return min(found, default=None)
