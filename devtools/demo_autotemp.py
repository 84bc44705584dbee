"""Demo step: autotemp heats ahead of the flow of a real slicer file.

With Klipper: a batch-mode klippy prints the first two layers of a real
PrusaSlicer file (tests/data/gcode/block_layers_1_2.gcode, annotated by
`flowloop annotate`) on the simulated sensor, whose twin is a 40 W hotend
melting what a weak material profile says (4 mm^3/s at 200 C; the infill
asks for up to 6.7), with autotemp: the filament that really moved, and
the targets autotemp set. Offline (and after it): the baked plan of the
same file.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any, Dict, List, Tuple

from devtools import stack
from devtools.demo_flowrate_limiter import WEAK_PROFILE, announced_peak, warm_up
from flowloop.gcode.annotate import annotate_file
from flowloop.material.profile import profile_from_dict, profile_line

GCODE = stack.PROJECT / "tests" / "data" / "gcode" / "block_layers_1_2.gcode"
CONFIG = stack.PROJECT / "tests" / "klippy" / "autotemp.cfg"
CHUNK_LINES = 10
# The weak profile, kept below 225 C: the file's peak (6.7 mm^3/s) needs 227
# (a clamp)
PROFILE = {**WEAK_PROFILE,
           "bounds": {"min_temp_c": 190.0, "recommended_temp_c": 200.0,
                      "max_temp_c": 225.0}}


def annotated(path: Path = GCODE) -> str:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "annotated.gcode"
        annotate_file(path, out)
        return out.read_text()


def print_with_autotemp(enable: int, build=None, venv=None,
                        profile: Dict[str, Any] = PROFILE, text: str = None,
                        config: Path = CONFIG
                        ) -> Tuple[List[Dict[str, Any]], float, str]:
    """Print the annotated excerpt on the twin with autotemp on (1) or off
    (0), after warming up to the file's first temperature as its M109 would;
    returns one record per chunk (print time, autotemp's status, the
    heater's target, the G-code responses), the filament the twin really
    moved, and klippy's log.

    An M400 every CHUNK_LINES lines: batch mode never holds the G-code
    reader back as a printer does, and the twin reads the heater's target as
    the steps are generated. The status after each chunk is read with
    KlippyApi.status_now: `config` must include
    tests/klippy/status_macro.cfg (autotemp.cfg does)."""
    text = annotated() if text is None else text
    workdir = stack.short_tempdir("fl-autotemp-")
    klippy = stack.Klippy(build or stack.build_klipper(),
                          venv or stack.klippy_venv(), config, workdir,
                          {"mcu": "atmega2560"})
    records = []
    try:
        api = klippy.ready_api()
        try:
            api.call("flowloop/set_active_profile", extruder="extruder",
                     profile=profile, working_point=0.5)
            api.gcode(f"SET_AUTOTEMP ENABLE={enable}")
            warm_up(api, 200.0)
            before = api.query("flow_sensor sim")["filament_position"] or 0.0
            lines = text.splitlines()
            for i in range(0, len(lines), CHUNK_LINES):
                chunk = lines[i:i + CHUNK_LINES]
                api.gcode("\n".join(chunk + ["M400"]))
                now = api.status_now("toolhead", "autotemp", "extruder")
                records.append({
                    "print_time": now["toolhead"]["print_time"],
                    "autotemp": now["autotemp"],
                    "heater_target": now["extruder"]["target"],
                    "lines": chunk})
            moved = api.query("flow_sensor sim")["filament_position"] - before
            api.gcode("QUERY_AUTOTEMP")
        finally:
            api.close()
    finally:
        klippy.stop()
        log = (workdir / "klippy.log").read_text(errors="replace")
        shutil.rmtree(workdir, ignore_errors=True)
    return records, moved, log


def with_klippy(ctx) -> None:
    peak = announced_peak(GCODE, CONFIG)
    need = profile_line(profile_from_dict(PROFILE), 0.5).temp_c(peak)
    ctx.say(f"A weak hotend (melts 4 mm^3/s at 200 C) prints two layers of a "
            f"real slicer file\n(infill asks for up to {peak:.1f} mm^3/s,"
            f" {need:.0f} C; the profile stops at"
            f" {PROFILE['bounds']['max_temp_c']:.0f} C), on the simulated sensor"
            f"\nand hotend, with [autotemp] (tests/klippy/test_autotemp.py"
            f" compares the file's own\ntemperatures, 200 and 215 C):")
    records, moved, _ = print_with_autotemp(1)
    targets = [r["heater_target"] for r in records]
    sources = {r["autotemp"]["source"] for r in records} - {None}
    ctx.say(f"  filament moved {moved:.1f} mm of the file's 404.4, heater target"
            f" {min(targets):.0f} to {max(targets):.0f} C, source"
            f" {', '.join(sorted(sources))}, "
            f"{records[-1]['autotemp']['capped_windows']} windows clamped")
    bake(ctx)


def bake(ctx) -> None:
    from flowloop.gcode.bake import bake_file
    profile = profile_from_dict({**PROFILE, "bounds": {**PROFILE["bounds"],
                                                       "max_temp_c": 240.0}})
    with tempfile.TemporaryDirectory() as tmp:
        result, _ = bake_file(GCODE, Path(tmp) / "baked.gcode", profile, 0.5)
    ctx.say(f"Offline bake of the same file (flowloop annotate --bake, profile"
            f" up to 240 C): {result.commands} M104 from {result.min_target_c:.0f}"
            f" to {result.max_target_c:.0f} C; the modelled hotend melts less than"
            f" demanded for {result.under_capacity_s:.1f} s of"
            f" {result.print_time_s:.0f} s")


def offline(ctx) -> None:
    bake(ctx)


def demo(ctx) -> None:
    if ctx.klippy_available:
        with_klippy(ctx)
    else:
        offline(ctx)
