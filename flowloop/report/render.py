"""A flow report as one HTML file with inline SVG: nothing it shows is
fetched from anywhere, so it opens offline, attached to a mail or from
Moonraker's data folder.

Four pictures (drawn with flowloop.material.plot's Panel, as the profile
plot is): commanded against measured flow with the limiter's cap, grip with
the limiter's slowdowns shaded by reason, the nozzle against its target and
autotemp's plan, and the filament under-extruded per layer. Sensor faults
and gaps in the data are shaded in every time panel. Tables: the job, what
the report lacks, the limiter's cost by reason, the faults and their lost
time, the profiles in force, the events. The document is well-formed XML
(XHTML syntax) so a test, or a script, can read it as such.
"""

from __future__ import annotations

from typing import Dict, List, Optional, Sequence, Tuple
from xml.sax.saxutils import escape

from ..material.plot import (
    COLORS,
    PANEL_HEIGHT,
    WIDTH,
    Panel,
    svg_line,
    svg_open,
    tooltip,
)
from .recorder import MAX_SAMPLE_GAP_S, Recorder, Span, duration_text

# Shading under the grid: solid pale colours (no renderer-dependent opacity).
SHADES = {"fault": "#f6d0cc", "no data": "#e0e0e0", "max_flow": "#e8e8e8",
          "temperature": "#fbd9d2", "grip": "#cdeff3", "model": "#d3f0d3",
          "mixed": "#fde3c8"}
GRIP_FLOOR = 1.0  # the axis holds full grip; room above it for the legend
# Above this many seconds the time axis is in minutes.
MINUTES_FROM_S = 600.0
STYLE = """
body { font-family: sans-serif; margin: 1.5em; max-width: 800px; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; }
td, th { border: 1px solid #ccc; padding: 2px 8px; text-align: left; }
th { background: #f3f3f3; }
#lacks li { color: #b42318; }
svg { display: block; margin: 0.5em 0; }
"""


class _Time:
    """The time axis: seconds, or minutes for a long print."""

    def __init__(self, duration_s: float) -> None:
        self.scale = 60.0 if duration_s > MINUTES_FROM_S else 1.0
        self.label = "time since the print started [min]" if self.scale > 1 \
            else "time since the print started [s]"
        self.range = (0.0, max(duration_s, 1.0) / self.scale)

    def __call__(self, seconds: float) -> float:
        return seconds / self.scale


def _segments(points: Sequence[Tuple[float, Optional[float]]], join: float
              ) -> List[List[Tuple[float, float]]]:
    """Runs of known points: empty bins between two samples less than `join`
    apart are bridged (samples sparser than the bins), a longer gap breaks
    the line (the recorder counts it lost)."""
    out: List[List[Tuple[float, float]]] = []
    for x, y in points:
        if y is None:
            continue
        if out and x - out[-1][-1][0] <= join:
            out[-1].append((x, y))
        else:
            out.append([(x, y)])
    return out


def _widened(seg: List[Tuple[float, float]], half: float
             ) -> List[Tuple[float, float]]:
    """A lone point as a level stroke one bin wide: a polyline of one point
    (or of one point twice) draws nothing."""
    if len(seg) > 1:
        return seg
    (x, y), = seg
    return [(x - half, y), (x + half, y)]


class _Spacing:
    """How far apart drawn points may be and still be one line, and how wide
    a lone point is drawn, in the time axis' units."""

    def __init__(self, rec: Recorder, time: _Time) -> None:
        # two samples up to the recorder's gap apart land in bins whose
        # centres are up to one bin further apart
        self.join = time(MAX_SAMPLE_GAP_S + rec.bins.width_s + 1e-9)
        self.half = time(rec.bins.width_s) / 2


def _line(panel: Panel, points, color: str, ident: str, spacing: _Spacing,
          dash: str = "", width: float = 2) -> None:
    panel.add(f'<g id="{ident}" class="series">')
    for k, seg in enumerate(_segments(points, spacing.join)):
        panel.polyline(_widened(seg, spacing.half), color, f"{ident}-{k}",
                       dash, width)
    panel.add("</g>")


def _band(panel: Panel, low, high, color: str, ident: str,
          spacing: _Spacing) -> None:
    """The area between each bin's min and max."""
    panel.add(f'<g id="{ident}" class="band">')
    pairs = [(x, None if lo is None or hi is None else (lo, hi))
             for (x, lo), (_, hi) in zip(low, high)]
    for seg in _segments(pairs, spacing.join):
        seg = _widened(seg, spacing.half)
        coords = [(x, hi) for x, (lo, hi) in seg] + \
            [(x, lo) for x, (lo, hi) in reversed(seg)]
        text = " ".join(f"{panel.x(a):.2f},{panel.y(b):.2f}" for a, b in coords)
        panel.add(f'<polygon points="{text}" fill="{color}" stroke="none"/>')
    panel.add("</g>")


