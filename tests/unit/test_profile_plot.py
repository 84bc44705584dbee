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


def pixels_of(image, color: str, tolerance: float = 8 / 255) -> int:
    """How many pixels of the image have this #rrggbb colour, within tolerance."""
    want = np.array([int(color[i:i + 2], 16) for i in (1, 3, 5)]) / 255.0
    return int((np.abs(image[..., :3] - want).max(axis=-1) < tolerance).sum())


ANTIALIASED = 40 / 255  # a renderer's thin or dotted lines come out paler


def test_png_draws_the_same_panels_as_the_svg(measured, tmp_path):
    from matplotlib import image as mpl_image  # the plot extra, in dev installs
    out = tmp_path / "x.png"
    plot.png(measured, out, 0.25)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = mpl_image.imread(str(out))
    panels = plot.panels(measured, 0.25)
    assert len(panels) == 2  # temperature and heater PWM, as in the SVG
    assert image.shape[:2] == (40 + plot.PANEL_HEIGHT * 2, plot.PROFILE_WIDTH)
    for color in (plot.COLORS["into_air"], plot.COLORS["real_print"],
                  plot.COLORS["working"]):
        assert pixels_of(image, color) > 200, color


def test_png_of_a_profile_without_power_lines_has_one_panel(tmp_path):
    from matplotlib import image as mpl_image
    out = tmp_path / "x.png"
    plot.png(P.profile_from_dict(make(name="$x$ and 100%")), out)
    assert mpl_image.imread(str(out)).shape[:2] == (40 + plot.PANEL_HEIGHT,
                                                    plot.PROFILE_WIDTH)


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


# --- what the pictures show, and that they show it everywhere ----------------


@pytest.fixture
def warned():
    """An imported profile whose real-print line lies above its into-air line."""
    p = P.profile_from_dict(make(real=(0.146, 160.0, 8.0)))
    assert P.line_warnings(p)
    return p


def test_the_legend_names_everything_the_profile_plot_draws(measured):
    root = parse(plot.svg(measured))
    legends = [e for e in root.iter(SVG + "g") if e.get("class") == "legend"]
    assert len(legends) == 2  # one per panel
    keys = {e.get("data-for"): e.find(SVG + "text").text
            for legend in legends for e in legend}
    drawn = {e.get("id") for e in root.iter() if e.get("id")} - {"points"}
    named = {name for names in keys for name in names.split()}
    assert drawn - named == set()
    assert {"points", "anchor"} <= named
    assert keys["band"] == "between the two lines"
    assert keys["min_temp max_temp"] == "min / max temperature"
    assert keys["recommended_temp"] == "recommended temperature"
    labels = [e.find(SVG + "text").text for e in legends[0]]
    assert "measured into air" in labels and "measured real print" in labels


def test_a_warned_profile_prints_its_warning_and_keeps_its_into_air_line_visible(
        warned):
    root = parse(plot.svg(warned))
    shown = " ".join(e.text for e in root.iter(SVG + "text")
                     if e.get("class") == "warning")
    assert shown == "warning: " + P.line_warnings(warned)[0]
    drawn = [e for e in root.iter(SVG + "polyline")]
    order = [e.get("id") for e in drawn]
    width = {e.get("id"): float(e.get("stroke-width")) for e in drawn}
    # the working line (here on the into-air line) lies under it and wider
    assert order.index("working_line") < order.index("into_air")
    assert width["working_line"] > width["into_air"]
    # the panel moves down to make room for the warning; a plain one does not
    assert float(root.get("height")) > 40 + plot.PANEL_HEIGHT


def test_a_plain_profile_prints_no_warning(measured):
    root = parse(plot.svg(measured))
    assert not [e for e in root.iter() if e.get("class") == "warning"]


def _svgs(measured, warned):
    from flowloop.control import rule_plot
    from flowloop.gcode.bake import Timeline, timeline_svg
    timeline = Timeline(demand_mm3_s=[5.0] * 100, target_c=[210.0] * 100,
                        nozzle_c=[205.0] * 100, capacity_mm3_s=[6.0] * 100)
    return {"profile": plot.svg(measured), "warned": plot.svg(warned),
            "timeline": timeline_svg(timeline, "t"), "rule": rule_plot.svg()}


