"""Nozzle health as a picture: each print's melt capacity against its
profile (the ratio, with bars of two standard errors), the profile (1),
the line below which a print warns (1 - HEALTHY_MARGIN) and the ratio at
which the prints' highest flows slip below min_grip. Drawn on the profile
plot's Panel (flowloop.material.plot)."""

from __future__ import annotations

from typing import List, Sequence
from xml.sax.saxutils import escape

from ..material.plot import COLORS, WIDTH, Panel, svg_line, svg_open, tooltip
from .nozzle_health import HEALTHY_MARGIN, PrintEstimate, judge

HEIGHT = 450


def svg(prints: Sequence[PrintEstimate], title: str) -> str:
    """Capacity against the profile over prints, oldest first; prints
    without an estimate are marked on the axis with their reason."""
    known = [e for e in prints if e.known]
    lows = [e.ratio - 2 * e.standard_error for e in known]
    limits = [e.limit_ratio for e in prints if e.limit_ratio is not None]
    y_lo = min([0.8] + lows + limits) - 0.02
    y_hi = max([1.1] + [e.ratio + 2 * e.standard_error for e in known])
    count = max(1, len(prints))
    panel = Panel(0, (0.5, count + 0.5), (y_lo, y_hi))
    ticks = [(float(i + 1), str(i + 1)) for i in range(count)]
    panel.frame(f"Nozzle health: {title}", "print", "melt capacity / profile",
                x_ticks=ticks if count <= 20 else None)
    span = (0.5, count + 0.5)
    marks = [("profile", 1.0, COLORS["working"], ""),
             ("warn below", 1.0 - HEALTHY_MARGIN, COLORS["recommended"], "6,4")]
    if limits:
        marks.append(("highest flows slip below min_grip", max(limits),
                      COLORS["cap"], "2,3"))
    for _name, value, color, dash in marks:
        panel.add(svg_line(panel.x(span[0]), panel.y(value), panel.x(span[1]),
                           panel.y(value), color, dash, 1.5))
    points: List[str] = []
    for i, e in enumerate(prints):
        x = panel.x(i + 1)
        if not e.known:
            points.append(tooltip(f"print {i + 1}: no estimate: {e.reason}",
                                  f'<circle class="no-estimate" cx="{x:.2f}" '
                                  f'cy="{panel.bottom - 6:.2f}" r="3" '
                                  f'fill="{COLORS["bound"]}"/>'))
            continue
        top, low = panel.y(e.ratio + 2 * e.standard_error), panel.y(
            e.ratio - 2 * e.standard_error)
        points.append(tooltip(
            f"print {i + 1}: {e.ratio:.3f} +/- {e.standard_error:.3f} "
            f"(grip noise {e.grip_noise:.4f}, {e.windows} windows)",
            svg_line(x, top, x, low, COLORS["measured"], "", 2)
            + f'<circle class="estimate" cx="{x:.2f}" cy="{panel.y(e.ratio):.2f}" '
            f'r="4" fill="white" stroke="{COLORS["measured"]}" stroke-width="2"/>'))
    panel.add('<g id="prints">' + "".join(points) + "</g>")
    verdict = judge(prints)
    legend = [("each print: ratio +/- 2 standard errors", COLORS["measured"], "")]
    if not all(e.known for e in prints):
        # drawn at the bottom; the dot's tooltip says why
        legend.append(("no estimate (too little evidence)", COLORS["bound"], "1,3"))
    panel.legend(legend + [(name, color, dash) for name, _, color, dash in marks])
    color = COLORS["cap"] if verdict.warn else "black"
    out = svg_open(WIDTH, HEIGHT) + panel.parts
    for i, row in enumerate(verdict.text.split("; ")):
        out.append(f'<text class="verdict" x="{panel.left}" '
                   f'y="{HEIGHT - 22 + 14 * i}" fill="{color}">{escape(row)}</text>')
    out.append("</svg>")
    return "\n".join(out) + "\n"
