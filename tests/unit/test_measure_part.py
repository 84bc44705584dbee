"""The real-print measurement part (flowloop.gcode.measure_part) and
`flowloop measure-part`."""

from __future__ import annotations

import math
import re

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flowloop.cli import main
from flowloop.errors import FlowloopError
from flowloop.gcode import measure_part
from flowloop.gcode.measure_part import PartOptions

pytestmark = pytest.mark.unit

COMMAND = re.compile(r"^(G0|G1|G28|G90|G91|G92|M83|M104|M109|M140|M190)"
                     r"( [XYZEFS]-?\d+(\.\d+)?)*$|^SET_PRINT_STATS_INFO "
                     r"CURRENT_LAYER=\d+ TOTAL_LAYER=\d+$|"
                     r"^MEASURE_MATERIAL_PROFILE_LAYER LAYER=\d+ FLOW=\d+\.\d+$")


def moves(text):
    """(layer, x, y, e, f) of every extruding G1 (relative E)."""
    layer, out, feed = 0, [], None
    for line in text.splitlines():
        if line.startswith("SET_PRINT_STATS_INFO"):
            layer = int(line.split("CURRENT_LAYER=")[1].split()[0])
        if line.startswith("G1 ") and " E" in line:
            words = dict((w[0], float(w[1:])) for w in line.split()[1:])
            feed = words.get("F", feed)
            out.append((layer, words["X"], words["Y"], words["E"], feed))
    return out


def test_every_line_is_a_command_klipper_knows_or_a_comment():
    text = measure_part.render(PartOptions(height_mm=3.0))
    for line in text.splitlines():
        if line and not line.startswith(";"):
            assert COMMAND.match(line), line


@settings(max_examples=25, deadline=None)
@given(rise=st.floats(0.01, 0.2), start=st.floats(1.0, 8.0),
       layer=st.sampled_from([0.1, 0.15, 0.2]))
def test_speed_rises_by_layer_up_to_max_flow_and_flow_matches(rise, start, layer):
    o = PartOptions(height_mm=6.0, rise=rise, start_flow_mm3_s=start,
                    max_flow_mm3_s=20.0, layer_height_mm=layer)
    plan = measure_part.layer_plan(o)
    flows = [p.flow_mm3_s for p in plan[1:]]
    assert flows[0] == pytest.approx(start)
    for a, b in zip(flows, flows[1:]):
        assert b == pytest.approx(min(o.max_flow_mm3_s,
                                      o.max_speed_mm_s * o.section_mm2(),
                                      a * (1 + rise)), rel=1e-9)
    # the file's feed rates are the plan's speeds, layer by layer
    feeds = {}
    for n, _, _, _, f in moves(measure_part.render(o)):
        feeds.setdefault(n, set()).add(f)
    for p in plan:
        assert feeds[p.number] == {round(60 * p.speed_mm_s)}
    # each layer tells MEASURE_MATERIAL_PROFILE_PRINT its planned flow
    announced = [float(line.split("FLOW=")[1]) for line in
                 measure_part.render(o).splitlines()
                 if line.startswith("MEASURE_MATERIAL_PROFILE_LAYER")]
    assert announced == pytest.approx([p.flow_mm3_s for p in plan], abs=1e-3)


def test_the_filament_is_the_part_volume():
    o = PartOptions(height_mm=1.5)
    extruded = sum(e for *_, e, _ in moves(measure_part.render(o)))
    volume = extruded * math.pi * (o.filament_diameter_mm / 2) ** 2
    solid = o.length_mm * o.width_mm * o.height_mm
    # full infill: within 10 % of the solid bar (line ends, rounded sections)
    assert volume == pytest.approx(solid, rel=0.1)


def test_every_move_stays_on_the_part():
    o = PartOptions(height_mm=1.0, bed_size_x_mm=200, bed_size_y_mm=180)
    x0, y0 = (200 - o.length_mm) / 2, (180 - o.width_mm) / 2
    for _, x, y, _, _ in moves(measure_part.render(o)):
        assert x0 < x < x0 + o.length_mm and y0 < y < y0 + o.width_mm


def test_the_file_size_is_bounded():
    # the largest part the options allow stays well under a few MB
    o = PartOptions(height_mm=150.0, layer_height_mm=0.15,
                    width_mm=10.0)
    assert o.layers() <= measure_part.MAX_LAYERS
    assert len(measure_part.render(o).encode()) < 5_000_000
    with pytest.raises(FlowloopError, match="at most 1000"):
        PartOptions(height_mm=200.0, layer_height_mm=0.1)


@pytest.mark.parametrize("kw, message", [
    ({"layer_height_mm": 0.4}, "more than 80 %"),
    ({"line_width_mm": 0.3}, "within 1..2 nozzle"),
    ({"max_flow_mm3_s": 1.0}, "max_flow_mm3_s must not be below"),
    ({"rise": 0.9}, "more than 50 %"),
    ({"length_mm": 300.0}, "does not fit the bed"),
    ({"width_mm": math.nan}, "width_mm must be a number above 0"),
    ({"rise": 0.0}, "rise must be a number above 0"),
])
def test_bad_options_are_refused(kw, message):
    with pytest.raises(FlowloopError, match=message):
        PartOptions(**kw)


def test_the_cli_writes_the_file_and_names_the_flag_it_refuses(tmp_path, capsys):
    out = tmp_path / "part.gcode"
    assert main(["measure-part", "-o", str(out), "--height", "3",
                 "--max-flow", "12"]) == 0
    assert out.read_text().startswith("; flowloop")
    assert "20 layers" in capsys.readouterr().out
    bad = tmp_path / "bad.gcode"
    assert main(["measure-part", "-o", str(bad), "--layer-height", "0.5"]) == 2
    err = capsys.readouterr().err
    assert "--layer-height 0.5 is more than 80 %" in err
    assert len(err.strip().splitlines()) == 1
    assert not bad.exists()