def test_the_svgs_use_only_what_every_renderer_draws(measured, warned):
    # ImageMagick's own renderer (`convert`, many viewers) strokes text in
    # black unless told not to, fills a line's dash gaps, drops a shape that
    # holds a <title>, ignores opacity and rotate(angle, cx, cy)
    for name, text in _svgs(measured, warned).items():
        root = parse(text)
        assert root.get("stroke") == "none", name
        parents = {child: parent for parent in root.iter() for child in parent}
        for e in root.iter():
            tag = e.tag.replace(SVG, "")
            assert tag != "style" and e.get("style") is None, (name, tag)
            assert not {"opacity", "fill-opacity", "stroke-opacity",
                        "dominant-baseline"} & set(e.keys()), (name, tag)
            assert "rotate" not in e.get("transform", "") \
                or e.get("transform").endswith("rotate(-90)"), (name, tag)
            if tag == "line":
                assert e.get("fill") == "none", (name, e.attrib)
            if tag == "rect":
                assert e.get("stroke") is not None, (name, e.attrib)
            if tag == "title":
                assert parents[e].tag in (SVG + "g", SVG + "svg"), name


def _renderers():
    import shutil
    magick = shutil.which("magick") or shutil.which("convert")
    return [
        pytest.param(["rsvg-convert", "{svg}", "-o", "{png}"]
                     if shutil.which("rsvg-convert") else None, id="rsvg-convert"),
        # msvg: ImageMagick's own renderer, what Debian's convert uses
        pytest.param([magick, "msvg:{svg}", "png:{png}"] if magick else None,
                     id="imagemagick"),
    ]


@pytest.mark.parametrize("command", _renderers())
def test_the_profile_plot_renders_its_labels_and_marks_outside_a_browser(
        command, measured, tmp_path):
    import subprocess

    from matplotlib import image as mpl_image
    if command is None:
        pytest.skip("renderer not installed (apt-get install librsvg2-bin "
                    "imagemagick; .ci/run does it)")
    svg_path, png_path = tmp_path / "p.svg", tmp_path / "p.png"
    svg_path.write_text(plot.svg(measured))
    subprocess.run([a.format(svg=svg_path, png=png_path) for a in command],
                   check=True, capture_output=True)
    image = mpl_image.imread(str(png_path))[:, :, :3]
    assert image.shape[:2] == (40 + 2 * plot.PANEL_HEIGHT, plot.PROFILE_WIDTH)
    (panel, _) = plot.panels(measured)
    axes = plot.Panel(40, panel.x_range, panel.y_range,
                      plot.PROFILE_WIDTH - plot.LEGEND_WIDTH)
    assert image[0, 0].min() > 0.95 and image[-1, -1].min() > 0.95  # no border
    # the y label, left of the tick numbers
    strip = image[int(axes.top) + 100:int(axes.bottom) - 100, 5:28]
    assert (strip.max(axis=2) < 0.5).sum() > 30
    # the dotted bound lines, grey and red, over the whole panel's height
    for mark, color in (("min_temp", "bound"), ("recommended_temp", "recommended")):
        x = axes.x({m.element_id: m.temp_c for m in panel.bounds}[mark])
        column = image[int(axes.top) + 5:int(axes.bottom) - 5,
                       int(x) - 1:int(x) + 2]
        assert pixels_of(column, plot.COLORS[color], ANTIALIASED) > 40, mark
    # the measured points: rings around white
    for p in measured.points:
        x, y = int(round(axes.x(p.temp_c))), int(round(axes.y(p.flow_mm3_s)))
        assert image[y, x].min() > 0.9, p
        ring = image[y - 6:y + 7, x - 6:x + 7]
        assert pixels_of(ring, plot.COLORS[p.kind], ANTIALIASED) > 8, p
    # the band, as pale as in a browser
    x = axes.x(250.0)
    air, real = (measured.lines.into_air.line().flow_mm3_s(250.0),
                 measured.lines.real_print.line().flow_mm3_s(250.0))
    inside = image[int(axes.y((air + real) / 2)) - 3:int(axes.y((air + real) / 2)) + 3,
                   int(x) - 3:int(x) + 3]
    assert pixels_of(inside, plot.COLORS["band"], ANTIALIASED) > 20


def test_a_warned_profile_s_png_prints_its_warning_above_the_panels(warned, tmp_path):
    from matplotlib import image as mpl_image
    out = tmp_path / "x.png"
    plot.png(warned, out)
    image = mpl_image.imread(str(out))
    rows = len(plot.warning_lines(warned))
    header = plot.HEADER_HEIGHT + plot.WARNING_LINE_HEIGHT * rows
    assert image.shape[:2] == (header + plot.PANEL_HEIGHT, plot.PROFILE_WIDTH)
    assert pixels_of(image[:header], plot.WARNING_COLOR) > 50
    assert pixels_of(image[header:], plot.WARNING_COLOR) == 0
