"""Demo step: the flowrate limiter holds grip on a real slicer file.

With Klipper: a batch-mode klippy prints the first two layers of a real
PrusaSlicer file (tests/data/gcode/block_layers_1_2.gcode) on the simulated
sensor, whose twin is a 40 W hotend melting what a weak material profile
says (4 mm^3/s at 200 C; the infill asks for up to 6.7). Once without the
limiter, once with it (mode predictive), after heating the nozzle as M109 would: grip
windows below min_grip, the filament that really moved, the time the limiter
added. Offline: the
reactive rule against ddPrint's on the scenario of docs/flowrate_limiter.md.
"""

from __future__ import annotations

import io
import shutil
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np

from devtools import stack
from flowloop.control import caps as fl_caps
from flowloop.control import nozzle_health as nh
from flowloop.control import rule_plot
from flowloop.gcode.annotate import AnnotateSettings, quantise_flow
from flowloop.gcode.bake import plan_announcements
from flowloop.gcode.bulk_planner import plan_file
from flowloop.gcode.reference_planner import Segment, limits_from_config
from flowloop.host.klipper_config import read_config

GCODE = stack.PROJECT / "tests" / "data" / "gcode" / "block_layers_1_2.gcode"
CONFIG = stack.PROJECT / "tests" / "klippy" / "flowrate_limiter_loop.cfg"
# A hotend that melts 4 mm^3/s at 200 C, 0.1 mm^3/s more per degree
WEAK_PROFILE = {
    "identity": {"name": "weak", "nozzle_diameter_mm": 0.4},
    "lines": {"into_air": {"slope_mm3_s_per_c": 0.1, "temp_c": 200.0,
                           "flow_mm3_s": 4.5},
              "real_print": {"slope_mm3_s_per_c": 0.1, "temp_c": 200.0,
                             "flow_mm3_s": 3.5}},
    "bounds": {"min_temp_c": 190.0, "recommended_temp_c": 210.0,
               "max_temp_c": 260.0},
    "provenance": {"method": "manual"},
}
# 6 mm^3/s at 200 C: what the bench's twin (melt_scale 0.7) melts, it says,
# but it melts only 70 % of that
OPTIMISTIC_PROFILE = {
    **WEAK_PROFILE,
    "identity": {"name": "optimistic", "nozzle_diameter_mm": 0.4},
    "lines": {"into_air": {"slope_mm3_s_per_c": 0.1, "temp_c": 200.0,
                           "flow_mm3_s": 6.5},
              "real_print": {"slope_mm3_s_per_c": 0.1, "temp_c": 200.0,
                             "flow_mm3_s": 5.5}},
}
# How far G-code runs ahead of the steps the twin has seen, in planned print
# time (print_in_chunks): about what a printer's toolhead holds
# (BUFFER_TIME_HIGH, 1 s)
CHUNK_S = 1.0
WARM_UP_C = 200.0


# warm_up's travel: 150 mm at 100 mm/s per move
WARM_UP_MOVE_S = 1.5
# M109 waits until the nozzle is this close to its target
WARM_UP_WITHIN_C = 1.0


def warm_up(api, target_c: float, seconds: float = 100.0,
            most_s: float = 600.0) -> None:
    """What M109 does on a printer, which batch mode skips: heat the nozzle
    before the file starts. Travel passes the time, so that the twin's
    hotend and the limiter's thermal model both see it (a dwell would pass
    only the twin's): `seconds` of it, then more, 10 s at a time, until
    the limiter's nozzle temperature (in batch mode its thermal estimate,
    which follows the twin's heater) is within WARM_UP_WITHIN_C of the
    target, as M109 waits, or most_s have passed. (Until 2026-11-30 only
    the 100 s: a heater block 2.5 times as heavy as the bench's, slow
    high-mass B, then started the file at 111 C.)"""
    def travel(first, count):
        return [f"G1 X{10 if i % 2 else 160} F6000"
                for i in range(first, first + count)]
    done = int(seconds / WARM_UP_MOVE_S)
    api.gcode("\n".join(["G28", f"SET_HEATER_TEMPERATURE HEATER=extruder"
                          f" TARGET={target_c:g}"] + travel(0, done) + ["M400"]))
    step = int(10.0 / WARM_UP_MOVE_S)
    while done * WARM_UP_MOVE_S < most_s:
        temp = (api.query_many("flowrate_limiter").get("flowrate_limiter")
                or {}).get("temperature")
        if temp is None or temp >= target_c - WARM_UP_WITHIN_C:
            return
        api.gcode("\n".join(travel(done, step) + ["M400"]))
        done += step


