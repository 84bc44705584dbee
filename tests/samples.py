"""Test data: sample profiles and the ddPrint profiles shipped in tests/data."""

from __future__ import annotations

from pathlib import Path

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


# A weak PLA for the bake's tests: its line melts 3.5 mm^3/s printing at
# 200 C, 0.1 more per degree, up to 240 C (the bake has heat to plan)
WEAK_PROFILE = {
    "identity": {"name": "weak", "nozzle_diameter_mm": 0.4},
    "lines": {"into_air": {"slope_mm3_s_per_c": 0.1, "temp_c": 200.0,
                           "flow_mm3_s": 4.5},
              "real_print": {"slope_mm3_s_per_c": 0.1, "temp_c": 200.0,
                             "flow_mm3_s": 3.5}},
    "bounds": {"min_temp_c": 190.0, "recommended_temp_c": 200.0,
               "max_temp_c": 240.0},
    "provenance": {"method": "manual"}}
