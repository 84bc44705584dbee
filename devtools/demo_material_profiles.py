"""`make demo` step: import a ddPrint profile, serve it, activate it in klippy."""

from __future__ import annotations

import contextlib
import io
import tempfile
from pathlib import Path
from urllib.parse import quote

from flowloop.cli import main as flowloop_cli
from flowloop.material import ddprint, plot
from flowloop.material import profile as fl_profile

# Shipped with the tests: ddPrint's public material profiles (SOURCE.md there).
PROFILES = Path("tests/data/ddprint-profiles/mat-profiles")
SAMPLE = PROFILES / "UM2-1/herz-pla-red.json"
# A real file whose real-print line lies above its into-air line.
IMPLAUSIBLE = PROFILES / "JP-1/kaiser-pla-grey.json"


def sample_profile(ctx) -> fl_profile.Profile:
    ctx.say(f"importing the ddPrint file {SAMPLE} (printer UM2-1)")
    return ddprint.import_file(ctx.project / SAMPLE).profiles[0]


def implausible_but_kept(ctx) -> None:
    (profile,) = ddprint.import_file(ctx.project / IMPLAUSIBLE).profiles
    ctx.say(f"importing {IMPLAUSIBLE}: kept, with a warning:")
    for warning in fl_profile.line_warnings(profile):
        ctx.say(f"  {warning}")
    temps = ", ".join(f"{fl_profile.temp_for_flow(profile, 12.0, wp):.1f}"
                      for wp in (0.0, 0.5, 1.0))
    ctx.say(f"  12 mm^3/s needs {temps} degC at working points 0, 0.5, 1 "
            f"(the into-air line at each)")


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
    implausible_but_kept(ctx)
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
        ctx.say(f"$ flowloop profile import {SAMPLE} -o OUT")
        with contextlib.redirect_stdout(io.StringIO()):  # it names the temp dir
            flowloop_cli(["profile", "import", str(ctx.project / SAMPLE), "-o", tmp])
        for written in sorted(Path(tmp).iterdir()):
            ctx.say(f"wrote OUT/{written.name}")
        out = Path(tmp) / "plot.svg"
        out.write_text(plot.svg(profile))
        ctx.say(f"plot written: {out.stat().st_size} bytes of SVG (flowloop profile "
                f"plot FILE -o plot.svg)")
