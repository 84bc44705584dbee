"""Demo step: differential A/B calibration, two rounds to convergence.

Offline: a simulated CoreXY whose belts move +0.22 % (A) and -0.16 % (B),
pylons printed with shrinkage and read with caliper noise, then
`flowloop ab-calibrate` twice and the pylon G-code. With Klipper: the demo
printer runs DIFF_AB_CALIBRATE if it has [diff_ab_calibrate], otherwise
the CoreXY batch test (tests/klippy/diff_ab_calibrate_corexy.test) runs and
its report and staged SAVE_CONFIG values are shown.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np

from flowloop.calibrate import pylons
from flowloop.cli import main as flowloop_main

TRUE_BELT_SCALE = {"a": 1.00221, "b": 0.99843}   # actual mm per commanded mm
DISTANCES = (10.0, 150.0)


def caliper_readings(rng, belt_scale, rotation_distance, nominal_rd=40.0):
    """Five readings per distance of one row printed with this rotation_distance."""
    # steps per commanded mm follow rotation_distance; the belt sets mm per step
    motion = belt_scale * nominal_rd / rotation_distance
    s = pylons.along_row_positions(DISTANCES, 4.0)
    printed_width = 4.0 * (1 - 0.004) - 0.03          # shrinkage, thin lines
    out = []
    for k in (1, 2):
        true = motion * (s[k] - s[0]) + printed_width
        out.append(",".join(f"{v:.2f}" for v in true + rng.normal(0, 0.006, 5)))
    return out


def run_cli(argv):
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = flowloop_main(argv)
    return code, out.getvalue()


def offline(ctx) -> dict:
    rng = np.random.default_rng(2023)
    rd = {"a": 40.0, "b": 40.0}
    history = Path(tempfile.mkdtemp(prefix="fl-ab-")) / "history.json"
    ctx.say(f"Simulated CoreXY: belts move {100 * (TRUE_BELT_SCALE['a'] - 1):+.3f} % "
            f"(A) and {100 * (TRUE_BELT_SCALE['b'] - 1):+.3f} % (B); "
            f"rotation_distance starts at 40.")
    last = {}
    for round_no in (1, 2):
        a1, a2 = caliper_readings(rng, TRUE_BELT_SCALE["a"], rd["a"])
        b1, b2 = caliper_readings(rng, TRUE_BELT_SCALE["b"], rd["b"])
        argv = ["ab-calibrate", "--rotation-distance-a", f"{rd['a']:.6f}",
                "--rotation-distance-b", f"{rd['b']:.6f}", "--a1", a1, "--a2", a2,
                "--b1", b1, "--b2", b2, "--history", str(history)]
        ctx.say(f"\nround {round_no}: $ flowloop ab-calibrate ... --a1 {a1} --a2 {a2} "
                f"--b1 {b1} --b2 {b2}")
        code, text = run_cli(argv)
        for line in text.splitlines():
            if line.startswith(("A ", "B ", "Converged", "Not converged", "  #")):
                ctx.say("  " + line)
        code, text = run_cli(argv[:-2] + ["--json"])
        last = json.loads(text)
        rd = {axis: last[axis]["rotation_distance"] for axis in ("a", "b")}
    ctx.say(f"  --json: {json.dumps(last)}")
    ideal = {axis: 40.0 * TRUE_BELT_SCALE[axis] for axis in ("a", "b")}
    ctx.say("  true values: "
            + ", ".join(f"{a.upper()} {v:.4f}" for a, v in ideal.items())
            + "  (found: "
            + ", ".join(f"{a.upper()} {v:.4f}" for a, v in rd.items()) + ")")
    shutil.rmtree(history.parent, ignore_errors=True)

    options = pylons.PylonOptions()
    gcode = pylons.render(options)
    ctx.say(f"\n$ flowloop ab-pylons  -> {len(gcode.splitlines())} lines of G-code, "
            f"pylons at:")
    ctx.say("  " + "  ".join(f"{p.name} ({p.centre[0]:.1f},{p.centre[1]:.1f})"
                             for p in pylons.pylons(options)))
    return rd


def on_demo_printer(ctx) -> bool:
    sections = ctx.query("flowloop").get("sections", [])
    if "diff_ab_calibrate" not in sections:
        return False
    before = ctx.query("diff_ab_calibrate")["rotation_distance"]
    readings = ("A1=10.01,10.02,10.00 A2=150.30,150.31,150.32 "
                "B1=10.00,10.01,9.99 B2=149.80,149.81,149.82")
    ctx.say(f"demo printer (its own readings, not the simulated rounds above):"
            f"\n$ DIFF_AB_CALIBRATE {readings}")
    ctx.gcode(f"DIFF_AB_CALIBRATE {readings}")
    after = ctx.query("diff_ab_calibrate")["rotation_distance"]
    for stepper in sorted(after):
        ctx.say(f"  {stepper}: rotation_distance {before[stepper]:.6f} ->"
                f" {after[stepper]:.6f} (applied, staged for SAVE_CONFIG)")
    return True


def in_batch_klippy(ctx, test: Path) -> None:
    log = ctx.batch_klippy_log(test)
    ctx.say(f"klippy batch run of {test.name} (WAIT_BED_EQUILIBRIUM, two rounds of "
            "DIFF_AB_CALIBRATE with G28 between):")
    keep = ("A (x=y", "B (x=-y", "stepper_x: rot", "stepper_y: rot", "save_config: set",
            "Converged", "X and Y are no longer", "!! Bed", "Bed heater")
    for line in log.splitlines():
        if line.startswith(keep):
            ctx.say("  " + line)


def demo(ctx) -> None:
    offline(ctx)
    if not ctx.klippy_available:
        ctx.say("(no klippy: the DIFF_AB_CALIBRATE run is shown by "
                "tests/klippy/diff_ab_calibrate_corexy.test)")
        return
    ctx.say("")
    if not on_demo_printer(ctx):
        in_batch_klippy(ctx, ctx.project / "tests" / "klippy"
                        / "diff_ab_calibrate_corexy.test")