def _shade(panel: Panel, spans: Sequence[Span], time: _Time, css: str,
           shade_of) -> None:
    for span in spans:
        x0 = panel.x(time(span.start_s))
        x1 = max(panel.x(time(span.end_s)), x0 + 1.0)
        panel.add(tooltip(
            f"{span.kind}: {duration_text(span.start_s)} to {duration_text(span.end_s)}"
            f", {span.cost_s:.1f} s",
            f'<rect class="{css}" x="{x0:.2f}" y="{panel.top:.2f}" '
            f'width="{x1 - x0:.2f}" height="{panel.bottom - panel.top:.2f}" '
            f'fill="{shade_of(span.kind)}" stroke="none"/>'))


def _fault_shade(kind: str) -> str:
    return SHADES["no data"] if kind == "no data" else SHADES["fault"]


def _slow_shade(kind: str) -> str:
    return SHADES.get(kind, SHADES["mixed"])


def _missing(panel: Panel, text: str) -> None:
    x = (panel.left + panel.right) / 2
    y = (panel.top + panel.bottom) / 2
    panel.add(f'<text class="missing" x="{x:.2f}" y="{y:.2f}" '
              f'text-anchor="middle" fill="#b42318">{escape(text)}</text>')


def _svg(ident: str, panel: Panel) -> str:
    # no XML declaration: the SVG sits inside the HTML
    return "\n".join(svg_open(WIDTH, PANEL_HEIGHT, f' id="{ident}"')[1:]
                     + panel.parts + ["</svg>"])


def _y_range(rec: Recorder, channels: Sequence[str], floor: float,
             room: float = 0.3) -> Tuple[float, float]:
    """A y axis from 0 (or the lowest value drawn, if below) to the highest
    value drawn (at least `floor`), with `room` of the span above it for
    the legend: every drawn value, bands included, inside the frame."""
    lows = [rec.bins.extreme(c, "min") for c in channels]
    highs = [rec.bins.extreme(c, "max") for c in channels]
    low = min([v for v in lows if v is not None] + [0.0])
    high = max([v for v in highs if v is not None] + [floor])
    span = high - low
    return (low - (0.05 * span if low < 0 else 0.0), high + room * span)


def _time_panel(rec: Recorder, time: _Time, y_range, title: str, y_label: str,
                slowdowns: bool = False) -> Panel:
    panel = Panel(0, time.range, y_range)
    if slowdowns:
        _shade(panel, rec.slowdowns.items, time, "slowdown", _slow_shade)
    _shade(panel, rec.faults.items, time, "fault", _fault_shade)
    panel.grid()
    panel.axes(title, time.label, y_label)
    return panel


def _series(rec: Recorder, time: _Time, channel: str, stat: str = "mean"):
    return [(time(t), v) for t, v in rec.bins.series(channel, stat)]


def flow_svg(rec: Recorder, time: _Time) -> str:
    spacing = _Spacing(rec, time)
    y_range = _y_range(rec, ("commanded_flow", "measured_flow", "cap"), 1.0)
    panel = _time_panel(rec, time, y_range, "Flow: commanded and measured",
                        "flow [mm³/s]")
    if rec.bins.extreme("commanded_flow", "max") is None:
        _missing(panel, "no flow data (no flow sensor reported)")
    _band(panel, _series(rec, time, "measured_flow", "min"),
          _series(rec, time, "measured_flow", "max"), COLORS["band"],
          "measured_flow_range", spacing)
    _line(panel, _series(rec, time, "commanded_flow"), COLORS["demand"],
          "commanded_flow", spacing)
    _line(panel, _series(rec, time, "measured_flow"), COLORS["measured"],
          "measured_flow", spacing)
    _line(panel, _series(rec, time, "measured_flow", "max"), COLORS["measured"],
          "measured_flow_max", spacing, "2,3", 1)
    _line(panel, _series(rec, time, "cap"), COLORS["cap"], "cap", spacing, "6,4")
    panel.legend([("commanded (mean per bin)", COLORS["demand"], ""),
                  ("measured (mean, band: min..max)", COLORS["measured"], ""),
                  ("limiter cap", COLORS["cap"], "6,4")])
    return _svg("flow-plot", panel)


