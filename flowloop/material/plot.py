"""Plots of a material profile, the way ddPrint's plot_mat_profile shows them.

Flow against temperature: the into-air and real-print lines over the bounds,
the band between them, the working-point line, the bounds as vertical marks,
each line's measured anchor (x) and the raw measured points (o, with grip),
each named in a legend beside the panel; what is implausible about the lines
(`line_warnings`) is printed above the panels. When the profile has
heater-power lines, a second panel shows flow against heater PWM. The series
are built once (`panels()`, in data units); `svg()` draws them as plain SVG
text (no plotting library), `png()` with matplotlib (the `plot` extra) and
says so when it is missing.

The SVG keeps to what every common renderer draws the same (browsers,
librsvg's rsvg-convert, ImageMagick's own MSVG renderer that `convert` and
many viewers use): presentation attributes only (no CSS), no opacity (the
band is a solid pale colour under the grid), `stroke="none"` on the root and
`fill="none"` on every line (MSVG strokes text and fills lines otherwise),
rotations as `translate(...) rotate(...)`, and tooltips (`<title>`) only as
the first child of a `<g>` (MSVG skips a shape that holds one).
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path
from typing import List, NamedTuple, Optional, Sequence, Tuple
from xml.sax.saxutils import escape, quoteattr

from ..errors import FlowloopError
from .profile import (
    DEFAULT_WORKING_POINT,
    Line,
    MeasuredPoint,
    PowerLine,
    Profile,
    check_working_point,
    line_warnings,
    profile_line,
)

WIDTH = 760
PANEL_HEIGHT = 420
MARGIN = (70, 20, 60, 60)  # left, right, top, bottom
LEGEND_WIDTH = 210  # the profile plot's legend, right of its panels
PROFILE_WIDTH = WIDTH + LEGEND_WIDTH
HEADER_HEIGHT = 40  # the plot's title
WARNING_LINE_HEIGHT = 16
WARNING_COLOR = "#b42318"
# Every picture's colours, the live page's too (flowloop.host.live_page
# writes them into page.js).
COLORS = {
    # a profile's lines and marks
    "into_air": "#1f77b4", "real_print": "#d62728", "working": "#2ca02c",
    "band": "#e5e5e5",  # #7f7f7f at 20 % on white: no renderer-dependent opacity
    "grid": "#dddddd", "bound": "#7f7f7f", "recommended": "#d62728",
    # temperatures over time: the target, the nozzle (measured or modelled)
    "target": "#d62728", "nozzle": "#1f77b4",
    # flows over time
    "demand": "#7f7f7f", "measured": "#9467bd", "capacity": "#2ca02c",
    "cap": "#d62728", "planned": "#ff7f0e", "grip": "#17becf",
    # where the printer is now (the live page's operating point and position)
    "now": "#9467bd",
}


def svg_open(width: float, height: float, extra: str = "") -> List[str]:
    """The first lines of every flowloop SVG: the root element (stroke="none"
    so no renderer outlines text) and a white background."""
    return ['<?xml version="1.0" encoding="UTF-8"?>',
            f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" '
            f'height="{height}" viewBox="0 0 {width} {height}" '
            f'font-family="sans-serif" font-size="12" stroke="none"{extra}>',
            f'<rect width="{width}" height="{height}" fill="white" stroke="none"/>']


def svg_line(x1: float, y1: float, x2: float, y2: float, color: str,
             dash: str = "", width: float = 1, element_id: str = "") -> str:
    """An SVG line (fill="none": ImageMagick fills a dashed line's gaps)."""
    ident = f'id="{element_id}" ' if element_id else ""
    dashed = f' stroke-dasharray="{dash}"' if dash else ""
    return (f'<line {ident}x1="{x1:.2f}" y1="{y1:.2f}" x2="{x2:.2f}" y2="{y2:.2f}" '
            f'fill="none" stroke="{color}" stroke-width="{width:g}"{dashed}/>')


def tooltip(text: str, shape: str) -> str:
    """A shape with a tooltip, the one way every renderer draws it."""
    return f'<g><title>{escape(text)}</title>{shape}</g>'


def nice_ticks(lo: float, hi: float, count: int = 6) -> List[float]:
    """Round tick values covering lo..hi."""
    span = hi - lo
    if span <= 0:
        return [lo]
    raw = span / count
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    first = math.ceil(lo / step) * step
    ticks = []
    value = first
    while value <= hi + step * 1e-9:
        ticks.append(round(value, 10))
        value += step
    return ticks


class Panel:
    """Maps data coordinates to one panel of the SVG (the profile plot's,
    the bake timeline's, the reactive rule's)."""

    def __init__(self, top: float, x_range: Tuple[float, float],
                 y_range: Tuple[float, float], width: float = WIDTH):
        self.left, self.right = MARGIN[0], width - MARGIN[1]
        self.top, self.bottom = top + MARGIN[2], top + PANEL_HEIGHT - MARGIN[3]
        self.x_range, self.y_range = x_range, y_range
        self.parts: List[str] = []

    def x(self, value: float) -> float:
        lo, hi = self.x_range
        return self.left + (value - lo) / (hi - lo) * (self.right - self.left)

    def y(self, value: float) -> float:
        lo, hi = self.y_range
        return self.bottom - (value - lo) / (hi - lo) * (self.bottom - self.top)

    def add(self, text: str) -> None:
        self.parts.append(text)

    def polyline(self, points: Sequence[Tuple[float, float]], color: str,
                 element_id: str, dash: str = "", width: float = 2) -> None:
        coords = " ".join(f"{self.x(a):.2f},{self.y(b):.2f}" for a, b in points)
        dashed = f' stroke-dasharray="{dash}"' if dash else ""
        self.add(f'<polyline id="{element_id}" points="{coords}" fill="none" '
                 f'stroke="{color}" stroke-width="{width}"{dashed}/>')

    def frame(self, title: str, x_label: str, y_label: str,
              x_ticks: Optional[Sequence[Tuple[float, str]]] = None) -> None:
        """Grid, ticks, box and labels; x_ticks are (value, text) when the
        x axis is not plain numbers."""
        self.grid(x_ticks)
        self.axes(title, x_label, y_label, x_ticks)

    def _x_ticks(self, x_ticks: Optional[Sequence[Tuple[float, str]]]
                 ) -> Sequence[Tuple[float, str]]:
        if x_ticks is not None:
            return x_ticks
        return [(value, f"{value:g}") for value in nice_ticks(*self.x_range)]

    def grid(self, x_ticks: Optional[Sequence[Tuple[float, str]]] = None) -> None:
        for value, _ in self._x_ticks(x_ticks):
            x = self.x(value)
            self.add(svg_line(x, self.top, x, self.bottom, COLORS["grid"]))
        for value in nice_ticks(*self.y_range):
            y = self.y(value)
            self.add(svg_line(self.left, y, self.right, y, COLORS["grid"]))

    def axes(self, title: str, x_label: str, y_label: str,
             x_ticks: Optional[Sequence[Tuple[float, str]]] = None) -> None:
        for value, text in self._x_ticks(x_ticks):
            self.add(f'<text class="x-tick" x="{self.x(value):.2f}" '
                     f'y="{self.bottom + 16}" text-anchor="middle">'
                     f'{escape(text)}</text>')
        for value in nice_ticks(*self.y_range):
            self.add(f'<text x="{self.left - 6}" y="{self.y(value) + 4:.2f}" '
                     f'text-anchor="end">{value:g}</text>')
        self.add(f'<rect x="{self.left}" y="{self.top}" '
                 f'width="{self.right - self.left}" height="{self.bottom - self.top}" '
                 f'fill="none" stroke="black"/>')
        mid_x = (self.left + self.right) / 2
        self.add(f'<text x="{mid_x}" y="{self.top - 10}" text-anchor="middle" '
                 f'font-weight="bold">{escape(title)}</text>')
        self.add(f'<text x="{mid_x}" y="{self.bottom + 36}" '
                 f'text-anchor="middle">{escape(x_label)}</text>')
        mid_y = (self.top + self.bottom) / 2
        # translate, then rotate: ImageMagick ignores rotate(angle, cx, cy)
        self.add(f'<text class="y-label" transform="translate(16 {mid_y:.2f}) '
                 f'rotate(-90)" text-anchor="middle">{escape(y_label)}</text>')

    def cross(self, a: float, b: float, color: str, label: str) -> None:
        self.add(tooltip(label, _cross(self.x(a), self.y(b), color, "anchor")))

    def legend(self, entries: Sequence[Tuple[str, str, str]]) -> None:
        """Line keys inside the panel's top left corner."""
        self.legend_keys([Key(label, color, dash) for label, color, dash in entries],
                         self.left + 8, self.top + 14)

    def legend_keys(self, keys: Sequence[Key], x: float, y: float) -> None:
        """A key per drawn thing, top to bottom from (x, y)."""
        for i, key in enumerate(keys):
            row = y + 18 * i
            self.add(f'<g class="legend-key" data-for="{key.names}">'
                     f'{_key_symbol(key, x, row - 4)}'
                     f'<text x="{x + 28}" y="{row}">{escape(key.label)}</text></g>')


def _cross(x: float, y: float, color: str, css_class: str = "") -> str:
    class_attr = f' class="{css_class}"' if css_class else ""
    return (f'<path{class_attr} d="M{x - 5:.2f},{y - 5:.2f} L{x + 5:.2f},'
            f'{y + 5:.2f} M{x - 5:.2f},{y + 5:.2f} L{x + 5:.2f},{y - 5:.2f}" '
            f'fill="none" stroke="{color}" stroke-width="2"/>')


class Key(NamedTuple):
    """One legend row: what is drawn, how, and the ids of what it names."""

    label: str
    color: str
    dash: str = ""
    kind: str = "line"  # line, point (o), anchor (x) or area
    names: str = ""
    width: float = 2


def _key_symbol(key: Key, x: float, y: float) -> str:
    """The legend's sample of a key, 22 px wide, centred on y."""
    if key.kind == "point":
        return (f'<circle cx="{x + 11}" cy="{y:.2f}" r="4" fill="white" '
                f'stroke="{key.color}" stroke-width="2"/>')
    if key.kind == "anchor":
        return _cross(x + 11, y, key.color)
    if key.kind == "area":
        return (f'<rect x="{x}" y="{y - 5:.2f}" width="22" height="10" '
                f'fill="{key.color}" stroke="none"/>')
    return svg_line(x, y, x + 22, y, key.color, key.dash, key.width)


# --- the series, built once for SVG and PNG ---------------------------------


class Series(NamedTuple):
    """One polyline: the into-air, real-print or working line, or a power line."""

    element_id: str
    label: str
    color: str
    dash: str  # SVG dash pattern; "" is solid
    points: List[Tuple[float, float]]
    width: float = 2


class Anchor(NamedTuple):
    """A line's measured point, drawn as x."""

    x: float
    flow_mm3_s: float
    color: str
    label: str


class BoundMark(NamedTuple):
    element_id: str
    temp_c: float
    color: str


BOUND_DASH = "2,3"
BOUND_WIDTH = 1.5
WORKING_DASH = "8,4"
# The working line is drawn first and wider: where it follows a measured line
# (a profile with a warning) both stay visible.
WORKING_WIDTH = 5


class PanelSeries(NamedTuple):
    """Everything one panel draws, in data units."""

    title: str
    x_label: str
    y_label: str
    x_range: Tuple[float, float]
    y_range: Tuple[float, float]
    lines: List[Series]  # in drawing order, the first at the bottom
    anchors: List[Anchor]
    band: List[Tuple[float, float]] = []  # polygon between the two lines
    bounds: List[BoundMark] = []
    points: List[MeasuredPoint] = []  # raw measurements


def _flow_range(values: Sequence[float]) -> Tuple[float, float]:
    top = max([v for v in values if math.isfinite(v)] + [1.0])
    return 0.0, top * 1.1


def line_points(line: Line, lo: float, hi: float) -> List[Tuple[float, float]]:
    """(temp, flow) along a line over lo..hi, with a point at every bend (its
    knee at the ceiling, its zero) so straight segments draw it exactly."""
    temps = {lo, hi}
    for bend in (line.knee_temp_c(), line.temp_c(0.0)):
        if bend is not None and lo < bend < hi:
            temps.add(bend)
    return [(t, line.flow_mm3_s(t)) for t in sorted(temps)]


def temperature_series(profile: Profile,
                       working_point: float = DEFAULT_WORKING_POINT) -> PanelSeries:
    """Flow against temperature: both lines, the band, the WP line, the bounds,
    the anchors and the raw points."""
    wp = check_working_point(working_point)
    b, lines = profile.bounds, profile.lines
    temps = [b.min_temp_c, b.max_temp_c, lines.into_air.temp_c,
             lines.real_print.temp_c] + [p.temp_c for p in profile.points]
    border = (b.min_temp_c + b.max_temp_c) / 40  # as ddPrint's plot
    lo, hi = b.min_temp_c, b.max_temp_c
    air = line_points(lines.into_air.line(), lo, hi)
    real = line_points(lines.real_print.line(), lo, hi)
    series = [Series("working_line", f"working point {wp:g}", COLORS["working"],
                     WORKING_DASH, line_points(profile_line(profile, wp), lo, hi),
                     WORKING_WIDTH),
              Series("into_air", "into air", COLORS["into_air"], "", air),
              Series("real_print", "real print", COLORS["real_print"], "", real)]
    flows = [f for s in series for _, f in s.points]
    flows += [lines.into_air.flow_mm3_s, lines.real_print.flow_mm3_s]
    flows += [p.flow_mm3_s for p in profile.points]
    return PanelSeries(
        title=f"Flow vs temperature, working point {wp:g}",
        x_label="hotend temperature [°C]", y_label="melt flow [mm³/s]",
        x_range=(min(temps) - border, max(temps) + border),
        y_range=_flow_range(flows), lines=series,
        anchors=[Anchor(lines.into_air.temp_c, lines.into_air.flow_mm3_s,
                        COLORS["into_air"], "into-air line's anchor"),
                 Anchor(lines.real_print.temp_c, lines.real_print.flow_mm3_s,
                        COLORS["real_print"], "real-print line's anchor")],
        band=air + real[::-1],
        bounds=[BoundMark("min_temp", b.min_temp_c, COLORS["bound"]),
                BoundMark("recommended_temp", b.recommended_temp_c,
                          COLORS["recommended"]),
                BoundMark("max_temp", b.max_temp_c, COLORS["bound"])],
        points=list(profile.points))


def power_series(profile: Profile) -> Optional[PanelSeries]:
    """Flow against heater PWM, when the profile has power lines."""
    lines, b = profile.lines, profile.bounds
    series, anchors = [], []
    for name in ("into_air", "real_print"):
        power: Optional[PowerLine] = getattr(lines, f"{name}_power")
        if power is None:
            continue
        temp_line = getattr(lines, name).line()
        flows = [temp_line.flow_mm3_s(t) for t in (b.min_temp_c, b.max_temp_c)]
        pwms = [power.pwm + (f - power.flow_mm3_s) / power.slope_mm3_s_per_pwm
                for f in flows]
        label = name.replace("_", " ")
        series.append(Series(f"{name}_power", label, COLORS[name], "",
                             list(zip(pwms, flows))))
        anchors.append(Anchor(power.pwm, power.flow_mm3_s, COLORS[name],
                              f"{name.replace('_', '-')} PWM anchor"))
    if not series:
        return None
    all_pwm = [a.x for a in anchors] + [x for s in series for x, _ in s.points]
    border = (max(all_pwm) - min(all_pwm)) / 20 or 1.0
    return PanelSeries(
        title="Flow vs heater PWM", x_label=f"heater PWM (0..{lines.pwm_max:g})",
        y_label="melt flow [mm³/s]",
        x_range=(min(all_pwm) - border, max(all_pwm) + border),
        y_range=_flow_range([f for s in series for _, f in s.points]),
        lines=series, anchors=anchors)


def panels(profile: Profile,
           working_point: float = DEFAULT_WORKING_POINT) -> List[PanelSeries]:
    """The panels a plot shows, top to bottom."""
    out = [temperature_series(profile, working_point)]
    power = power_series(profile)
    if power is not None:
        out.append(power)
    return out


_POINT_LABELS = {"into_air": "measured into air", "real_print": "measured real print"}


def legend(series: PanelSeries) -> List[Key]:
    """A key for everything the panel draws, the same in SVG and PNG."""
    keys = [Key(s.label, s.color, s.dash, "line", s.element_id, s.width)
            for s in series.lines]
    kinds = [k for k in _POINT_LABELS if any(p.kind == k for p in series.points)]
    keys += [Key(_POINT_LABELS[k], COLORS[k], kind="point", names="points")
             for k in kinds]
    keys += [Key(a.label, a.color, kind="anchor", names="anchor")
             for a in series.anchors]
    if series.band:
        keys.append(Key("between the two lines", COLORS["band"], kind="area",
                        names="band"))
    outer = [m for m in series.bounds if m.element_id != "recommended_temp"]
    if outer:
        keys.append(Key("min / max temperature", outer[0].color, BOUND_DASH,
                        names=" ".join(m.element_id for m in outer), width=BOUND_WIDTH))
    keys += [Key("recommended temperature", m.color, BOUND_DASH, names=m.element_id,
                 width=BOUND_WIDTH)
             for m in series.bounds if m.element_id == "recommended_temp"]
    return keys


def plot_title(profile: Profile) -> str:
    ident = profile.identity
    return f"{ident.name}: {ident.printer or 'any printer'}, nozzle " \
        f"{ident.nozzle_diameter_mm:g} mm, {ident.filament_type or 'filament'}"


WARNING_CHARS = 120  # a warning line's length, to fit the plot's width


def warning_lines(profile: Profile) -> List[str]:
    """The profile's line warnings, wrapped to the plot's width."""
    return [row for text in line_warnings(profile)
            for row in textwrap.wrap("warning: " + text, WARNING_CHARS)]


# --- SVG ----------------------------------------------------------------------


def _svg_panel(series: PanelSeries, top: float) -> Panel:
    panel = Panel(top, series.x_range, series.y_range, PROFILE_WIDTH - LEGEND_WIDTH)
    if series.band:  # under the grid: a solid colour hides nothing
        coords = " ".join(f"{panel.x(a):.2f},{panel.y(c):.2f}" for a, c in series.band)
        panel.add(f'<polygon id="band" points="{coords}" fill="{COLORS["band"]}" '
                  f'stroke="none"/>')
    panel.grid()
    panel.axes(series.title, series.x_label, series.y_label)
    for mark in series.bounds:
        x = panel.x(mark.temp_c)
        panel.add(tooltip(f"{mark.element_id} {mark.temp_c:g} °C", svg_line(
            x, panel.top, x, panel.bottom, mark.color, BOUND_DASH, BOUND_WIDTH,
            mark.element_id)))
    for line in series.lines:
        panel.polyline(line.points, line.color, line.element_id, line.dash,
                       line.width)
    for anchor in series.anchors:
        panel.cross(anchor.x, anchor.flow_mm3_s, anchor.color, anchor.label)
    if series.points:
        panel.add('<g id="points">')
        for p in series.points:
            panel.add(tooltip(
                f"{p.kind} {p.temp_c:g} °C {p.flow_mm3_s:g} mm³/s grip {p.grip:g}",
                f'<circle class="point" cx="{panel.x(p.temp_c):.2f}" '
                f'cy="{panel.y(p.flow_mm3_s):.2f}" r="4" fill="white" '
                f'stroke="{COLORS[p.kind]}" stroke-width="2"/>'))
        panel.add("</g>")
    panel.add('<g class="legend">')
    panel.legend_keys(legend(series), panel.right + 14, panel.top + 8)
    panel.add("</g>")
    return panel


def svg(profile: Profile, working_point: float = DEFAULT_WORKING_POINT) -> str:
    """The plot as SVG text."""
    shown = panels(profile, working_point)
    warnings = warning_lines(profile)
    first = HEADER_HEIGHT + WARNING_LINE_HEIGHT * len(warnings)
    height = first + PANEL_HEIGHT * len(shown)
    title = plot_title(profile)
    out = svg_open(PROFILE_WIDTH, height,
                   f" data-profile={quoteattr(profile.identity.name)}")
    out += [f'<title>{escape(title)}</title>',
            f'<text x="{PROFILE_WIDTH / 2}" y="24" text-anchor="middle" '
            f'font-size="15" font-weight="bold">{escape(title)}</text>']
    if warnings:
        out.append('<g id="warnings">')
        out += [f'<text class="warning" x="{MARGIN[0]}" '
                f'y="{HEADER_HEIGHT + 4 + WARNING_LINE_HEIGHT * i}" '
                f'fill="{WARNING_COLOR}">{escape(row)}</text>'
                for i, row in enumerate(warnings)]
        out.append("</g>")
    for i, series in enumerate(shown):
        out += _svg_panel(series, first + PANEL_HEIGHT * i).parts
    out.append("</svg>")
    return "\n".join(out) + "\n"


# --- PNG (the plot extra: pip install 'klipper-flowloop[plot]') ---------------


def _mpl_dash(dash: str) -> str:
    return {"": "-", BOUND_DASH: ":"}.get(dash, "--")


def png(profile: Profile, path: Path,
        working_point: float = DEFAULT_WORKING_POINT) -> None:
    """The same panels as PNG; needs matplotlib (the `plot` extra)."""
    shown = panels(profile, working_point)
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise FlowloopError("PNG plots need matplotlib (pip install "
                            "'klipper-flowloop[plot]'); SVG plots work without "
                            "it") from None
    warnings = warning_lines(profile)
    header = HEADER_HEIGHT + WARNING_LINE_HEIGHT * len(warnings)
    height = header + PANEL_HEIGHT * len(shown)
    fig, axes = plt.subplots(len(shown), 1, squeeze=False,
                             figsize=(PROFILE_WIDTH / 100, height / 100))
    # No mathtext: a "$" in a name is text.
    fig.suptitle(plot_title(profile).replace("$", r"\$"), fontweight="bold")
    for i, row in enumerate(warnings):
        fig.text(MARGIN[0] / PROFILE_WIDTH,
                 1 - (HEADER_HEIGHT + 4 + WARNING_LINE_HEIGHT * i) / height,
                 row.replace("$", r"\$"), color=WARNING_COLOR, fontsize=9)
    for ax, series in zip(axes[:, 0], shown):
        _png_panel(ax, series)
    fig.tight_layout(rect=(0, 0, 1, 1 - (header - HEADER_HEIGHT) / height))
    fig.savefig(str(path), dpi=100)
    plt.close(fig)


def _png_panel(ax, series: PanelSeries) -> None:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    ax.set_axisbelow(True)
    if series.band:
        ax.fill([t for t, _ in series.band], [f for _, f in series.band],
                color=COLORS["band"], linewidth=0, zorder=0.1)
    for mark in series.bounds:
        ax.axvline(mark.temp_c, color=mark.color, linestyle=_mpl_dash(BOUND_DASH),
                   linewidth=BOUND_WIDTH)
    for line in series.lines:
        ax.plot([x for x, _ in line.points], [f for _, f in line.points],
                _mpl_dash(line.dash), color=line.color, linewidth=line.width)
    for anchor in series.anchors:
        ax.plot([anchor.x], [anchor.flow_mm3_s], "x", color=anchor.color,
                markersize=9, markeredgewidth=2)
    for p in series.points:
        ax.plot([p.temp_c], [p.flow_mm3_s], "o", mfc="white", color=COLORS[p.kind])
    ax.set_xlim(*series.x_range)
    ax.set_ylim(*series.y_range)
    ax.set_title(series.title)
    ax.set_xlabel(series.x_label)
    ax.set_ylabel(series.y_label)
    ax.grid(True, color=COLORS["grid"])
    handles = []
    for key in legend(series):
        if key.kind == "area":
            handles.append(Patch(color=key.color, label=key.label))
        elif key.kind in ("point", "anchor"):
            handles.append(Line2D([], [], linestyle="none", color=key.color,
                                  marker="o" if key.kind == "point" else "x",
                                  mfc="white", markeredgewidth=2, label=key.label))
        else:
            handles.append(Line2D([], [], linestyle=_mpl_dash(key.dash),
                                  color=key.color, linewidth=key.width,
                                  label=key.label))
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0),
              fontsize=9, frameon=False)
