"""What the start G-code heats the nozzle to, and what the bake does about it.

A baked file (`flowloop annotate --bake`) plans the print from a start
temperature. Klipper runs the start G-code's last heat-and-wait before the
first extrusion after any M104 placed before it, so that wait decides the
temperature the print really starts at. Before the first extruding move the
bake looks for the last of:

- `M109 S<t>` / `M109 R<t>` for this extruder (no `T`, or `T0`);
- a start macro: a command that is not a G/M/T code and either has a
  temperature parameter (START_MACRO_TEMP_PARAMS: `PRINT_START EXTRUDER=215`,
  `START_PRINT EXTRUDER_TEMP=215`, `PRINT_START HOTEND=215`) or a name with
  START in it (`PRINT_START`, `START_PRINT`): it heats and waits inside
  Klipper, where the file does not say to what.

and decides (`start_fix`) so that the print starts at or above the plan's
start temperature: a lower `M109` is raised, a higher one kept (hotter melts
more; the plan's targets take over after it); after a start macro that heats
to less than the plan, or to an unknown temperature, an `M109` is added;
without either, one is added before the first extrusion. A wait the
printer's heater would refuse is first brought within its range (`heat_at`,
by the bake): a start macro's line is then rewritten (`LineFix`).
"""

from __future__ import annotations

import codecs
import re
from dataclasses import dataclass, replace
from typing import BinaryIO, Optional

# Parameter names slicers' Klipper profiles pass the first layer's nozzle
# temperature under (PrusaSlicer, OrcaSlicer, Cura and the macros users copy).
START_MACRO_TEMP_PARAMS = ("EXTRUDER", "EXTRUDER_TEMP", "EXTRUDER_TEMPERATURE",
                           "HOTEND", "HOTEND_TEMP", "NOZZLE", "NOZZLE_TEMP",
                           "TOOL_TEMP", "TEMP")
_GMT = re.compile(rb"^\s*[GMTgmt]\d")
_M109 = re.compile(rb"^\s*M109(?=\s|$)", re.IGNORECASE)
_WORD = re.compile(rb"^\s*([A-Za-z_][A-Za-z0-9_]*)(?=\s|$)")
_M109_ARG = re.compile(rb"\s([SRT])\s*([-+]?[0-9.]+)", re.IGNORECASE)
_MACRO_ARG = re.compile(rb"\s([A-Za-z_][A-Za-z0-9_]*)=([-+]?[0-9.]+)")


@dataclass(frozen=True)
class StartHeat:
    """The start G-code's last heat-and-wait before the first extrusion."""
    kind: str                   # "m109", "macro" or "none"
    line_no: int                # 1-based; of the first extrusion for "none"
    offset: int                 # the line's first byte
    end: int                    # the byte after the line (its newline)
    text: str                   # the line without its comment
    temp_c: Optional[float]     # the wait's temperature, None where unknown
    param: Optional[str] = None  # the macro's temperature parameter


@dataclass(frozen=True)
class LineFix:
    """A line of the file written otherwise."""
    offset: int                 # the line's first byte
    line: str                   # written instead, with its newline
    message: str                # one line for the user


@dataclass(frozen=True)
class StartFix:
    """What the bake writes so the print starts where the plan does."""
    action: str                 # "keep", "raise" or "add"
    offset: int                 # "raise" replaces [offset, end), "add" inserts here
    end: int
    line: Optional[str]         # the line written (None: "keep")
    start_c: float              # the nozzle when the first extrusion starts
    message: str                # one line for the user
    heat_fix: Optional[LineFix] = None  # the start macro's temperature changed


def _code(line: bytes) -> bytes:
    if line.startswith(codecs.BOM_UTF8):    # no command (planner.Planner.line)
        line = line[len(codecs.BOM_UTF8):]
    return line.split(b";", 1)[0].rstrip(b"\r\n")


def find_start_heat(f: BinaryIO, first_extrusion: int) -> StartHeat:
    """The last heat-and-wait of f (binary, at its start) before byte offset
    first_extrusion (the first extruding move's line)."""
    found: Optional[StartHeat] = None
    offset, line_no = 0, 0
    for line in f:
        line_no += 1
        if offset >= first_extrusion:
            break
        heat = _heat_of(_code(line), line_no, offset, offset + len(line))
        if heat is not None:
            found = heat
        offset += len(line)
    if found is None:
        return StartHeat("none", line_no, first_extrusion, first_extrusion, "",
                         None)
    return found