def chunks(lines: List[str], chunk_s: float = CHUNK_S) -> List[List[str]]:
    """lines cut where the planned print time (flowloop's planner, at the
    bench printer's limits: where to cut, not a figure) passes each
    multiple of chunk_s; a line that moves longer than that is a chunk of
    its own (a printer queues a move whole, or in pieces where the limiter
    cuts it: cut_as_on_a_printer)."""
    data = "".join(line + "\n" for line in lines).encode()
    first_byte = np.cumsum([0] + [len(line) + 1 for line in lines[:-1]])
    limits = limits_from_config(read_config(CONFIG))
    starts = {}
    for event in plan_file(io.BytesIO(data), limits):
        if isinstance(event, Segment):
            starts.setdefault(event.offset, event.start_s)
    cut_at, next_cut = [0], chunk_s
    for k, offset in enumerate(first_byte.tolist()):
        start_s = starts.get(offset)
        if start_s is not None and start_s >= next_cut and k > cut_at[-1]:
            cut_at.append(k)
            next_cut = (int(start_s / chunk_s) + 1) * chunk_s
    return [lines[a:b] for a, b in zip(cut_at, cut_at[1:] + [len(lines)])]


def cut_as_on_a_printer(lines: List[str]) -> List[str]:
    """The G-code with every extruding G1 cut into the pieces
    klippy_extras/flowrate_limiter.py queues it in on a printer, where the
    caps can change between them (fl_caps.piece_count at the move's F);
    batch mode queues every move whole, so the benches feed it the pieces.
    Reads absolute XYZ (G90), E absolute or relative (M82/M83), G92 and
    M220 (klippy hands the limiter the speed after its factor)."""
    pos = {"X": 0.0, "Y": 0.0, "Z": 0.0, "E": 0.0}
    feed, factor, relative_e, out = 1500.0, 1.0, False, []
    for line in lines:
        words = line.split(";", 1)[0].split()
        cmd = words[0].upper() if words else ""
        if cmd in ("G2", "G3", "G91"):
            raise ValueError(f"cut_as_on_a_printer reads G0/G1 in G90 only: {line!r}")
        args = {w[0].upper(): float(w[1:]) for w in words[1:]
                if cmd in ("G0", "G1", "G92", "M220") and len(w) > 1}
        factor = args.get("S", 100.0) / 100.0 if cmd == "M220" else factor
        relative_e = {"M82": False, "M83": True}.get(cmd, relative_e)
        if cmd == "G92":
            pos.update(args)
        if cmd not in ("G0", "G1"):
            out.append(line)
            continue
        feed = args.get("F", feed)
        end = {a: pos[a] + args["E"] if a == "E" and relative_e and "E" in args
               else args.get(a, pos[a]) for a in pos}
        start, target = [pos[a] for a in "XYZE"], [end[a] for a in "XYZE"]
        count = fl_caps.piece_count(fl_caps.move_shape(start, target),
                                    feed / 60.0 * factor)
        if count == 1:
            out.append(line)
        else:
            prev = start[3]
            for p in fl_caps.piece_ends(start, target, count):
                e = p[3] - prev if relative_e else p[3]
                out.append(f"G1 X{p[0]:.4f} Y{p[1]:.4f} Z{p[2]:.4f}"
                           f" E{e:.5f} F{feed:g}")
                prev = p[3]
        pos = end
    return out


def print_in_chunks(api, lines: List[str],
                    after_chunk: Optional[Callable[[List[str]], None]] = None
                    ) -> None:
    """Send G-code lines a chunk (chunks(): about CHUNK_S of planned print
    time) at a time, each followed by M400 and QUERY_FLOW_SENSOR (below),
    then after_chunk(chunk) if given.

    Batch mode never holds the G-code reader back as a printer does (about
    1 s of moves ahead), so feedback would arrive only after the whole file:
    the M400 bounds how far G-code runs ahead of the steps the twin has
    seen, and QUERY_FLOW_SENSOR after it generates those steps and hands the
    twin's samples to the sensor there and then (left to klippy's flush
    timer, how much of it is done before the next lines run depends on how
    busy the machine is). Cut every 10 lines instead (until 2026-11-30),
    a chunk of the bench print's long lines lasted up to 12 s planned (p90
    4 s), and feedback came that much later than on a printer."""
    for chunk in chunks(lines):
        api.gcode("\n".join(chunk + ["M400", "QUERY_FLOW_SENSOR"]))
        if after_chunk is not None:
            after_chunk(chunk)


