"""The reactive speed rule as a plot (docs/flowrate_limiter_rule.svg).

A steady print demands `demand` mm^3/s; for a while the hotend melts less
(`weak_capacity`, a cold draft or a sagging heater). The feeder slips by
capacity / flow. Each grip window is judged and acted on after the buffer's
latency: moves queued in the lookahead run about a second after the decision.
The same scenario runs under flowloop's rule (flowloop.control.reactive) and
under ddPrint's (speed in proportion to grip / min_grip, no memory, no
hysteresis), and the plot shows speed factor and grip over time for both.
"""

from __future__ import annotations

import collections
from typing import Deque, Dict, List, Tuple

from ..material.plot import COLORS, WIDTH, Panel, svg_open
from ..window import JUDGED, Window
from .reactive import DEFAULT_MIN_SPEED_FACTOR, ReactiveRule, ReactiveSettings

WINDOW_S = 0.25
LATENCY_S = 1.0
DEFAULT_SETTINGS = ReactiveSettings()
# The scenario is in mm^3/s: its windows count filament as volume (an area
# of 1 mm^2), so flows go through the rule unrounded.
AREA_MM2 = 1.0


def simulate(rule: str, demand: float = 20.0, capacity: float = 30.0,
             weak_capacity: float = 12.0, weak_from_s: float = 2.0,
             weak_until_s: float = 12.0, duration_s: float = 20.0,
             settings: ReactiveSettings = DEFAULT_SETTINGS,
             min_speed_factor: float = DEFAULT_MIN_SPEED_FACTOR
             ) -> List[Tuple[float, float, float]]:
    """(time, speed factor, grip) per window under `rule` ("flowloop" or
    "ddprint")."""
    reactive = ReactiveRule(settings, AREA_MM2)
    pending: Deque[Tuple[float, float]] = collections.deque()  # (from, factor)
    factor, out = 1.0, []
    steps = int(duration_s / WINDOW_S)
    for k in range(steps):
        t = k * WINDOW_S
        while pending and pending[0][0] <= t:
            factor = pending.popleft()[1]
        melt = weak_capacity if weak_from_s <= t < weak_until_s else capacity
        flow = factor * demand
        grip = min(1.0, melt / flow)
        out.append((t, factor, grip))
        if rule == "flowloop":
            commanded_mm = flow * WINDOW_S / AREA_MM2
            cap = reactive.on_window(Window(
                t, t + WINDOW_S, commanded_mm, grip * commanded_mm, grip,
                JUDGED))
            wanted = 1.0 if cap is None else max(min_speed_factor,
                                                 min(1.0, cap / demand))
        else:
            wanted = 1.0 if grip >= settings.min_grip else max(
                min_speed_factor, factor * grip / settings.min_grip)
        pending.append((t + WINDOW_S + LATENCY_S, wanted))
    return out


def under_extrusion(run: List[Tuple[float, float, float]], demand: float = 20.0
                    ) -> float:
    """mm^3 the feeder failed to push over a run."""
    return sum((1.0 - grip) * factor * demand * WINDOW_S
               for _, factor, grip in run)


def svg() -> str:
    runs: Dict[str, List[Tuple[float, float, float]]] = {
        rule: simulate(rule) for rule in ("flowloop", "ddprint")}
    height = 460
    panel = Panel(0, (0.0, 20.0), (0.0, 1.5))  # room for the legend
    panel.frame("Reactive rule: demand 20 mm³/s, the hotend melts 12 from 2 s "
                "to 12 s", "time (s)", "speed factor, grip")
    ours, theirs = COLORS["working"], COLORS["real_print"]
    styles = {("flowloop", 1): (ours, ""), ("flowloop", 2): (ours, "5,4"),
              ("ddprint", 1): (theirs, ""), ("ddprint", 2): (theirs, "5,4")}
    legend = []
    for rule, run in runs.items():
        for column, what in ((1, "speed factor"), (2, "grip")):
            color, dash = styles[(rule, column)]
            points = [(row[0], row[column]) for row in run]
            panel.polyline(points, color, f"{rule}_{what.replace(' ', '_')}", dash)
            lost = under_extrusion(run)
            legend.append((f"{rule} {what}"
                           + (f" (lost {lost:.0f} mm³)" if column == 2 else ""),
                           color, dash))
    panel.legend(legend)
    out = svg_open(WIDTH, height) + panel.parts
    out.append("</svg>")
    return "\n".join(out) + "\n"