def grip_svg(rec: Recorder, time: _Time) -> str:
    spacing = _Spacing(rec, time)
    panel = _time_panel(rec, time, _y_range(rec, ("grip",), GRIP_FLOOR, 0.4),
                        "Grip, and where the limiter "
                        "slowed the print", "grip (measured / commanded)",
                        slowdowns=True)
    if rec.bins.extreme("grip", "min") is None:
        _missing(panel, "no grip: the sensor reported none (absent or faulted)")
    limit = 1.0 - rec.grip_noise
    panel.add(svg_line(panel.left, panel.y(limit), panel.right, panel.y(limit),
                       COLORS["bound"], "2,3", 1, "grip_noise_limit"))
    _line(panel, _series(rec, time, "grip"), COLORS["grip"], "grip", spacing)
    _line(panel, _series(rec, time, "grip", "min"), COLORS["grip"], "grip_min",
          spacing, "3,3", 1)
    panel.legend([("grip (mean per bin)", COLORS["grip"], ""),
                  ("grip (lowest per bin)", COLORS["grip"], "3,3"),
                  (f"1 - sensor noise ({limit:g})", COLORS["bound"], "2,3")])
    return _svg("grip-plot", panel)


def temperature_svg(rec: Recorder, time: _Time) -> str:
    spacing = _Spacing(rec, time)
    channels = ("temp", "target", "planned_temp")
    highs = [rec.bins.extreme(c, "max") for c in channels]
    lows = [rec.bins.extreme(c, "min") for c in channels]
    known = [v for v in highs + lows if v is not None]
    y_range = (min(known) - 5.0, max(known) + 5.0) if known else (0.0, 300.0)
    if y_range[1] - y_range[0] < 20:
        mid = sum(y_range) / 2
        y_range = (mid - 10, mid + 10)
    panel = _time_panel(rec, time, y_range, "Hotend: nozzle, target and "
                        "autotemp's plan", "temperature [°C]")
    if not known:
        _missing(panel, "no hotend temperature was recorded")
    elif rec.planned_samples == 0:
        _missing(panel, "autotemp planned no temperature for this print")
    _line(panel, _series(rec, time, "target"), COLORS["target"], "target",
          spacing, "6,4")
    _line(panel, _series(rec, time, "planned_temp"), COLORS["planned"],
          "planned_temp", spacing)
    _line(panel, _series(rec, time, "temp"), COLORS["nozzle"], "temp", spacing)
    panel.legend([("nozzle", COLORS["nozzle"], ""),
                  ("heater target", COLORS["target"], "6,4"),
                  ("autotemp's plan", COLORS["planned"], "")])
    return _svg("temperature-plot", panel)


def layers_svg(rec: Recorder) -> str:
    layers = [layer for _, layer in sorted(rec.layers.items())]
    first = layers[0].layer if layers else 1
    last = layers[-1].layer if layers else 1
    top = max([layer.under_mm for layer in layers] + [0.1]) * 1.3
    panel = Panel(0, (first - 0.5, last + 0.5), (0.0, top))
    panel.frame("Filament under-extruded per layer", "layer",
                "under-extruded filament [mm]")
    if not layers:
        _missing(panel, "no layer information was recorded")
    width = max(1.0, panel.x(first + 0.4) - panel.x(first - 0.4))
    panel.add('<g id="under_extrusion">')
    for layer in layers:
        x = panel.x(layer.layer) - width / 2
        y = panel.y(layer.under_mm)
        z = "" if layer.z_mm is None else f" (z {layer.z_mm:g} mm)"
        panel.add(tooltip(
            f"layer {layer.layer}{z}: {layer.under_mm:.2f} mm under-extruded of "
            f"{layer.commanded_mm:.1f} mm commanded",
            f'<rect class="layer" data-layer="{layer.layer}" x="{x:.2f}" '
            f'y="{y:.2f}" width="{width:.2f}" height="{panel.bottom - y:.2f}" '
            f'fill="{COLORS["real_print"]}" stroke="none"/>'))
    panel.add("</g>")
    return _svg("layers-plot", panel)


# --- tables ---------------------------------------------------------------------

def _table(ident: str, head: Sequence[str], rows: Sequence[Sequence[str]],
           empty: str) -> str:
    if not rows:
        return f'<p id="{ident}">{escape(empty)}</p>'
    out = [f'<table id="{ident}">']
    if head:
        out.append("<tr>" + "".join(f"<th>{escape(h)}</th>" for h in head)
                   + "</tr>")
    out += ["<tr>" + "".join(f"<td>{escape(c)}</td>" for c in row) + "</tr>"
            for row in rows]
    return "\n".join(out) + "</table>"


def _wp(value: Optional[float]) -> str:
    return "-" if value is None else f"{value:g}"


