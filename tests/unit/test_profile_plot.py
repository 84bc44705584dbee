"""Profile plots: valid SVG showing both lines, the WP line and the points."""

from __future__ import annotations

import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from flowloop.errors import FlowloopError
from flowloop.material import plot
from flowloop.material import profile as P
from tests.samples import make

SVG = "{http://www.w3.org/2000/svg}"


def parse(text: str):
    return ET.fromstring(text.encode())


def coords(root, element_id):
    (el,) = [e for e in root.iter() if e.get("id") == element_id]
    return [tuple(map(float, pair.split(","))) for pair in el.get("points").split()]


@pytest.fixture
def measured():
    return P.profile_from_dict(make(
        name='<PLA & "friends">',
        points=[{"kind": "into_air", "temp_c": 200.0, "flow_mm3_s": 12.0, "grip": 0.9},
                {"kind": "into_air", "temp_c": 240.0, "flow_mm3_s": 18.0, "grip": 0.9},
                {"kind": "real_print", "temp_c": 210.0, "flow_mm3_s": 10.1,
                 "grip": 0.88}],
        lines={"into_air": {"slope_mm3_s_per_c": 0.146, "temp_c": 171.6312,
                            "flow_mm3_s": 7.5789},
               "real_print": {"slope_mm3_s_per_c": 0.146, "temp_c": 210.0,
                              "flow_mm3_s": 10.1356},
               "into_air_power": {"slope_mm3_s_per_pwm": 0.1472, "pwm": 90.0,
                                  "flow_mm3_s": 7.5789}}))


def test_svg_parses_and_escapes_the_name(measured):
    root = parse(plot.svg(measured))
    assert root.tag == SVG + "svg"
    assert root.get("data-profile") == '<PLA & "friends">'
    assert '<PLA & "friends">' in root.find(SVG + "title").text


@settings(max_examples=200, deadline=None)
@given(st.text(min_size=1, max_size=30))
@example("PLA\ufffe")
@example("]]><script>alert(1)</script><!--")
def test_every_accepted_name_gives_valid_svg_that_shows_it_verbatim(name):
    try:
        p = P.profile_from_dict(make(name=name))
    except FlowloopError:
        return  # refused names are the validators' test
    root = parse(plot.svg(p))
    assert root.get("data-profile") == name
    assert root.find(SVG + "title").text.startswith(f"{name}: UM2-1, nozzle")
    assert not [e for e in root.iter() if "script" in e.tag]


def test_working_line_lies_between_the_two_lines(measured):
    root = parse(plot.svg(measured, 0.25))
    air, real, wp = (coords(root, i) for i in ("into_air", "real_print",
                                               "working_line"))
    for a, r, w in zip(air, real, wp):
        assert a[0] == r[0] == w[0]
        # SVG y grows downwards: into air is higher (smaller y) than real print
        assert a[1] < w[1] < r[1]
        assert w[1] == pytest.approx(r[1] + 0.25 * (a[1] - r[1]), abs=0.02)


def test_measured_points_and_anchors_are_drawn(measured):
    root = parse(plot.svg(measured))
    assert len([e for e in root.iter(SVG + "circle")
                if e.get("class") == "point"]) == 3
    anchors = [e for e in root.iter(SVG + "path") if e.get("class") == "anchor"]
    assert len(anchors) == 3  # two temperature points, one PWM point
    assert {e.get("id") for e in root.iter()} >= {
        "band", "min_temp", "recommended_temp", "max_temp", "into_air_power"}


def test_bounds_marks_are_ordered_left_to_right(measured):
    root = parse(plot.svg(measured))
    x = {e.get("id"): float(e.get("x1")) for e in root.iter(SVG + "line")
         if e.get("id")}
    assert x["min_temp"] < x["recommended_temp"] < x["max_temp"]


def test_without_power_lines_there_is_one_panel():
    p = P.profile_from_dict(make())
    root = parse(plot.svg(p))
    assert root.get("height") == str(40 + plot.PANEL_HEIGHT)


def test_bad_working_point_is_refused():
    with pytest.raises(FlowloopError, match="working point"):
        plot.svg(P.profile_from_dict(make()), 2.0)


def test_png_without_matplotlib_says_what_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import fails as if absent
    with pytest.raises(FlowloopError, match=r"klipper-flowloop\[plot\]"):
        plot.png(P.profile_from_dict(make()), tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def pixels_of(image, color: str) -> int:
    """How many pixels of the PNG have this #rrggbb colour (within 8/255)."""
    want = np.array([int(color[i:i + 2], 16) for i in (1, 3, 5)]) / 255.0
    return int((np.abs(image[:, :, :3] - want).max(axis=2) < 8 / 255).sum())


def test_png_draws_the_same_panels_as_the_svg(measured, tmp_path):
    from matplotlib import image as mpl_image  # the plot extra, in dev installs
    out = tmp_path / "x.png"
    plot.png(measured, out, 0.25)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = mpl_image.imread(str(out))
    panels = plot.panels(measured, 0.25)
    assert len(panels) == 2  # temperature and heater PWM, as in the SVG
    assert image.shape[:2] == (40 + plot.PANEL_HEIGHT * 2, plot.WIDTH)
    for color in (plot.COLORS["into_air"], plot.COLORS["real_print"],
                  plot.COLORS["working"]):
        assert pixels_of(image, color) > 200, color


def test_png_of_a_profile_without_power_lines_has_one_panel(tmp_path):
    from matplotlib import image as mpl_image
    out = tmp_path / "x.png"
    plot.png(P.profile_from_dict(make(name="$x$ and 100%")), out)
    assert mpl_image.imread(str(out)).shape[:2] == (40 + plot.PANEL_HEIGHT, plot.WIDTH)


def test_the_working_line_is_drawn_with_its_knee_at_the_into_air_line():
    # real print steeper than into air: they cross at 229.8 degC
    p = P.profile_from_dict(make(real=(0.3, 210.0, 10.1356)))
    (temperature,) = plot.panels(p, 0.5)
    working = {s.element_id: s for s in temperature.lines}["working_line"]
    temps = [t for t, _ in working.points]
    assert temps[0] == 190.0 and temps[-1] == 260.0
    assert temps[1] == pytest.approx(229.8, abs=0.05)
    air = p.lines.into_air.line()
    assert working.points[-1][1] == pytest.approx(air.flow_mm3_s(260.0))


def test_nice_ticks_cover_the_range():
    assert plot.nice_ticks(185.0, 265.0) == [200, 220, 240, 260]
    assert plot.nice_ticks(0.0, 20.9) == [0, 5, 10, 15, 20]
