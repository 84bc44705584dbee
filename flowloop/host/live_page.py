"""The live page Moonraker serves at /server/flowloop/page/: its one HTML
document, and the numbers it draws that only the core can give (the active
profile's melt lines, an annotated file's planned flow and temperature).

The page itself is static (page/index.html, page.js, page.css and the
vendored uPlot, see page/README.md); the browser takes everything else from
Moonraker's websocket.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any, Dict, List, NamedTuple, Optional, Sequence, Tuple

from ..control.autotemp import DEFAULT_PARAMS, GRID_S, Autotemp
from ..control.hotend import HotendParams
from ..errors import FlowloopError
from ..gcode.annotate import COMMAND, HEADER_BYTES, is_annotated
from ..gcode.bake import parse_announcement, replay
from ..gcode.start import find_start_heat
from ..material.plot import COLORS
from ..material.profile import Profile, decode_profile, encode_profile, profile_line

ASSETS = Path(__file__).resolve().parent / "page"
# What the page draws of a file's plan and a profile's lines: enough for a
# chart a few thousand pixels wide, and a bounded answer for any file.
MAX_PLAN_POINTS = 2000
LINE_POINTS = 41

_LINK = re.compile(r'<link rel="stylesheet" href="(?P<name>[\w.]+)">')
_SCRIPT = re.compile(r'<script src="(?P<name>[\w.]+)"></script>')
# Where page.js takes the plots' colours (one palette, flowloop.material.plot's).
PALETTE_MARK = "{/* plot.COLORS */}"


def _read(assets: Path, name: str) -> str:
    path = assets / name
    try:
        return path.read_text(encoding="utf-8")
    except OSError as e:
        raise FlowloopError(f"{path}: the page's file cannot be read "
                            f"({e.strerror}): reinstall flowloop") from None


def document(assets: Path = ASSETS) -> bytes:
    """index.html with the stylesheets and scripts it links put inline.

    One response holds the whole page, so one authorised request loads it
    (a trusted client, or Moonraker's `?access_token=` / `?token=` in the
    URL, which a browser sends with the page but not with its sub-requests).
    The files stay separate in the package: index.html also opens straight
    from the folder while the page is being worked on. page.js gets the
    plots' colours (flowloop.material.plot.COLORS) here.
    """
    html = _read(assets, "index.html")
    html = _LINK.sub(
        lambda m: f"<style>\n{_read(assets, m['name'])}\n</style>", html)
    # "</script" inside a script would end it early; "<\/" is the same text
    # to JavaScript.
    html = _SCRIPT.sub(lambda m: "<script>\n" + _read(assets, m["name"]).replace(
        "</script", "<\\/script") + "\n</script>", html)
    return html.replace(PALETTE_MARK, json.dumps(COLORS)).encode("utf-8")


# ---------------------------------------------------------------------------
# The active profile's lines


def profile_lines(profile: Profile, working_point: float,
                  heater_max_temp_c: Optional[float] = None) -> Dict[str, Any]:
    """Into-air, real-print and working-point lines (flow in mm^3/s) over the
    profile's temperature range, on LINE_POINTS temperatures: the page draws
    what the one melt line says instead of evaluating lines itself.

    `max_temp_c` is the bound the printer runs to: the profile's, capped at
    the heater's max_temp where it is known. The temperatures drawn reach 10 %
    past either bound, a drawing matter only (the live point shows even a
    little outside)."""
    bounds = profile.bounds
    max_temp_c = bounds.max_temp_c if heater_max_temp_c is None \
        else min(bounds.max_temp_c, heater_max_temp_c)
    margin = 0.1 * max(max_temp_c - bounds.min_temp_c, 1.0)
    low, top = bounds.min_temp_c - margin, max_temp_c + margin
    temps = [low + (top - low) * k / (LINE_POINTS - 1) for k in range(LINE_POINTS)]
    lines = {
        "into_air": profile.lines.into_air.line(),
        "real_print": profile.lines.real_print.line(),
        "working": profile_line(profile, working_point),
    }
    return {
        "name": profile.identity.name,
        "working_point": working_point,
        "min_temp_c": bounds.min_temp_c,
        "max_temp_c": max_temp_c,
        "temp_c": [round(t, 2) for t in temps],
        **{key: [round(line.flow_mm3_s(t), 3) for t in temps]
           for key, line in lines.items()},
    }


# ---------------------------------------------------------------------------
# An annotated file's plan

_LINE_START = COMMAND.encode()


def announcements(path: Path) -> List[Tuple[int, str]]:
    """(byte offset, text) of each AUTOTEMP_FLOW line of an annotated file;
    FlowloopError if the file cannot be read or carries no annotations."""
    try:
        with open(path, "rb") as f:
            head = f.read(HEADER_BYTES)
            if not is_annotated(head):
                raise FlowloopError(f"{path.name} has no autotemp annotations "
                                    f"(upload it with [autotemp] loaded, or run "
                                    f"flowloop annotate on it)")
            f.seek(0)
            found, offset = [], 0
            for raw in f:
                if raw.startswith(_LINE_START):
                    found.append((offset, raw.decode("ascii", "replace").strip()))
                offset += len(raw)
    except OSError as e:
        raise FlowloopError(f"{path.name}: cannot read: {e.strerror}") from None
    return found


class _Timed(NamedTuple):
    offset: int        # of the command in the file
    time_s: float      # print time the command runs at
    line: str
    start_s: float     # of the window it announces
    flow_mm3_s: float


def _timed(found: Sequence[Tuple[int, str]]) -> Tuple[List[_Timed], float]:
    """Each announcement with its print time, and the end of the last window.
    The windows follow each other without gaps (annotate.py), so window k
    starts where k-1 ended, and its command sits LEAD before that start."""
    timed: List[_Timed] = []
    start = None
    for offset, line in found:
        try:
            flow, lead, duration = parse_announcement(line)
        except FlowloopError:
            continue  # not a well-formed announcement: autotemp refuses it too
        if start is None:
            start = lead  # the first command runs at the first move
        timed.append(_Timed(offset, max(0.0, start - lead), line, start, flow))
        start += duration
    return timed, start or 0.0


def _buckets(values: Sequence[Optional[float]], size: int) -> List[Optional[float]]:
    """The highest value of each run of `size` (None where all are None)."""
    out: List[Optional[float]] = []
    for k in range(0, len(values), size):
        known = [v for v in values[k:k + size] if v is not None]
        out.append(max(known) if known else None)
    return out


def _start(path: Path, first_offset: int, heater_max_temp_c: Optional[float]
           ) -> Optional[Tuple[float, float]]:
    """Where the start G-code's wait leaves the nozzle (the last M109 or
    start macro's temperature before the first announcement), as [autotemp]
    finds it at the printer's first flush: the replay's start. None: the
    file sets none (an excerpt), the model starts at the profile's
    minimum."""
    with open(path, "rb") as f:
        heat = find_start_heat(f, first_offset)
    if heat.temp_c is None:
        return None
    temp_c = heat.temp_c if heater_max_temp_c is None \
        else min(heat.temp_c, heater_max_temp_c)
    return 0.0, temp_c


def file_plan(path: Path, profile: Optional[Profile], working_point: float,
              heater_max_temp_c: Optional[float] = None,
              params: HotendParams = DEFAULT_PARAMS) -> Dict[str, Any]:
    """What an annotated file tells [autotemp] over the whole print: the
    announced flow, and with a profile the targets autotemp's controller
    sets from them (the same replay as `flowloop annotate --bake`), at most
    MAX_PLAN_POINTS of each; `positions` maps file offsets (each command's,
    then the file's end) to print time so the page can mark where the print
    is."""
    timed, end_s = _timed(announcements(path))
    if not timed:
        raise FlowloopError(f"{path.name}: its annotations announce no flow")
    steps = math.ceil(end_s / GRID_S) + 1
    flows: List[Optional[float]] = []
    k = 0
    for i in range(steps):  # the announced flow at each GRID_S
        t = i * GRID_S
        while k + 1 < len(timed) and timed[k + 1].start_s <= t:
            k += 1
        flows.append(timed[k].flow_mm3_s if timed[k].start_s <= t < end_s else 0.0)
    targets: List[Optional[float]] = [None] * steps
    why = None
    if profile is None:
        why = "no active profile: the planned temperature needs one"
    else:
        controller = Autotemp(params, heater_max_temp_c)
        controller.set_profile(profile, working_point)
        if controller.plan is None:
            why = controller.why
        else:
            commands = [(a.offset, a.time_s, a.line) for a in timed]
            targets = replay(commands, end_s, controller,
                             _start(path, timed[0].offset, heater_max_temp_c)
                             )[:steps]
    size = max(1, math.ceil(steps / MAX_PLAN_POINTS))
    positions = [(a.offset, round(a.time_s, 2)) for a in timed]
    if len(positions) > MAX_PLAN_POINTS:
        positions = positions[::math.ceil(len(positions) / MAX_PLAN_POINTS)]
    # the file's end is the print's end: the moves after the last command
    # (its LEAD before the last window) get their time too
    end_s = round(end_s, 2)   # one figure: the plan's length and its end
    positions.append((path.stat().st_size, end_s))
    return {
        "file": path.name,
        "print_time_s": end_s,
        "windows": len(timed),
        "time_s": [round(k * GRID_S, 2) for k in range(0, steps, size)],
        "flow_mm3_s": _buckets(flows, size),
        "target_c": [None if v is None else round(v, 1)
                     for v in _buckets(targets, size)],
        "positions": positions,
        "why": why,
    }


# ---------------------------------------------------------------------------
# The plan in a process of its own

PLAN_TIMEOUT_S = 300.0


def plan_command(python: str, path: Path, profile: Optional[Profile],
                 working_point: float) -> Tuple[List[str], bytes]:
    """(argv, stdin) that print file_plan's answer as one JSON line: a long
    print's replay is seconds of pure Python, which Moonraker runs apart so
    it holds neither its loop nor its GIL."""
    argv = [python, "-c", "from flowloop.host.live_page import plan_main; "
            "plan_main()", str(path), repr(float(working_point))]
    return argv, b"" if profile is None else encode_profile(profile, indent=0)


def plan_main(argv: Optional[List[str]] = None) -> None:
    """plan_command's other end: the file and working point in argv, the
    profile (or nothing) on stdin; a refusal is {"why": ...}."""
    import json
    import sys
    path, wp = (argv or sys.argv[1:])[:2]
    data = sys.stdin.buffer.read()
    try:
        profile = decode_profile(data) if data.strip() else None
        answer = file_plan(Path(path), profile, float(wp))
        answer["annotated"] = True
    except FlowloopError as e:
        answer = {"file": Path(path).name, "annotated": False, "why": str(e)}
    sys.stdout.write(json.dumps(answer) + "\n")