def summary_rows(rec: Recorder) -> List[Tuple[str, str]]:
    """The job's figures, as the report's first table (and the CLI) show them."""
    job = rec.job
    profiles = ", ".join(f"{s.kind} (working point {_wp(s.working_point)})"
                         for s in rec.profiles.items) or "none"
    commanded = rec.commanded_mm
    share = f" ({100 * rec.under_mm / commanded:.2f} % of {commanded:.0f} mm " \
        "commanded)" if commanded > 0 else ""
    slowed = sum(rec.slowdown_by_reason().values())
    return [
        ("job", job.job_id or "-"),
        ("file", job.filename or "-"),
        ("ended", job.state or "not yet"),
        ("duration", duration_text(rec.duration_s())),
        ("profile", profiles),
        ("under-extruded", f"{rec.under_mm:.2f} mm of filament{share}"),
        ("limiter slowed the print", f"{slowed:.1f} s"),
        ("sensor faults and gaps", f"{len(rec.faults.items)}, "
         f"{rec.lost_s():.1f} s without a judged grip"),
    ]


def _layer_rows(rec: Recorder) -> List[List[str]]:
    """Every layer, in print order: the layers that extruded well show as
    much as the ones that did not."""
    return [[str(layer.layer), "-" if layer.z_mm is None else f"{layer.z_mm:g}",
             f"{layer.under_mm:.2f}", f"{layer.commanded_mm:.1f}",
             f"{100 * layer.under_mm / layer.commanded_mm:.1f}"
             if layer.commanded_mm > 0 else "-"]
            for _, layer in sorted(rec.layers.items())]


def html(rec: Recorder) -> str:
    """The report: one HTML document, its pictures inline."""
    time = _Time(rec.duration_s())
    title = f"Flow report: {rec.job.filename or 'job ' + (rec.job.job_id or '?')}"
    lacks = rec.lacks()
    by_reason: Dict[str, float] = rec.slowdown_by_reason()
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8"/>',
        f"<title>{escape(title)}</title><style>{STYLE}</style></head><body>",
        f"<h1>{escape(title)}</h1>",
        _table("summary", (), summary_rows(rec), ""),
        "<h2>What this report lacks</h2>",
        ('<ul id="lacks">' + "".join(f"<li>{escape(x)}</li>" for x in lacks)
         + "</ul>") if lacks else '<p id="lacks">Nothing: the print completed and '
        'every series was recorded (faults and gaps are listed below).</p>',
        "<h2>Flow</h2>", flow_svg(rec, time),
        "<h2>Grip and the limiter</h2>", grip_svg(rec, time),
        _table("slowdowns", ("reason", "time it cost [s]", "stretches"),
               [[reason, f"{cost:.1f}",
                 str(sum(1 for s in rec.slowdowns.items if s.kind == reason))]
                for reason, cost in sorted(by_reason.items())],
               "The limiter did not slow the print."),
        "<h2>Temperature</h2>", temperature_svg(rec, time),
        "<h2>Under-extrusion by layer</h2>", layers_svg(rec),
        _table("layer-table", ("layer", "z [mm]", "under-extruded [mm]",
                               "commanded [mm]", "share [%]"),
               _layer_rows(rec), "No layer was recorded."),
        "<h2>Sensor faults and lost time</h2>",
        _table("faults", ("fault", "from", "to", "lost [s]", "layer"),
               [[s.kind, duration_text(s.start_s), duration_text(s.end_s),
                 f"{s.cost_s:.1f}", "-" if s.layer is None else str(s.layer)]
                for s in rec.faults.items], "No sensor fault, no gap in the data."),
        "<h2>Profile and working point</h2>",
        _table("profiles", ("profile", "working point", "from", "to"),
               [[s.kind, _wp(s.working_point), duration_text(s.start_s),
                 duration_text(s.end_s)] for s in rec.profiles.items],
               "No material profile was active."),
        "<h2>Events</h2>",
        _table("events", ("time", "event"),
               [[duration_text(e.time_s), e.text] for e in rec.events]
               + ([["", f"{rec.events_dropped} more not kept"]]
                  if rec.events_dropped else []),
               "None."),
        "</body></html>",
    ]
    return "\n".join(parts) + "\n"


def not_kept_html(job_id: str, filename: Optional[str], keep: int) -> str:
    """The page a report link opens for a job of Moonraker's history whose
    report flowloop does not keep: pruned by number_of_reports_to_keep, or
    never written (printed before flowloop was installed)."""
    title = f"No report kept for job {job_id}"
    of = f" ({filename})" if filename else ""
    return "\n".join([
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8"/>',
        '<meta name="color-scheme" content="light dark"/>',
        f"<title>{escape(title)}</title><style>{STYLE}</style></head><body>",
        f"<h1>{escape(title)}</h1>",
        f'<p id="not-kept">flowloop keeps the flow reports of the newest {keep} '
        f"jobs (number_of_reports_to_keep in moonraker.conf's [flowloop]): the "
        f"report of job {escape(job_id + of)} is no longer kept, or the job "
        "printed before flowloop was installed. Its figures stay in the job's "
        "history.</p>",
        "</body></html>",
    ]) + "\n"
