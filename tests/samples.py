"""Test data: sample profiles and the ddPrint profiles shipped in tests/data."""

from __future__ import annotations

import math
from pathlib import Path

from devtools.demo_flowrate_limiter import WEAK_PROFILE as DEMO_WEAK_PROFILE

# Every material file of ddPrint's public profile repository (see SOURCE.md).
DATA = Path(__file__).resolve().parent / "data" / "ddprint-profiles"
MAT = DATA / "mat-profiles"


def make(air=(0.146, 171.6312, 7.5789), real=(0.146, 210.0, 10.1356),
         bounds=(190.0, 210.0, 260.0), name="herz-pla-red_80", identity=None,
         **extra):
    """The UM2-1 herz-pla-red 0.8 mm numbers (ddPrint file), as a dict;
    identity updates the identity fields, extra the top-level ones."""
    data = {
        "identity": {"name": name, "printer": "UM2-1", "nozzle_diameter_mm": 0.8,
                     "filament_name": "herz-pla-red", "filament_type": "PLA"},
        "lines": {
            "into_air": dict(zip(("slope_mm3_s_per_c", "temp_c", "flow_mm3_s"), air)),
            "real_print": dict(zip(("slope_mm3_s_per_c", "temp_c", "flow_mm3_s"),
                                   real)),
        },
        "bounds": dict(zip(("min_temp_c", "recommended_temp_c", "max_temp_c"),
                           bounds)),
        "provenance": {"method": "manual"},
    }
    data["identity"].update(identity or {})
    data.update(extra)
    return data


# A line the simulated twin melts at any working point (into_air ==
# real_print): the measurement tests' "known" material, as a dict.
TWIN_SLOPE, TWIN_TEMP, TWIN_FLOW = 0.12, 210.0, 6.0


def twin_known():
    line = {"slope_mm3_s_per_c": TWIN_SLOPE, "temp_c": TWIN_TEMP,
            "flow_mm3_s": TWIN_FLOW}
    return {
        "identity": {"name": "known", "nozzle_diameter_mm": 0.4},
        "lines": {"into_air": dict(line), "real_print": dict(line)},
        "bounds": {"min_temp_c": 185.0, "recommended_temp_c": 210.0,
                   "max_temp_c": 250.0},
        "provenance": {"method": "manual"},
    }


# A weak PLA for the bake's tests: the demo's weak profile (its line melts
# 3.5 mm^3/s printing at 200 C, 0.1 more per degree) recommended at 200 C
# and allowed up to 240 C (the bake has heat to plan below max_temp)
WEAK_PROFILE = {
    **DEMO_WEAK_PROFILE,
    "bounds": {"min_temp_c": 190.0, "recommended_temp_c": 200.0,
               "max_temp_c": 240.0}}

# 12 mm^3/s at 200 C (working point 0.5): a hotend three times the weak one
STRONG_PROFILE = {
    **WEAK_PROFILE, "identity": {"name": "strong", "nozzle_diameter_mm": 0.4},
    "lines": {"into_air": {"slope_mm3_s_per_c": 0.1, "temp_c": 200.0,
                           "flow_mm3_s": 12.5},
              "real_print": {"slope_mm3_s_per_c": 0.1, "temp_c": 200.0,
                             "flow_mm3_s": 11.5}}}


def arc_fitted(layers: int, absolute_e: bool) -> bytes:
    """A file as an arc fitter leaves it: each layer's rings as quarter
    arcs (alternately G2 and G3) between straight infill lines, relative or
    absolute E (reset with G92 E0 each layer)."""
    area = 0.45 * 0.2 / (math.pi * 1.75 ** 2 / 4)
    out = ["M82" if absolute_e else "M83", "G1 Z0.2 F600", "G1 X110 Y100 F6000"]
    e = 0.0

    def extrude(mm):
        nonlocal e
        e = e + mm * area if absolute_e else mm * area
        return f"E{e:.5f}"
    for layer in range(layers):
        out += [";LAYER_CHANGE", f"G1 Z{0.2 + 0.2 * layer:.2f} F600"]
        if absolute_e:
            out.append("G92 E0")
            e = 0.0
        for k, r in enumerate((10.0, 9.55, 5.0)):
            out.append(f"G1 X{100 + r:.3f} Y100 F9000")
            x, y = 100 + r, 100.0
            cw = (layer + k) % 2 == 1
            for q in range(4):
                angle = (-1 if cw else 1) * math.pi / 2 * (q + 1)
                nx, ny = 100 + r * math.cos(angle), 100 + r * math.sin(angle)
                out.append(f"{'G2' if cw else 'G3'} X{nx:.3f} Y{ny:.3f}"
                           f" I{100 - x:.3f} J{100 - y:.3f}"
                           f" {extrude(math.pi / 2 * r)} F2400")
                x, y = nx, ny
        for i in range(4):
            out += [f"G1 X92 Y{94 + 4 * i} F9000",
                    f"G1 X108 Y{94 + 4 * i} {extrude(16)} F4800"]
    return ("\n".join(out) + "\n").encode()