def print_closed_loop(enable: int, build=None, venv=None,
                      profile: Dict[str, Any] = WEAK_PROFILE,
                      config: Path = CONFIG, mode: str = "predictive",
                      gcode: Path = GCODE, melt_ratio: Optional[float] = None
                      ) -> Tuple[Dict[str, Any], float]:
    """Print the slicer excerpt (or `gcode`) on the twin with the limiter on
    (1) or off (0) in `mode`, after warming the nozzle up, the profile
    activated with `melt_ratio` (as Moonraker sends the carried ratio);
    the limiter's status (with the toolhead's final `print_time` and the
    print's nozzle health estimate as Moonraker stores it, `nozzle_health`,
    added) and the filament
    the twin really moved while printing the file (sent by print_in_chunks,
    in the pieces a printer's limiter queues its long moves in)."""
    workdir = stack.short_tempdir("fl-limiter-")
    klippy = stack.Klippy(build or stack.build_klipper(),
                          venv or stack.klippy_venv(), config, workdir,
                          {"mcu": "atmega2560"})
    try:
        api = klippy.ready_api()
        try:
            seed = {} if melt_ratio is None else {"melt_ratio": melt_ratio}
            api.call("flowloop/set_active_profile", extruder="extruder",
                     profile=profile, working_point=0.5, **seed)
            api.gcode(f"SET_FLOWRATE_LIMIT ENABLE={enable} MODE={mode}")
            warm_up(api, WARM_UP_C)
            before = api.query("flow_sensor sim")["filament_position"] or 0.0
            start = api.query("toolhead")["print_time"]
            # Every run gets the pieces a printer's limiter queues (the same
            # path at the same speeds; the limiter off, a printer queues the
            # long moves whole): the chunks' M400 then stops the head at the
            # same places in every run, mid-line too (an artifact of batch
            # mode, the same in each: with the limiter off, 2.3 % of print
            # time and 1.6 mm less slip than the moves fed whole)
            print_in_chunks(api, cut_as_on_a_printer(gcode.read_text().splitlines()))
            moved = api.query("flow_sensor sim")["filament_position"] - before
            # what Moonraker's nozzle health asks at a job's end
            answer = api.call("flowrate_limiter/nozzle_evidence",
                              extruder="extruder")
            status = dict(api.query("flowrate_limiter"),
                          print_time=api.query("toolhead")["print_time"] - start,
                          nozzle_health=nh.estimate(
                              nh.PrintEvidence.from_dict(answer["evidence"]),
                              answer["model_melt_ratio"]))
            return status, moved
        finally:
            api.close()
    finally:
        klippy.stop()
        shutil.rmtree(workdir, ignore_errors=True)


def announced_peak(gcode: Path = GCODE, config: Path = CONFIG) -> float:
    """The file's peak flow as its annotation announces it on this printer
    (flowloop annotate's summary): one figure for every demo that names it."""
    limits = limits_from_config(read_config(config))
    return quantise_flow(plan_announcements(gcode, limits, AnnotateSettings()).peak)


def with_klippy(ctx) -> None:
    ctx.say(f"A weak hotend (melts 4 mm^3/s at 200 C) prints two layers of a "
            f"real slicer file\n(infill asks for up to {announced_peak():.1f}"
            f" mm^3/s), on the simulated sensor and hotend:")
    for enable, what in ((0, "limiter off"), (1, "limiter on ")):
        status, moved = print_closed_loop(enable)
        windows = status["grip_windows"]
        ctx.say(f"  {what}: {windows['below_min_grip']:3d} of {windows['judged']}"
                f" grip windows below min_grip {status['min_grip']:g}, filament"
                f" moved {moved:6.1f} mm, slowed {status['slowed_moves']} moves"
                f" by {status['slowed_time']:.0f} s")
    ctx.say(f"  (last cap {status['cap']} mm^3/s, {status['reason']}; model "
            f"{status['model']})")


def offline(ctx) -> None:
    ctx.say("No klippy: the reactive rule against ddPrint's (demand 20 mm^3/s, "
            "the hotend melts 12 for 10 s, decisions act 1 s later):")
    for rule in ("ddprint", "flowloop"):
        run = rule_plot.simulate(rule)
        slow = sum(1.0 - f for _, f, _ in run) * rule_plot.WINDOW_S
        ctx.say(f"  {rule:8s}: under-extruded {rule_plot.under_extrusion(run):5.1f}"
                f" mm^3, {slow:.1f} s of full-speed time lost")


def demo(ctx) -> None:
    if ctx.klippy_available:
        with_klippy(ctx)
    else:
        offline(ctx)
