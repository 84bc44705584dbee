"""The cap arithmetic for one G-code move, and which cap wins.

A move goes from one G-code position (x, y, z, e) to the next at a requested
speed. Klipper treats the speed as the XYZ speed, or as the E speed when the
move has no XYZ motion (an extrude-only move). The volumetric flow a move
asks of the hotend is filament_area * dE / duration; only forward E melts
plastic, so retractions (and wipes with negative E) ask for no flow and are
never slowed, and travel (no E) is never touched. A cap only ever lowers a
speed, and nothing here changes a distance.
"""

from __future__ import annotations

import math
from typing import Iterator, List, NamedTuple, Optional, Sequence

from ..errors import FlowloopError

# Below this the move has no XYZ motion (Klipper's own threshold in Move()).
MIN_XYZ_MM = 1e-9
# A cap is never set below this: a zero cap would stop a move forever.
MIN_CAP_MM3_S = 0.1

CAP_NAMES = ("max_flow", "temperature", "grip", "model")
# On a printer a cap acts on a move when klippy queues it, about a second
# (its BUFFER_TIME_HIGH) before the move runs, and a move runs whole at the
# speed it was queued at: a 3 s infill line went on slipping to its end,
# whatever the windows said meanwhile (4.7 s from a slip to the first
# slowed move, against 1.3 s on 5 mm segments). So where the caps can
# change while a move waits (klippy runs its timers between the pieces), an
# extruding move longer than CUT_FROM_S, klippy's buffer, is queued in
# equal pieces of at most PIECE_S, half of it, each capped as it is queued
# (2.2 s on the 3 s line). A shorter move is replaced within the buffer
# anyway; pieces of 0.25 s from 0.25 s reacted in 1.6 s but cost klippy
# 1.20x its host time on the bench print, where these cost 1.03-1.10x.
PIECE_S = 0.5
CUT_FROM_S = 1.0


class MoveShape(NamedTuple):
    """What the limiter needs of a move: XYZ distance and filament pushed."""

    distance_mm: float  # XYZ path length; 0 for an extrude-only move
    extrude_mm: float   # E change (after the extrude factor); < 0 retracts

    @property
    def extrudes(self) -> bool:
        return self.extrude_mm > 0.0

    def flow_mm3_s(self, speed_mm_s: float, filament_area_mm2: float) -> float:
        """Volumetric flow at a requested speed; 0 unless the move extrudes."""
        if not self.extrudes:
            return 0.0
        if self.distance_mm < MIN_XYZ_MM:
            return filament_area_mm2 * speed_mm_s
        return filament_area_mm2 * self.extrude_mm / self.distance_mm * speed_mm_s

    def duration_s(self, speed_mm_s: float) -> float:
        """Time at the requested speed (no acceleration): for slowed_time."""
        length = self.distance_mm if self.distance_mm >= MIN_XYZ_MM \
            else abs(self.extrude_mm)
        return length / speed_mm_s if speed_mm_s > 0 else 0.0


def move_shape(start: Sequence[float], end: Sequence[float]) -> MoveShape:
    """The shape of a move between two G-code positions (x, y, z, e, ...)."""
    dx, dy, dz = end[0] - start[0], end[1] - start[1], end[2] - start[2]
    return MoveShape(math.sqrt(dx * dx + dy * dy + dz * dz), end[3] - start[3])


def piece_count(shape: MoveShape, speed_mm_s: float,
                piece_s: float = PIECE_S, cut_from_s: float = CUT_FROM_S) -> int:
    """How many equal pieces make an extruding move none of which takes
    longer than piece_s at the requested speed, if the move takes longer
    than cut_from_s (1: the move as it is)."""
    if not shape.extrudes:
        return 1
    duration = shape.duration_s(speed_mm_s)
    return 1 if duration <= cut_from_s else math.ceil(duration / piece_s)


def piece_ends(start: Sequence[float], end: Sequence[float], count: int
               ) -> Iterator[List[float]]:
    """The end position of each of count equal pieces of the move from start
    to end (every axis, E and any extra one, interpolated alike); the last
    is end itself, so the pieces add up to the move exactly."""
    for k in range(1, count):
        f = k / count
        yield [a + (b - a) * f for a, b in zip(start, end)]
    yield list(end)


def capped_speed(shape: MoveShape, speed_mm_s: float, cap_mm3_s: Optional[float],
                 filament_area_mm2: float, floor_mm_s: float = 0.0) -> float:
    """speed = min(speed, cap / (area * dE / distance)), never below floor_mm_s
    (and never above the requested speed, whatever the floor). A cap below
    MIN_CAP_MM3_S counts as MIN_CAP_MM3_S: a speed of 0 would stop klippy."""
    if cap_mm3_s is None or not shape.extrudes:
        return speed_mm_s
    cap_mm3_s = max(cap_mm3_s, MIN_CAP_MM3_S)
    flow = shape.flow_mm3_s(speed_mm_s, filament_area_mm2)
    if flow <= cap_mm3_s:
        return speed_mm_s
    slowed = speed_mm_s * cap_mm3_s / flow
    return min(speed_mm_s, max(slowed, floor_mm_s))


class ActiveCap(NamedTuple):
    cap_mm3_s: Optional[float]  # the lowest cap, None when no cap is on
    reason: str                 # one of CAP_NAMES, or "none"


def lowest_cap(**caps: Optional[float]) -> ActiveCap:
    """The lowest of the named caps (None = that cap is off), at least
    MIN_CAP_MM3_S; ties go to the first name in CAP_NAMES."""
    best = ActiveCap(None, "none")
    for name in CAP_NAMES:
        value = caps.pop(name, None)
        if value is not None and (best.cap_mm3_s is None or value < best.cap_mm3_s):
            best = ActiveCap(max(MIN_CAP_MM3_S, value), name)
    if caps:
        raise FlowloopError(f"unknown cap {sorted(caps)[0]!r}")
    return best


def check_max_flow(value: float, what: str = "max_flow") -> float:
    """A fixed cap in mm^3/s: a finite number above 0."""
    try:
        flow = float(value)
    except (TypeError, ValueError):
        raise FlowloopError(f"{what} must be a number in mm^3/s, not {value!r}") \
            from None
    if not math.isfinite(flow) or flow <= 0.0:
        raise FlowloopError(f"{what} must be above 0 mm^3/s, not {value}")
    return flow
