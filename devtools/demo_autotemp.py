"""Demo step: autotemp heats ahead of the flow of a real slicer file.

With Klipper: a batch-mode klippy prints the first two layers of a real
PrusaSlicer file (tests/data/gcode/block_layers_1_2.gcode, annotated by
`flowloop annotate`) on the simulated sensor, whose twin is a 40 W hotend
melting what a weak material profile says (4 mm^3/s at 200 C; the infill
asks for up to 6.4). Once at the file's own temperatures (autotemp off),
once with autotemp: the filament that really moved, and the targets
autotemp set. Offline: the baked plan of the same file.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any, Dict, List, Tuple

from devtools import stack
from devtools.demo_flowrate_limiter import WEAK_PROFILE, Api, warm_up
from flowloop.gcode.annotate import annotate_file

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
    the steps are generated."""
    text = annotated() if text is None else text
    workdir = stack.short_tempdir("fl-autotemp-")
    klippy = stack.Klippy(build or stack.build_klipper(),
                          venv or stack.klippy_venv(), config, workdir,
                          {"mcu": "atmega2560"})
    records = []
    try:
        klippy.wait_ready()
        api = Api(klippy.api_socket)
        try:
            stack.wait_until(lambda: api.call("info")["state"] == "ready", 30)
            api.call("flowloop/set_active_profile", extruder="extruder",
                     profile=profile, working_point=0.5)
            api.gcode(f"SET_AUTOTEMP ENABLE={enable}")
            warm_up(api, 200.0)
            before = api.query("flow_sensor sim")["filament_position"] or 0.0
            lines = text.splitlines()
            for i in range(0, len(lines), CHUNK_LINES):
                chunk = lines[i:i + CHUNK_LINES]
                api.gcode("\n".join(chunk + ["M400"]))
                records.append({
                    "print_time": api.query("toolhead")["print_time"],
                    "autotemp": api.query("autotemp"),
                    "heater_target": api.query("extruder")["target"],
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
    ctx.say("A weak hotend (melts 4 mm^3/s at 200 C) prints two layers of a "
            "real slicer file\n(infill asks for up to 6.4 mm^3/s), on the "
            "simulated sensor and hotend:")
    for enable, what in ((0, "file's own M104/M109"), (1, "autotemp         ")):
        records, moved, _ = print_with_autotemp(enable)
        targets = [r["heater_target"] for r in records]
        ctx.say(f"  {what}: filament moved {moved:6.1f} mm, heater target "
                f"{min(targets):.0f} to {max(targets):.0f} C")


def offline(ctx) -> None:
    ctx.say("No klippy: see `flowloop annotate --bake` in docs/autotemp.md.")


def demo(ctx) -> None:
    if ctx.klippy_available:
        with_klippy(ctx)
    else:
        offline(ctx)
