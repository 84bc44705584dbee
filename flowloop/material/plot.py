"""Plots of a material profile, the way ddPrint's plot_mat_profile shows them.

Flow against temperature: the into-air and real-print lines over the bounds,
the band between them, the working-point line, the bounds as vertical marks,
each line's measured anchor (x) and the raw measured points (o, with grip).
When the profile has heater-power lines, a second panel shows flow against
heater PWM. The series are built once (`panels()`, in data units); `svg()`
draws them as plain SVG text (no plotting library), `png()` with matplotlib
(the `plot` extra) and says so when it is missing.
"""

from __future__ import annotations

import math
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
    profile_line,
)

WIDTH = 760
PANEL_HEIGHT = 420
MARGIN = (70, 20, 60, 60)  # left, right, top, bottom
COLORS = {"into_air": "#1f77b4", "real_print": "#d62728", "working": "#2ca02c",
          "band": "#7f7f7f", "grid": "#dddddd", "bound": "#7f7f7f",
          "recommended": "#d62728"}


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


class _Panel:
    """Maps data coordinates to one panel of the SVG."""

    def __init__(self, top: float, x_range: Tuple[float, float],
                 y_range: Tuple[float, float]):
        self.left, self.right = MARGIN[0], WIDTH - MARGIN[1]
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

    def frame(self, title: str, x_label: str, y_label: str) -> None:
        for value in nice_ticks(*self.x_range):
            x = self.x(value)
            self.add(f'<line x1="{x:.2f}" y1="{self.top}" x2="{x:.2f}" '
                     f'y2="{self.bottom}" stroke="{COLORS["grid"]}"/>')
            self.add(f'<text x="{x:.2f}" y="{self.bottom + 16}" '
                     f'text-anchor="middle">{value:g}</text>')
        for value in nice_ticks(*self.y_range):
            y = self.y(value)
            self.add(f'<line x1="{self.left}" y1="{y:.2f}" x2="{self.right}" '
                     f'y2="{y:.2f}" stroke="{COLORS["grid"]}"/>')
            self.add(f'<text x="{self.left - 6}" y="{y + 4:.2f}" '
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
        self.add(f'<text x="16" y="{mid_y}" text-anchor="middle" '
                 f'transform="rotate(-90 16 {mid_y})">{escape(y_label)}</text>')

    def cross(self, a: float, b: float, color: str, label: str) -> None:
        x, y = self.x(a), self.y(b)
        self.add(f'<path class="anchor" d="M{x - 5:.2f},{y - 5:.2f} L{x + 5:.2f},'
                 f'{y + 5:.2f} M{x - 5:.2f},{y + 5:.2f} L{x + 5:.2f},{y - 5:.2f}" '
                 f'stroke="{color}" stroke-width="2"><title>{escape(label)}</title>'
                 f'</path>')

    def legend(self, entries: Sequence[Tuple[str, str, str]]) -> None:
        for i, (label, color, dash) in enumerate(entries):
            y = self.top + 14 + 16 * i
            dashed = f' stroke-dasharray="{dash}"' if dash else ""
            self.add(f'<line x1="{self.left + 8}" y1="{y - 4}" x2="{self.left + 30}" '
                     f'y2="{y - 4}" stroke="{color}" stroke-width="2"{dashed}/>')
            self.add(f'<text x="{self.left + 36}" y="{y}">{escape(label)}</text>')


# --- the series, built once for SVG and PNG ---------------------------------


class Series(NamedTuple):
    """One polyline: the into-air, real-print or working line, or a power line."""

    element_id: str
    label: str
    color: str
    dash: str  # SVG dash pattern; "" is solid
    points: List[Tuple[float, float]]


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


class PanelSeries(NamedTuple):
    """Everything one panel draws, in data units."""

    title: str
    x_label: str
    y_label: str
    x_range: Tuple[float, float]
    y_range: Tuple[float, float]
    lines: List[Series]
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
    series = [Series("into_air", "into air", COLORS["into_air"], "", air),
              Series("real_print", "real print", COLORS["real_print"], "", real),
              Series("working_line", f"working point {wp:g}", COLORS["working"],
                     "8,4", line_points(profile_line(profile, wp), lo, hi))]
    flows = [f for s in series for _, f in s.points]
    flows += [lines.into_air.flow_mm3_s, lines.real_print.flow_mm3_s]
    flows += [p.flow_mm3_s for p in profile.points]
    return PanelSeries(
        title=f"Flow vs temperature, working point {wp:g}",
        x_label="hotend temperature [°C]", y_label="melt flow [mm³/s]",
        x_range=(min(temps) - border, max(temps) + border),
        y_range=_flow_range(flows), lines=series,
        anchors=[Anchor(lines.into_air.temp_c, lines.into_air.flow_mm3_s,
                        COLORS["into_air"], "into-air point"),
                 Anchor(lines.real_print.temp_c, lines.real_print.flow_mm3_s,
                        COLORS["real_print"], "real-print point")],
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
                              f"{name} PWM point"))
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


