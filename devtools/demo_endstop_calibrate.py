"""Demo step: delta tower endstops solved in one round.

Offline: a synthetic delta with wrong endstops, this solver against the
per-tower loop, and `flowloop delta-endstops --json`. With Klipper: the demo
printer is cartesian, so ENDSTOP_CALIBRATE METHOD=manual runs in its own
batch-mode delta klippy (tests/klippy/endstop_calibrate.test) and its report
and staged SAVE_CONFIG values are shown.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

from flowloop.calibrate import delta
from flowloop.cli import main as flowloop_main

TRUE_ENDSTOPS = (301.2, 298.8, 300.5)


def _naive_rounds(believed, true, points, limit_mm=0.01):
    for rounds in range(1, 50):
        z = delta.simulate_probe_z(believed, true, points)
        towers = [z[i] for i in (1, 2, 3)]
        believed = believed.with_endstops(
            delta.naive_endstop_update(believed.position_endstops, towers))
        after = delta.simulate_probe_z(believed, true, points)
        if max(abs(h) for h in after) < limit_mm:
            return rounds
    return None


def offline(ctx, cfg: Path) -> None:
    from flowloop.host.klipper_config import read_config
    believed = delta.geometry_from_config(read_config(cfg))
    true = believed.with_endstops(TRUE_ENDSTOPS)
    points = delta.probe_points(believed.angles_deg, 100.0)
    z = delta.simulate_probe_z(believed, true, points)
    probes = [(x, y, round(float(h), 3)) for (x, y), h in zip(points, z)]
    ctx.say(f"A delta believing endstops {believed.position_endstops}; really "
            f"{TRUE_ENDSTOPS}. Paper-test heights at 7 points (mm):")
    ctx.say("  " + "  ".join(f"{p[2]:+.3f}" for p in probes))
    solution = delta.solve_endstops(believed, probes)
    ctx.say("solver, one round: " + ", ".join(
        f"{n} {v:.4f}" for n, v in zip(delta.TOWERS, solution.position_endstop))
        + f"  (spread {solution.spread_before_mm:.3f} -> "
          f"{solution.spread_after_mm:.4f} mm, {solution.iterations} Newton steps)")
    rounds = _naive_rounds(believed, true, points[:4])
    ctx.say(f"per-tower loop: {rounds} probe rounds to get within 0.01 mm")
    argv = ["delta-endstops", "--printer-cfg", str(cfg), "--json"]
    for x, y, h in probes:   # negative coordinates typed as they read
        argv += ["--probe", f"{x:.3f},{y:.3f},{h:.3f}"]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = flowloop_main(argv)
    first = ",".join(f"{v:.3f}" for v in probes[1])
    ctx.say(f"$ flowloop delta-endstops --printer-cfg {cfg.name} --probe {first}"
            " ... --json")
    ctx.say(f"  {out.getvalue().strip()}  (exit {code})")


def in_klippy(ctx, test: Path) -> None:
    log = ctx.batch_klippy_log(test)
    ctx.say(f"klippy batch run of {test.name} (G28, ENDSTOP_CALIBRATE "
            "METHOD=manual, 7 x G1 Z/ACCEPT):")
    keep = ("ENDSTOP_CALIBRATE: ", "stepper_a: position", "stepper_b: position",
            "stepper_c: position", "predicted spread", "save_config: set")
    for line in log.splitlines():
        if line.startswith(keep):
            ctx.say("  " + line)


def demo(ctx) -> None:
    tests = ctx.project / "tests" / "klippy"
    offline(ctx, tests / "endstop_calibrate.cfg")
    if ctx.klippy_available:
        in_klippy(ctx, tests / "endstop_calibrate.test")
    else:
        ctx.say("(no klippy: the ENDSTOP_CALIBRATE run is shown by "
                "tests/klippy/endstop_calibrate.test)")

