"""Plots of a material profile, the way ddPrint's plot_mat_profile shows them.

Flow against temperature: the into-air and real-print lines over the bounds,
the band between them, the working-point line, the bounds as vertical marks,
each line's measured anchor (x) and the raw measured points (o, with grip).
When the profile has heater-power lines, a second panel shows flow against
heater PWM. `svg()` writes plain SVG text (no plotting library); `png()` needs
matplotlib and says so when it is missing.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import List, Optional, Sequence, Tuple
from xml.sax.saxutils import escape, quoteattr

from ..errors import FlowloopError
from .profile import DEFAULT_WORKING_POINT, Profile, check_working_point, profile_line

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


def _flow_range(values: Sequence[float]) -> Tuple[float, float]:
    top = max([v for v in values if math.isfinite(v)] + [1.0])
    return 0.0, top * 1.1


def _temperature_panel(profile: Profile, wp: float, top: float) -> _Panel:
    b, lines = profile.bounds, profile.lines
    temps = [b.min_temp_c, b.max_temp_c, lines.into_air.temp_c,
             lines.real_print.temp_c] + [p.temp_c for p in profile.points]
    border = (b.min_temp_c + b.max_temp_c) / 40  # as ddPrint's plot
    x_range = (min(temps) - border, max(temps) + border)
    air, real = lines.into_air.line(), lines.real_print.line()
    working = profile_line(profile, wp)
    ends = (b.min_temp_c, b.max_temp_c)
    flows = [line.flow_mm3_s(t) for line in (air, real) for t in ends]
    flows += [lines.into_air.flow_mm3_s, lines.real_print.flow_mm3_s]
    flows += [p.flow_mm3_s for p in profile.points]
    panel = _Panel(top, x_range, _flow_range(flows))
    panel.frame(f"Flow vs temperature, working point {wp:g}",
                "hotend temperature [°C]", "melt flow [mm³/s]")
    band = [(t, max(0.0, air.flow_mm3_s(t))) for t in ends] + \
        [(t, max(0.0, real.flow_mm3_s(t))) for t in reversed(ends)]
    coords = " ".join(f"{panel.x(a):.2f},{panel.y(c):.2f}" for a, c in band)
    panel.add(f'<polygon id="band" points="{coords}" fill="{COLORS["band"]}" '
              f'fill-opacity="0.2" stroke="none"/>')
    for temp, color, element_id in ((b.min_temp_c, COLORS["bound"], "min_temp"),
                                    (b.recommended_temp_c, COLORS["recommended"],
                                     "recommended_temp"),
                                    (b.max_temp_c, COLORS["bound"], "max_temp")):
        x = panel.x(temp)
        panel.add(f'<line id="{element_id}" x1="{x:.2f}" y1="{panel.top}" '
                  f'x2="{x:.2f}" y2="{panel.bottom}" stroke="{color}" '
                  f'stroke-dasharray="2,3"><title>{element_id} {temp:g} °C</title>'
                  f'</line>')
    for line, color, element_id, dash in ((air, COLORS["into_air"], "into_air", ""),
                                          (real, COLORS["real_print"], "real_print",
                                           ""),
                                          (working, COLORS["working"], "working_line",
                                           "8,4")):
        panel.polyline([(t, max(0.0, line.flow_mm3_s(t))) for t in ends], color,
                       element_id, dash)
    panel.cross(lines.into_air.temp_c, lines.into_air.flow_mm3_s,
                COLORS["into_air"], "into-air point")
    panel.cross(lines.real_print.temp_c, lines.real_print.flow_mm3_s,
                COLORS["real_print"], "real-print point")
    panel.add('<g id="points">')
    for p in profile.points:
        panel.add(f'<circle class="point" cx="{panel.x(p.temp_c):.2f}" '
                  f'cy="{panel.y(p.flow_mm3_s):.2f}" r="4" fill="white" '
                  f'stroke="{COLORS[p.kind]}" stroke-width="2"><title>{p.kind} '
                  f'{p.temp_c:g} °C {p.flow_mm3_s:g} mm³/s grip {p.grip:g}</title>'
                  f'</circle>')
    panel.add("</g>")
    panel.legend([("into air", COLORS["into_air"], ""),
                  ("real print", COLORS["real_print"], ""),
                  (f"working point {wp:g}", COLORS["working"], "8,4")])
    return panel


def _power_panel(profile: Profile, top: float) -> Optional[_Panel]:
    lines = profile.lines
    powers = [(name, power) for name, power in (("into_air", lines.into_air_power),
                                                ("real_print", lines.real_print_power))
              if power is not None]
    if not powers:
        return None
    b = profile.bounds
    segments = []
    for name, power in powers:
        temp_line = getattr(lines, name).line()
        flows = [max(0.0, temp_line.flow_mm3_s(t))
                 for t in (b.min_temp_c, b.max_temp_c)]
        pwms = [power.pwm + (f - power.flow_mm3_s) / power.slope_mm3_s_per_pwm
                for f in flows]
        segments.append((name, power, list(zip(pwms, flows))))
    all_pwm = [p for _, power, seg in segments for p in [power.pwm] +
               [a for a, _ in seg]]
    border = (max(all_pwm) - min(all_pwm)) / 20 or 1.0
    panel = _Panel(top, (min(all_pwm) - border, max(all_pwm) + border),
                   _flow_range([f for _, _, seg in segments for _, f in seg]))
    panel.frame("Flow vs heater PWM", f"heater PWM (0..{lines.pwm_max:g})",
                "melt flow [mm³/s]")
    for name, power, seg in segments:
        panel.polyline(seg, COLORS[name], f"{name}_power")
        panel.cross(power.pwm, power.flow_mm3_s, COLORS[name], f"{name} PWM point")
    return panel


def svg(profile: Profile, working_point: float = DEFAULT_WORKING_POINT) -> str:
    """The plot as SVG text."""
    wp = check_working_point(working_point)
    ident = profile.identity
    panels = [_temperature_panel(profile, wp, 40)]
    power = _power_panel(profile, 40 + PANEL_HEIGHT)
    if power is not None:
        panels.append(power)
    height = 40 + PANEL_HEIGHT * len(panels)
    title = f"{ident.name}: {ident.printer or 'any printer'}, nozzle " \
            f"{ident.nozzle_diameter_mm:g} mm, {ident.filament_type or 'filament'}"
    out = ['<?xml version="1.0" encoding="UTF-8"?>',
           f'<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" '
           f'height="{height}" viewBox="0 0 {WIDTH} {height}" '
           f'font-family="sans-serif" font-size="12" '
           f'data-profile={quoteattr(ident.name)}>',
           f'<title>{escape(title)}</title>',
           f'<rect width="{WIDTH}" height="{height}" fill="white"/>',
           f'<text x="{WIDTH / 2}" y="24" text-anchor="middle" font-size="15" '
           f'font-weight="bold">{escape(title)}</text>']
    for panel in panels:
        out += panel.parts
    out.append("</svg>")
    return "\n".join(out) + "\n"


def png(profile: Profile, path: Path,
        working_point: float = DEFAULT_WORKING_POINT) -> None:
    """The temperature plot as PNG; needs matplotlib."""
    wp = check_working_point(working_point)
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise FlowloopError("PNG plots need matplotlib (pip install matplotlib); "
                            "SVG plots work without it") from None
    b, lines = profile.bounds, profile.lines
    ends = [b.min_temp_c, b.max_temp_c]
    fig, ax = plt.subplots(figsize=(8, 5))
    for line, label, color, style in (
            (lines.into_air.line(), "into air", COLORS["into_air"], "-"),
            (lines.real_print.line(), "real print", COLORS["real_print"], "-"),
            (profile_line(profile, wp), f"working point {wp:g}", COLORS["working"],
             "--")):
        ax.plot(ends, [max(0.0, line.flow_mm3_s(t)) for t in ends], style,
                color=color, label=label)
    for fl, color in ((lines.into_air, COLORS["into_air"]),
                      (lines.real_print, COLORS["real_print"])):
        ax.plot([fl.temp_c], [fl.flow_mm3_s], "x", color=color)
    for p in profile.points:
        ax.plot([p.temp_c], [p.flow_mm3_s], "o", mfc="none", color=COLORS[p.kind])
    for temp in (b.min_temp_c, b.recommended_temp_c, b.max_temp_c):
        ax.axvline(temp, color="grey", linestyle=":")
    ax.set_xlabel("hotend temperature [°C]")
    ax.set_ylabel("melt flow [mm³/s]")
    ax.set_title(profile.identity.name.replace("$", r"\$"))  # no mathtext
    ax.set_ylim(bottom=0)
    ax.grid(True)
    ax.legend(loc="upper left")
    fig.savefig(str(path), dpi=100)
    plt.close(fig)
