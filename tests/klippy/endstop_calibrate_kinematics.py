"""Klipper's own delta kinematics, for checking flowloop's (test helper).

Run with klippy's Python: `python endstop_calibrate_kinematics.py KLIPPY_DIR`
with a JSON request on stdin; prints a JSON list of answers. It imports only
Klipper (kinematics/delta.py's DeltaCalibration, the class DELTA_CALIBRATE
uses to turn probe results into positions), never flowloop, so flowloop's
geometry is compared with numbers it had no part in.

Request: {"geometries": {NAME: {"radius", "angles", "arms", "endstops"}},
          "requests": [...]} where each request is one of
  {"op": "travel", "geometry": NAME, "xyz": [x, y, z]}
      -> how far each carriage is below its endstop with the effector at xyz
  {"op": "position", "geometry": NAME, "travel": [a, b, c]}
      -> the effector position for those carriage travels
  {"op": "probe_z", "believed": NAME, "true": NAME, "xy": [x, y], "bed_z": z}
      -> the z the believed printer reports at (x, y) when the true printer's
         nozzle is at bed_z (same carriage travels, the other geometry)
"""

import json
import sys
from pathlib import Path

# A stepdist of 1 makes Klipper's "stable position" the travel in mm.
STEPDISTS = [1.0, 1.0, 1.0]


def calibrations(delta, geometries):
    return {name: delta.DeltaCalibration(g["radius"], g["angles"], g["arms"],
                                         g["endstops"], STEPDISTS)
            for name, g in geometries.items()}


def probe_z(believed, true, xy, bed_z):
    # Lower the toolhead at the believed (x, y) until the true nozzle is at
    # bed_z; d(true z)/d(believed z) is close to 1, so this converges fast.
    z = 0.0
    for _ in range(60):
        stable = believed.calc_stable_position([xy[0], xy[1], z])
        error = true.get_position_from_stable(stable)[2] - bed_z
        z -= error
        if abs(error) < 1e-13:
            break
    return z


def answer(cals, request):
    op = request["op"]
    if op == "travel":
        return cals[request["geometry"]].calc_stable_position(request["xyz"])
    if op == "position":
        return cals[request["geometry"]].get_position_from_stable(request["travel"])
    if op == "probe_z":
        return probe_z(cals[request["believed"]], cals[request["true"]],
                       request["xy"], request.get("bed_z", 0.0))
    raise ValueError(f"unknown op {op!r}")


def main():
    sys.path.insert(0, sys.argv[1])
    if Path(sys.argv[1], "__init__.py").is_file():
        # Kalico: klippy is a package whose modules import klippy.mathutil
        sys.path.insert(0, str(Path(sys.argv[1]).parent))
    from kinematics import delta
    job = json.load(sys.stdin)
    cals = calibrations(delta, job["geometries"])
    json.dump([answer(cals, r) for r in job["requests"]], sys.stdout)


if __name__ == "__main__":
    main()
