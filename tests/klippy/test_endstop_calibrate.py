"""flowloop's delta geometry (flowloop.calibrate.delta) against Klipper's own.

Every expected number here comes from Klipper: its kinematics/delta.py
imported from the patched copy (endstop_calibrate_kinematics.py, which never
imports flowloop), or a batch-mode klippy moving a delta built from a config.
A mistake shared by flowloop's kinematics and flowloop's own simulated probes
cannot pass these.
"""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

from devtools.klippy_test import run_file, write_test
from flowloop.calibrate import delta
from flowloop.host.klipper_config import read_config

HERE = Path(__file__).resolve().parent
HELPER = HERE / "endstop_calibrate_kinematics.py"


def klipper_delta(build, venv, geometries, requests):
    """Answers of Klipper's DeltaCalibration (see the helper's docstring)."""
    job = {"geometries": {name: {"radius": g.radius, "angles": list(g.angles_deg),
                                 "arms": list(g.arm_lengths),
                                 "endstops": list(g.position_endstops)}
                          for name, g in geometries.items()},
           "requests": requests}
    proc = subprocess.run([str(venv.python), str(HELPER), str(build.tree / "klippy")],
                          input=json.dumps(job), capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def odd_geometry(rng) -> delta.DeltaGeometry:
    """A delta with every parameter off its default: radius, arms, endstops,
    and towers up to 3 degrees off 210/330/90."""
    radius = rng.uniform(100.0, 200.0)
    return delta.DeltaGeometry(
        radius, tuple(radius + rng.uniform(110.0, 190.0, 3)),
        tuple(rng.uniform(250.0, 350.0, 3)),
        tuple(np.add(delta.DEFAULT_ANGLES_DEG, rng.uniform(-3.0, 3.0, 3))))


def reachable_points(rng, geometry, count):
    r = rng.uniform(0.0, 0.6 * geometry.radius, count)
    phi = rng.uniform(0.0, 2 * np.pi, count)
    return np.column_stack((r * np.cos(phi), r * np.sin(phi),
                            rng.uniform(-5.0, 60.0, count)))


def test_inverse_and_forward_kinematics_match_klippers(klipper_build, klippy_venv):
    rng = np.random.default_rng(9)
    geometries = {f"g{i}": odd_geometry(rng) for i in range(25)}
    cases, requests = [], []
    for name, g in geometries.items():
        for xyz in reachable_points(rng, g, 6):
            # forward kinematics on travels nobody computed from xyz
            travel = g.travel(xyz) + rng.uniform(-2.0, 2.0, 3)
            cases.append((g, xyz, travel))
            requests += [{"op": "travel", "geometry": name, "xyz": list(xyz)},
                         {"op": "position", "geometry": name, "travel": list(travel)}]
    answers = klipper_delta(klipper_build, klippy_venv, geometries, requests)
    for (g, xyz, travel), k_travel, k_position in zip(cases, answers[::2],
                                                      answers[1::2]):
        assert g.travel(xyz) == pytest.approx(k_travel, abs=1e-9)
        assert g.position_from_travel(travel) == pytest.approx(k_position, abs=1e-9)


def test_simulated_probe_heights_match_klippers_for_a_printer_built_otherwise(
        klipper_build, klippy_venv):
    # The true printer differs from the believed one in every parameter the
    # solver does not fit (radius, an angle, the arms) as well as the endstops.
    believed = delta.DeltaGeometry(140.0, (300.0, 300.4, 300.0), (300.0,) * 3,
                                   (210.0, 329.8, 90.0))
    true = delta.DeltaGeometry(140.3, (300.2, 300.1, 299.9), (301.2, 298.8, 300.5),
                               (210.4, 329.8, 89.7))
    points = delta.probe_points(believed.angles_deg, 100.0)
    answers = klipper_delta(
        klipper_build, klippy_venv, {"believed": believed, "true": true},
        [{"op": "probe_z", "believed": "believed", "true": "true", "xy": list(p),
          "bed_z": 0.4} for p in points])
    ours = delta.simulate_probe_z(believed, true, points, bed_z=0.4)
    assert ours == pytest.approx(answers, abs=1e-9)
    assert np.ptp(answers) > 1.0   # the printers really differ


# --- klippy moving a delta built from a config ---------------------------------

POSITION_RE = re.compile(
    r"stepper: stepper_a:(\S+) stepper_b:(\S+) stepper_c:(\S+)\n"
    r"kinematic: X:(\S+) Y:(\S+) Z:(\S+)\n"
    r"toolhead: X:(\S+) Y:(\S+) Z:(\S+)")
POINTS = [(0.0, 0.0, 20.0), (-86.6, -50.0, 0.3), (86.4, -50.3, -0.8),
          (0.0, 100.0, 5.0), (40.0, 70.0, 12.5), (-95.0, 30.0, 45.0)]


def klippy_positions(build, venv, workdir, config, points):
    """GET_POSITION after G28 (home), then for each point after a move and
    after SET_KINEMATIC_POSITION to it: [(steppers, kinematic, toolhead)]."""
    gcode = ["G28", "GET_POSITION"]
    for x, y, z in points:
        gcode += [f"G1 X{x} Y{y} Z{z} F6000",
                  # flushes step generation, so the steppers report the move
                  "SET_STEPPER_ENABLE STEPPER=stepper_a ENABLE=1",
                  "GET_POSITION",
                  f"SET_KINEMATIC_POSITION X={x} Y={y} Z={z}",
                  "GET_POSITION"]
    # SET_KINEMATIC_POSITION needs [force_move]; the delta itself is the file's.
    printer_cfg, test = write_test(
        workdir, "printer", "\n".join(gcode) + "\n",
        cfg=f"[include {config}]\n[force_move]\nenable_force_move: True\n")
    log = run_file(test, build, venv, workdir)
    found = [tuple(np.array(m.groups()[i:i + 3], float) for i in (0, 3, 6))
             for m in POSITION_RE.finditer(log)]
    assert len(found) == 1 + 2 * len(points), log[-3000:]
    return printer_cfg, found


@pytest.mark.parametrize("config", ["endstop_calibrate.cfg",
                                    "endstop_calibrate_kinematics.cfg"])
def test_klippy_puts_the_carriages_where_flowloop_says(
        klipper_build, klippy_venv, short_tmp, config):
    printer_cfg, found = klippy_positions(klipper_build, klippy_venv, short_tmp,
                                          HERE / config, POINTS)
    g = delta.geometry_from_config(read_config(printer_cfg))
    (home_steppers, _, home), moves = found[0], found[1:]
    # Homed: carriages at the absolute endstops, the effector where they put it.
    assert home_steppers == pytest.approx(g.abs_endstops, abs=2e-6)
    assert home == pytest.approx(g.position(g.abs_endstops), abs=2e-6)
    step_mm = 40.0 / (200 * 256)
    for (x, y, z), moved, placed in zip(POINTS, moves[::2], moves[1::2]):
        steppers, kinematic, toolhead = moved
        assert toolhead == pytest.approx((x, y, z), abs=1e-9)
        # after a move the steppers stand on whole steps
        assert steppers == pytest.approx(g.carriage_heights(toolhead), abs=step_mm)
        # Klipper's forward kinematics of those carriage heights
        assert kinematic == pytest.approx(g.position(steppers), abs=1e-5)
        # SET_KINEMATIC_POSITION: Klipper's inverse kinematics, exactly
        assert placed[0] == pytest.approx(g.carriage_heights((x, y, z)), abs=2e-6)


# --- endstop_calibrate.test's heights are Klipper's ----------------------------

BELIEVED = delta.DeltaGeometry(140.0, (300.0, 300.4, 300.0), (300.0,) * 3,
                               (210.0, 329.8, 90.0))
TRUE_ENDSTOPS = (301.2, 298.8, 300.5)
# the true printer behind each ENDSTOP_CALIBRATE METHOD=manual test
TRUE_PRINTERS = {
    "endstop_calibrate.test": BELIEVED.with_endstops(TRUE_ENDSTOPS),
    "endstop_calibrate_included.test": BELIEVED.with_endstops(TRUE_ENDSTOPS),
    # tower C really stands at 90.5 degrees
    "endstop_calibrate_angle.test": delta.DeltaGeometry(
        140.0, BELIEVED.arm_lengths, TRUE_ENDSTOPS, (210.0, 329.8, 90.5)),
}


def pasted_heights(test_file: Path):
    return [float(m.group(1))
            for m in re.finditer(r"^G1 Z(\S+)$", test_file.read_text(), re.M)]


@pytest.mark.parametrize("test_file", sorted(TRUE_PRINTERS))
def test_the_manual_probe_heights_of_the_test_files_are_klippers(
        klipper_build, klippy_venv, test_file):
    assert delta.geometry_from_config(
        read_config(HERE / "endstop_calibrate.cfg")) == BELIEVED
    points = delta.probe_points(BELIEVED.angles_deg, 100.0)
    heights = klipper_delta(
        klipper_build, klippy_venv,
        {"believed": BELIEVED, "true": TRUE_PRINTERS[test_file]},
        [{"op": "probe_z", "believed": "believed", "true": "true", "xy": list(p)}
         for p in points])
    assert pasted_heights(HERE / test_file) == [round(h, 6) for h in heights]
