"""Demo step: a print that moves in real time, for the live page.

With Klipper: a second stack (klippy paced to the clock by
devtools/realtime_klippy.py, and its own Moonraker) with the simulated
sensor and its twin hotend, [flowrate_limiter] and [autotemp]
(devtools/live_printer.cfg). A real ddPrint profile is stored and activated,
a real PrusaSlicer excerpt uploaded (Moonraker annotates it for autotemp on
upload) and, once the nozzle is hot, printed through Moonraker's API
(printer.print.start). Every few seconds one line: grip, measured and
commanded flow, the limiter's cap, autotemp's target, the nozzle temperature. The page
(/server/flowloop/page/) of that Moonraker shows the same as it happens; the
stack stays up with the demo's own until Ctrl-C.

FLOWLOOP_DEMO_LIVE_S: how long the lines are printed once the nozzle is hot
(default 30 s; heating takes about 45 s before); the
print goes on in the background.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from urllib.parse import quote

from devtools import stack
from flowloop.material import ddprint
from flowloop.material import profile as fl_profile

CONFIG = Path(__file__).resolve().parent / "live_printer.cfg"
GCODE = stack.PROJECT / "tests" / "data" / "gcode" / "block_layers_1_2.gcode"
PROFILE = (stack.PROJECT / "tests" / "data" / "ddprint-profiles" / "mat-profiles"
           / "UM2-1" / "herz-pla-red.json")
SECONDS_ENV = "FLOWLOOP_DEMO_LIVE_S"
DEFAULT_SECONDS = 30.0
EVERY_S = 3.0
PREHEAT_C = 200.0
PREHEAT_MAX_S = 90.0
PAGE_PATH = "/server/flowloop/page/"
OBJECTS = {"flow_sensor sim": ["grip", "measured_flow", "commanded_flow"],
           "flowrate_limiter": ["cap", "reason"],
           "autotemp": ["target", "source"],
           "extruder": ["temperature", "target"],
           "print_stats": ["state", "message"],
           "virtual_sdcard": ["progress"]}


def seconds() -> float:
    value = os.environ.get(SECONDS_ENV)
    try:
        return DEFAULT_SECONDS if value is None else max(0.0, float(value))
    except ValueError:
        raise SystemExit(f"{SECONDS_ENV}={value!r}: a number of seconds, "
                         f"e.g. {SECONDS_ENV}=30") from None


def _call(moonraker: stack.Moonraker, method: str, path: str, body=None):
    status, answer = moonraker.request(method, path, body)
    if status != 200:
        raise RuntimeError(f"{method} {path} -> {status}: {answer}")
    return answer["result"]


def _number(value, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


def progress_line(elapsed: float, status: dict) -> str:
    sensor, limiter = status["flow_sensor sim"], status["flowrate_limiter"]
    auto, extruder = status["autotemp"], status["extruder"]
    return (f"  {elapsed:4.0f} s  {status['print_stats']['state']:9s}"
            f" {100 * status['virtual_sdcard']['progress']:5.1f} %  grip"
            f" {_number(sensor['grip'], '5.3f')}  flow"
            f" {sensor['measured_flow']:5.2f}/{sensor['commanded_flow']:5.2f}"
            f" mm^3/s  cap {_number(limiter['cap'], '5.2f')}"
            f" ({limiter['reason'] or '-'})  target"
            f" {_number(auto['target'], '5.1f')} ({auto['source'] or '-'})"
            f"  nozzle {extruder['temperature']:5.1f} C")


def live(ctx, printer: stack.PrinterStack) -> None:
    mr = printer.moonraker
    ctx.say(f"A second stack whose klippy runs in real time: {mr.url}")
    ctx.say(f"  live page: {mr.url}{PAGE_PATH}")
    ctx.live_page_url = f"{mr.url}{PAGE_PATH}"
    (profile,) = ddprint.import_file(PROFILE).profiles
    name = profile.identity.name
    _call(mr, "POST", "/server/flowloop/profile",
          {"profile": fl_profile.profile_to_dict(profile)})
    _call(mr, "POST", "/server/flowloop/profile/activate",
          {"name": name, "extruder": "extruder", "working_point": 0.5})
    ctx.say(f"  active profile {name!r} (ddPrint, UM2-1), working point 0.5")
    mr.upload(GCODE.name, GCODE.read_bytes())
    annotation = _call(mr, "GET", "/server/flowloop/annotation?filename="
                       + quote(GCODE.name))
    ctx.say(f"  uploaded {GCODE.name}: annotated for autotemp "
            f"{bool(annotation.get('annotated'))}, peak flow "
            f"{annotation.get('peak_flow')} mm^3/s")
    query = "/printer/objects/query?" + "&".join(
        f"{quote(obj)}={','.join(fields)}" for obj, fields in OBJECTS.items())
    # M109 does not wait in batch mode: heat first, as the file expects
    ctx.say(f"  heating the nozzle to {PREHEAT_C:g} C (the twin's 80 W heater"
            f" and its lag):")
    _call(mr, "POST", "/printer/gcode/script?script=" + quote(
        f"SET_HEATER_TEMPERATURE HEATER=extruder TARGET={PREHEAT_C:g}"))
    start = time.monotonic()
    while time.monotonic() - start < PREHEAT_MAX_S:
        status = _call(mr, "GET", query)["status"]
        ctx.say(progress_line(time.monotonic() - start, status))
        if status["extruder"]["temperature"] >= PREHEAT_C - 3.0:
            break
        time.sleep(EVERY_S)
    _call(mr, "POST", "/printer/print/start?filename=" + quote(GCODE.name))
    duration = seconds()
    ctx.say(f"  printing it through Moonraker; a line every {EVERY_S:g} s for"
            f" {duration:g} s ({SECONDS_ENV} sets it):")
    start = time.monotonic()
    while True:
        elapsed = time.monotonic() - start
        status = _call(mr, "GET", query)["status"]
        ctx.say(progress_line(elapsed, status))
        state = status["print_stats"]["state"]
        if state == "error":
            ctx.say(f"  the print stopped: {status['print_stats']['message']}")
        if elapsed + EVERY_S > duration or state in ("complete", "error"):
            break
        time.sleep(EVERY_S)
    ctx.say(f"  the print goes on; watch it at {mr.url}{PAGE_PATH}")


def demo(ctx) -> None:
    if not ctx.klippy_available:
        ctx.say("No klippy: the live print needs a Klipper checkout "
                "(KLIPPER_PATH). The page is served by any flowloop Moonraker "
                f"at {PAGE_PATH}.")
        return
    printer = ctx.keep(stack.printer_stack(
        CONFIG, moonraker_conf="annotate_uploads: True\n", realtime=True))
    live(ctx, printer)