def plot_title(profile: Profile) -> str:
    ident = profile.identity
    return f"{ident.name}: {ident.printer or 'any printer'}, nozzle " \
        f"{ident.nozzle_diameter_mm:g} mm, {ident.filament_type or 'filament'}"


# --- SVG ----------------------------------------------------------------------


def _svg_panel(series: PanelSeries, top: float) -> _Panel:
    panel = _Panel(top, series.x_range, series.y_range)
    panel.frame(series.title, series.x_label, series.y_label)
    if series.band:
        coords = " ".join(f"{panel.x(a):.2f},{panel.y(c):.2f}" for a, c in series.band)
        panel.add(f'<polygon id="band" points="{coords}" fill="{COLORS["band"]}" '
                  f'fill-opacity="0.2" stroke="none"/>')
    for mark in series.bounds:
        x = panel.x(mark.temp_c)
        panel.add(f'<line id="{mark.element_id}" x1="{x:.2f}" y1="{panel.top}" '
                  f'x2="{x:.2f}" y2="{panel.bottom}" stroke="{mark.color}" '
                  f'stroke-dasharray="2,3"><title>{mark.element_id} '
                  f'{mark.temp_c:g} °C</title></line>')
    for line in series.lines:
        panel.polyline(line.points, line.color, line.element_id, line.dash)
    for anchor in series.anchors:
        panel.cross(anchor.x, anchor.flow_mm3_s, anchor.color, anchor.label)
    if series.bounds:  # the temperature panel: points and legend
        panel.add('<g id="points">')
        for p in series.points:
            panel.add(f'<circle class="point" cx="{panel.x(p.temp_c):.2f}" '
                      f'cy="{panel.y(p.flow_mm3_s):.2f}" r="4" fill="white" '
                      f'stroke="{COLORS[p.kind]}" stroke-width="2"><title>{p.kind} '
                      f'{p.temp_c:g} °C {p.flow_mm3_s:g} mm³/s grip {p.grip:g}'
                      f'</title></circle>')
        panel.add("</g>")
        panel.legend([(s.label, s.color, s.dash) for s in series.lines])
    return panel


def svg(profile: Profile, working_point: float = DEFAULT_WORKING_POINT) -> str:
    """The plot as SVG text."""
    shown = panels(profile, working_point)
    height = 40 + PANEL_HEIGHT * len(shown)
    title = plot_title(profile)
    out = ['<?xml version="1.0" encoding="UTF-8"?>',
           f'<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" '
           f'height="{height}" viewBox="0 0 {WIDTH} {height}" '
           f'font-family="sans-serif" font-size="12" '
           f'data-profile={quoteattr(profile.identity.name)}>',
           f'<title>{escape(title)}</title>',
           f'<rect width="{WIDTH}" height="{height}" fill="white"/>',
           f'<text x="{WIDTH / 2}" y="24" text-anchor="middle" font-size="15" '
           f'font-weight="bold">{escape(title)}</text>']
    for i, series in enumerate(shown):
        out += _svg_panel(series, 40 + PANEL_HEIGHT * i).parts
    out.append("</svg>")
    return "\n".join(out) + "\n"


# --- PNG (the plot extra: pip install 'klipper-flowloop[plot]') ---------------


def _mpl_dash(dash: str) -> str:
    return "--" if dash else "-"


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
    height_in = PANEL_HEIGHT / 100
    fig, axes = plt.subplots(len(shown), 1, squeeze=False,
                             figsize=(WIDTH / 100, 0.4 + height_in * len(shown)))
    # No mathtext: a "$" in a name is text.
    fig.suptitle(plot_title(profile).replace("$", r"\$"), fontweight="bold")
    for ax, series in zip(axes[:, 0], shown):
        _png_panel(ax, series)
    fig.tight_layout()
    fig.savefig(str(path), dpi=100)
    plt.close(fig)


def _png_panel(ax, series: PanelSeries) -> None:
    if series.band:
        ax.fill([t for t, _ in series.band], [f for _, f in series.band],
                color=COLORS["band"], alpha=0.2, linewidth=0)
    for mark in series.bounds:
        ax.axvline(mark.temp_c, color=mark.color, linestyle=":")
    for line in series.lines:
        ax.plot([x for x, _ in line.points], [f for _, f in line.points],
                _mpl_dash(line.dash), color=line.color, label=line.label,
                linewidth=2)
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
    if series.bounds:
        ax.legend(loc="upper left")