def _heat_of(code: bytes, line_no: int, offset: int, end: int
             ) -> Optional[StartHeat]:
    text = code.decode("ascii", "replace").strip()
    if _M109.match(code):
        args = {m[1].upper(): m[2] for m in _M109_ARG.finditer(b" " + code)}
        if args.get(b"T", b"0") not in (b"0", b"+0"):
            return None   # another tool's heater
        value = args.get(b"S", args.get(b"R"))
        return StartHeat("m109", line_no, offset, end, text,
                         _number(value) if value is not None else None)
    if _GMT.match(code):
        return None
    word = _WORD.match(code)
    if word is None:
        return None
    name = word[1].upper()
    params = {m[1].upper().decode(): m[2] for m in _MACRO_ARG.finditer(code)}
    for param in START_MACRO_TEMP_PARAMS:
        if param in params:
            return StartHeat("macro", line_no, offset, end, text,
                             _number(params[param]), param)
    if b"START" in name:
        return StartHeat("macro", line_no, offset, end, text, None)
    return None


def _number(value: bytes) -> Optional[float]:
    try:
        return float(value)
    except ValueError:
        return None


def heat_at(heat: StartHeat, temp_c: int) -> StartHeat:
    """The same heat-and-wait at temp_c: its M109 S, or the start macro's
    temperature parameter, changed."""
    if heat.kind == "m109":
        return replace(heat, temp_c=float(temp_c), text=f"M109 S{temp_c}")
    value = re.compile(rf"(\s{heat.param}=)[-+]?[0-9.]+", re.IGNORECASE)
    text = value.sub(lambda m: f"{m[1]}{temp_c}", " " + heat.text)[1:]
    return replace(heat, temp_c=float(temp_c), text=text)


def start_fix(heat: StartHeat, plan_start_c: float, newline: str = "\n"
              ) -> StartFix:
    """What to write so that the nozzle is at least plan_start_c (whole
    degrees, rounded up by the caller) when the first extrusion starts."""
    t = int(plan_start_c)
    where = f"line {heat.line_no}"
    name = heat.text.split()[0] if heat.text else ""
    if heat.kind == "none":
        return _added(heat.offset, t, plan_start_c, newline,
                      f"no M109 or start macro before the first extrusion"
                      f" ({where}): added M109 S{t} before it")
    if heat.temp_c is not None and heat.temp_c >= plan_start_c:
        said = (f"the file's {heat.text} ({where}) heats to at least the plan's"
                f" {t} C: kept, the plan's targets follow it"
                if heat.kind == "m109" else
                f"{name} ({where}) is given {heat.param}={heat.temp_c:g}, at"
                f" least the plan's {t} C: kept, assuming your macro waits at it")
        return StartFix("keep", heat.offset, heat.end, None, heat.temp_c,
                        "start: " + said)
    if heat.kind == "m109" and heat.temp_c is not None:
        return StartFix(
            "raise", heat.offset, heat.end,
            f"M109 S{t} ; flowloop bake: was {heat.text}" + newline,
            plan_start_c,
            f"start: raised the file's {heat.text} ({where}) to M109 S{t},"
            f" the temperature the plan starts from")
    # a start macro (or an M109 without S or R): what it waits at is unknown
    # or below the plan
    told = (f"is given {heat.param}={heat.temp_c:g}, below the plan's {t} C"
            if heat.temp_c is not None else
            "waits at a temperature the file does not say")
    hint = (f"give it {heat.param}={t}" if heat.param is not None
            else f"make it wait at {t} C")
    return _added(heat.end, t, plan_start_c, newline,
                  f"{name} ({where}) {told}: added M109 S{t} after it; to heat"
                  f" once, {hint}")


def _added(offset: int, t: int, start_c: float, newline: str, said: str
           ) -> StartFix:
    return StartFix("add", offset, offset,
                    f"M109 S{t} ; flowloop bake: the plan starts at {t} C"
                    + newline, start_c, "start: " + said)
