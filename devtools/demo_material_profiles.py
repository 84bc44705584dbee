"""`make demo` step: import a ddPrint profile, serve it, activate it in klippy."""

from __future__ import annotations

import tempfile
from pathlib import Path
from urllib.parse import quote

from flowloop.cli import main as flowloop_cli
from flowloop.material import ddprint, plot
from flowloop.material import profile as fl_profile

SAMPLE = "shared/data/ddprint-profiles/mat-profiles/UM2-1/herz-pla-red.json"

# The same numbers, for a checkout without ../shared/data beside it.
FALLBACK = {
    "identity": {"name": "herz-pla-red_80", "printer": "UM2-1",
                 "nozzle_diameter_mm": 0.8, "filament_name": "herz-pla-red",
                 "filament_type": "PLA"},
    "lines": {"into_air": {"slope_mm3_s_per_c": 0.146, "temp_c": 171.6312,
                           "flow_mm3_s": 7.5789},
              "real_print": {"slope_mm3_s_per_c": 0.146, "temp_c": 210.0,
                             "flow_mm3_s": 10.1356}},
    "bounds": {"min_temp_c": 190.0, "recommended_temp_c": 210.0, "max_temp_c": 260.0},
    "provenance": {"method": "manual", "note": "ddPrint's herz-pla-red numbers"},
}


def sample_profile(ctx) -> fl_profile.Profile:
    path = ctx.project.parent / SAMPLE
    if path.is_file():
        ctx.say(f"importing the ddPrint file {path.name} (printer UM2-1)")
        return ddprint.import_file(path).profiles[0]
    ctx.say(f"({path} not found: using the same numbers built in)")
    return fl_profile.profile_from_dict(FALLBACK)


def demo(ctx) -> None:
    profile = sample_profile(ctx)
    name = profile.identity.name
    ctx.say(f"profile {name!r}: into air {profile.lines.into_air.temp_c:g} degC @ "
            f"{profile.lines.into_air.flow_mm3_s:g} mm^3/s, real print "
            f"{profile.lines.real_print.temp_c:g} degC @ "
            f"{profile.lines.real_print.flow_mm3_s:g} mm^3/s, slope "
            f"{profile.lines.into_air.slope_mm3_s_per_c:g} mm^3/s per degC")
    for wp in (0.0, 0.5, 1.0):
        ctx.say(f"  12 mm^3/s at working point {wp:g} needs "
                f"{fl_profile.temp_for_flow(profile, 12.0, wp):.1f} degC; at 230 degC "
                f"the hotend melts {fl_profile.max_flow_at(profile, 230.0, wp):.2f} "
                f"mm^3/s")
    mr = ctx.moonraker
    if mr is None:
        offline(ctx, profile)
        return
    status, body = mr.request("POST", "/server/flowloop/profile",
                              {"profile": fl_profile.profile_to_dict(profile)})
    ctx.say(f"POST /server/flowloop/profile -> {status} {body.get('result')}")
    status, body = mr.request("POST", "/server/flowloop/profile/activate",
                              {"name": name, "extruder": "extruder",
                               "working_point": 0.5})
    ctx.say(f"POST /server/flowloop/profile/activate -> {status} {body.get('result')}")
    q = quote(name, safe="")
    ctx.say("endpoints:")
    for path in (f"/server/flowloop/profile?name={q}", "/server/flowloop/profiles",
                 f"/server/flowloop/profile/plot?name={q}&working_point=0.5",
                 "/server/flowloop/info"):
        ctx.say(f"  {mr.url}{path}")
    status, svg = mr.request("GET", f"/server/flowloop/profile/plot?name={q}")
    ctx.say(f"  (the plot is {len(svg)} bytes of SVG)")
    if ctx.klippy_available:
        shown = ctx.query("flowloop").get("profiles", {}).get("extruder", {})
        ctx.say(f"klippy printer.flowloop.profiles.extruder: name {shown.get('name')!r}"
                f", working point {shown.get('working_point')}, max_temp_c "
                f"{shown.get('max_temp_c')} "
                f"(heater max {shown.get('heater_max_temp_c')})")
    else:
        ctx.say("(no klippy: the activation is stored and sent when klippy is ready)")


def offline(ctx, profile: fl_profile.Profile) -> None:
    with tempfile.TemporaryDirectory(prefix="fl-demo-") as tmp:
        src = ctx.project.parent / SAMPLE
        if src.is_file():
            ctx.say(f"$ flowloop profile import {src.name} -o {tmp}")
            flowloop_cli(["profile", "import", str(src), "-o", tmp])
        out = Path(tmp) / "plot.svg"
        out.write_text(plot.svg(profile))
        ctx.say(f"plot written: {out.stat().st_size} bytes of SVG (flowloop profile "
                f"plot FILE -o plot.svg)")
