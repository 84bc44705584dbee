"""Files and profiles autotemp can do little with (issue 40): a file with no
extrusion, one with only travel after its first layer, one whose flow is
entirely above what the profile melts at its maximum, a profile whose line
barely rises with temperature. Each gets one clear line from the bake, and
every target it writes stays within the profile's and the printer's
limits."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest

from flowloop.cli import main
from flowloop.control.autotemp import (
    FLAT_GAIN_MM3_S,
    TemperaturePlan,
    TempLimits,
    flat_line_note,
)
from flowloop.material.profile import Line
from tests.unit.test_autotemp_bake import WEAK  # the bake's weak profile

pytestmark = pytest.mark.unit

# Every heater target a line sets (commented lines set none).
TARGET = re.compile(r"^\s*M10[49]\b[^;\n]*?\s[SR](\d+(?:\.\d*)?)", re.M)
START = "G28\nM109 S200\nG90\nM82\nG92 E0\n"


def square(z: float, e: float, feed: float, width: float = 20.0,
           e_per_mm: float = 0.033):
    """Lines of one square perimeter at z from absolute E e; (text, new e)."""
    lines = [f"G1 Z{z:.2f} F3000", f"G1 X50 Y50 F{feed:g}"]
    for x, y in ((50 + width, 50), (50 + width, 50 + width), (50, 50 + width),
                 (50, 50)):
        e += width * e_per_mm
        lines.append(f"G1 X{x:g} Y{y:g} E{e:.5f} F{feed:g}")
    return "\n".join(lines) + "\n", e


def first_layer(layers: int = 4, feed: float = 1800.0, e_per_mm: float = 0.033
                ) -> str:
    text, e = START, 0.0
    for _ in range(layers * 10):
        part, e = square(0.2, e, feed, e_per_mm=e_per_mm)
        text += part
    return text


def printer_cfg(tmp_path: Path, max_temp: float = 235.0) -> Path:
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[printer]\nkinematics: cartesian\nmax_velocity: 300\n"
                   "max_accel: 3000\n\n[extruder]\nnozzle_diameter: 0.4\n"
                   "filament_diameter: 1.75\nmax_extrude_cross_section: 50\n"
                   f"min_temp: 195\nmax_temp: {max_temp:g}\n")
    return cfg


def bake(tmp_path: Path, capsys, gcode: str, profile: dict = WEAK):
    src = tmp_path / "part.gcode"
    src.write_text(gcode)
    prof = tmp_path / "profile.json"
    prof.write_text(json.dumps(profile))
    out = tmp_path / "baked.gcode"
    code = main(["annotate", str(src), "-o", str(out), "--bake", str(prof),
                 "--printer-cfg", str(printer_cfg(tmp_path))])
    said = capsys.readouterr()
    assert code == 0, said.err
    targets = [float(x) for x in TARGET.findall(out.read_text())]
    # within the profile (190..240) and the printer (195..235): 195..235
    assert all(195.0 <= t <= 235.0 for t in targets), targets
    return said.out, said.err, targets


def test_a_file_without_extrusion_says_so_and_sets_nothing(tmp_path, capsys):
    gcode = START + "".join(f"G1 X{50 + i % 20} Y{50 + i % 7} F6000\n"
                            for i in range(200))
    out, err, targets = bake(tmp_path, capsys, gcode)
    assert err == (f"flowloop annotate: warning: {tmp_path / 'part.gcode'}:"
                   " no move extrudes: nothing to announce\n")
    assert "0 M104" in out and "none to none C" in out
    assert targets == [200.0]            # the file's own M109, as it was


def test_only_travel_after_the_first_layer_is_one_line(tmp_path, capsys):
    # 20 moves of 100 mm at 20 mm/s: 100 s of travel, layer after layer
    travel = "".join(f"G1 Z{0.4 + 0.2 * i:.2f} F600\nG1 X{150 if i % 2 else 50} Y60"
                     f" F1200\n" for i in range(20))
    out, _, targets = bake(tmp_path, capsys, first_layer() + travel)
    (line,) = [x for x in out.splitlines() if "nothing is extruded" in x]
    assert re.fullmatch(r"  nothing is extruded in the last 1 min \d\d s of the"
                        r" print \(after 1 min \d\d s\): the baked targets fall"
                        r" to their minimum there", line), line
    assert targets and max(targets) <= 235.0
    # the last target written is the floor (profile 190, printer 195)
    assert targets[-1] == 195.0


def test_a_print_that_ends_in_a_few_seconds_says_nothing_of_travel(tmp_path,
                                                                   capsys):
    out, _, _ = bake(tmp_path, capsys, first_layer() + "G1 Z10 F600\n")
    assert "nothing is extruded" not in out


def test_flow_entirely_above_the_maximum_is_clamped_and_said(tmp_path, capsys):
    # 60 mm/s of a 3.3 mm^2 bead: about 18 mm^3/s, where the profile melts
    # 8 mm^3/s at its 240 C, 7.5 at the printer's 235 C
    out, _, targets = bake(tmp_path, capsys,
                           first_layer(feed=3600.0, e_per_mm=2.0))
    (line,) = [x for x in out.splitlines() if "needs more than" in x]
    assert re.fullmatch(r"  every window with flow \(\d+\) needs more than the"
                        r" printer's max_temp 235 C: clamped there; the hotend"
                        r" melts 7.50 mm\^3/s there: slice with a max volumetric"
                        r" speed of 7.50 mm\^3/s, or let \[flowrate_limiter\]"
                        r" hold the flow", line), line
    assert max(targets) == 235.0
    assert "melts less than demanded" in out


def test_a_line_that_barely_rises_is_one_line(tmp_path, capsys):
    flat = json.loads(json.dumps(WEAK))
    for name in ("into_air", "real_print"):
        flat["lines"][name]["slope_mm3_s_per_c"] = 0.001
    out, _, targets = bake(tmp_path, capsys, first_layer(), flat)
    (line,) = [x for x in out.splitlines() if "hardly changes" in x]
    assert line == ("  the profile's line gains only 0.05 mm^3/s from 190 to 235 C"
                    " (3.99 to 4.04 mm^3/s): the temperature hardly changes what"
                    " the hotend melts; any flow above 3.99 mm^3/s is planned up"
                    " to 235 C, and autotemp saves little over a fixed"
                    " temperature")
    assert targets and max(targets) <= 235.0


def test_a_nearly_flat_line_plans_within_the_limits():
    limits = TempLimits(190.0, 240.0)
    for slope in (1e-3, 1e-9, 5e-324):
        line = Line.through(slope, 200.0, 4.0)
        assert flat_line_note(line, limits) is not None
        plan = TemperaturePlan(line, limits)
        plan.announce(0.0, 6.0, 30.0, 10.0)
        plan.announce(0.0, 3.0, 40.0, 10.0)
        targets = [plan.target_at(k * 0.1) for k in range(600)]
        assert all(190.0 <= t <= 240.0 and math.isfinite(t) for t in targets)
        assert max(targets) == 240.0 and targets[-1] == 190.0
    steep = Line.through(FLAT_GAIN_MM3_S / 25.0, 200.0, 4.0)
    assert flat_line_note(steep, limits) is None
