"""The flow a hotend has to melt: the planner's flow averaged over MELT_TIME_S.

A move of a few hundredths of a millimetre can ask for three times its
neighbours' flow for a few milliseconds (a slicer's rounding of E, a short
burst of fast infill between two corners). The hotend does not feel it: the
plastic that leaves in such a burst was heated in the melt zone during the
seconds before (a V6-like melt zone holds some 30 mm^3, over a second of the
highest flows these hotends print), the heater answers after a dead time of
about a second, and the grip windows that judge a slip span 1.25 mm of
filament (0.1-0.3 s at 10-30 mm^3/s). What the melt zone has to heat is the
flow over a time comparable with its residence; docs/autotemp.md gives the
evidence for MELT_TIME_S and what a shorter burst does.

`melt_events()` turns the planner's events into the flow the annotator
announces: the move batches as they were (`Lines`: where commands may go)
and `Segments` of constant flow, CELL_S long, each the higher of the mean
flow over the MELT_TIME_S centred on its start and on its end (the plastic
volume integrated exactly from the trapezoids at those times; between them
the mean moves by at most the flow times CELL_S / MELT_TIME_S, 2 %, and only
where it rises or falls, which the plan's margins absorb).
Barriers cut the average: no flow is counted across a wait the file does not
time.
"""

from __future__ import annotations

from typing import Iterable, Iterator, List, NamedTuple, Union

import numpy as np

from .fastplan import Segments
from .planner import Barrier, Segment

MELT_TIME_S = 0.5
CELL_S = 0.01
_RECORDS_PER_BATCH = 256


class Lines(NamedTuple):
    """A batch of the planner's moves: the lines commands may go before."""
    moves: Segments


MeltEvent = Union[Lines, Segments, Barrier]


def volume_at(batch: Segments, volume_before: float, times: np.ndarray
              ) -> np.ndarray:
    """Plastic (mm^3) left through the nozzle by each of times (within or
    after the batch, not before it), the trapezoids of flow integrated."""
    start, duration = batch.start_s, batch.duration_s
    i = np.clip(np.searchsorted(start, times, "right") - 1, 0, len(start) - 1)
    volume = batch.flow_mm3_s * 0.0
    whole = batch.filament_mm > 0.0
    # a move's plastic: its trapezoid's area (== filament * area up to rounding)
    accel, decel = batch.accel_s, batch.decel_s
    f0, f1, fc = batch.start_flow_mm3_s, batch.end_flow_mm3_s, batch.flow_mm3_s
    cruise = duration - accel - decel
    volume = np.where(whole, 0.5 * (f0 + fc) * accel + fc * cruise
                      + 0.5 * (fc + f1) * decel, 0.0)
    before = volume_before + np.concatenate(([0.0], np.cumsum(volume)))
    u = np.clip(times - start[i], 0.0, duration[i])
    a, d, c = accel[i], decel[i], cruise[i]
    s0, s1, sc = f0[i], f1[i], fc[i]
    ua = np.minimum(u, a)
    with np.errstate(divide="ignore", invalid="ignore"):
        rise = np.where(a > 0.0, 0.5 * (sc - s0) * ua * ua / a, 0.0)
        uc = np.clip(u - a, 0.0, c)
        ud = np.clip(u - a - c, 0.0, d)
        fall = np.where(d > 0.0, 0.5 * (sc - s1) * ud * ud / d, 0.0)
    part = s0 * ua + rise + sc * uc + sc * ud - fall
    return before[i] + np.where(whole[i], part, 0.0)


def _batches(events: Iterable) -> Iterator[Union[Segments, Barrier]]:
    """Planner events as batches: records (planner.Segment) are gathered."""
    records: List[Segment] = []

    def gathered() -> Segments:
        columns = list(zip(*records))
        records.clear()
        return Segments(*[np.array(c, dtype=np.int64 if k == len(columns) - 1
                                   else float) for k, c in enumerate(columns)])
    for event in events:
        if isinstance(event, Segment):
            records.append(event)
            if len(records) >= _RECORDS_PER_BATCH:
                yield gathered()
            continue
        if records:
            yield gathered()
        yield event
    if records:
        yield gathered()


class _Grid:
    """The volume on a grid of CELL_S from an origin (0, or a barrier)."""

    def __init__(self, origin_s: float, volume: float, melt_s: float,
                 cell_s: float):
        self.origin_s = origin_s
        self.cell_s = cell_s
        self.melt_s = melt_s
        self.half = max(1, round(0.5 * melt_s / cell_s))   # cells in h
        self.known = [np.array([volume])]   # V at grid points first.. (chunks)
        self.first = 0                      # grid index of known[0][0]
        self.count = 1                      # grid points known
        self.next_cell = 0

    def extend(self, values: np.ndarray) -> None:
        if len(values):
            self.known.append(values)
            self.count += len(values)

    def next_time(self) -> float:
        return self.origin_s + self.count * self.cell_s

    def cells(self, until_cell: int) -> Segments:
        """Cells next_cell..until_cell-1 whose volumes are known."""
        h = self.half
        last = min(until_cell, self.count - 1 - h)     # cell k needs V[k+1+h]
        k = np.arange(self.next_cell, max(self.next_cell, last))
        v = np.concatenate(self.known)
        at_start = v[k + h - self.first] - v[np.maximum(k - h, 0) - self.first]
        at_end = v[k + 1 + h - self.first] - v[np.maximum(k + 1 - h, 0) - self.first]
        flow = np.maximum(at_start, at_end) / (2 * h * self.cell_s)
        if len(k):
            self.next_cell = int(k[-1]) + 1
            # keep what later cells still need
            keep = self.next_cell - h - self.first
            if keep > 0:
                self.known = [v[keep:]]
                self.first += keep
        start = self.origin_s + k * self.cell_s
        zero = np.zeros(len(k))
        return Segments(start, zero + self.cell_s, flow, zero, zero, flow, flow,
                        zero, zero, zero, np.full(len(k), -1, dtype=np.int64))


def melt_events(events: Iterable, melt_s: float = MELT_TIME_S,
                cell_s: float = CELL_S) -> Iterator[MeltEvent]:
    """Planner events (records or batches) as Lines, melt-flow cells and
    barriers, in print time."""
    grid = _Grid(0.0, 0.0, melt_s, cell_s)
    volume = 0.0
    end_s = 0.0
    for event in _batches(events):
        if isinstance(event, Barrier):
            yield from _close(grid, event.time_s, volume)
            yield event
            grid = _Grid(event.time_s, volume, melt_s, cell_s)
            continue
        if not len(event):
            continue
        yield Lines(event)
        first = grid.count
        last = int(np.floor((float(event.start_s[-1] + event.duration_s[-1])
                             - grid.origin_s) / cell_s))
        if last >= first:
            times = grid.origin_s + np.arange(first, last + 1) * cell_s
            grid.extend(volume_at(event, volume, times))
        volume = float(volume_at(event, volume, np.array(
            [event.start_s[-1] + event.duration_s[-1]]))[0])
        end_s = float(event.start_s[-1] + event.duration_s[-1])
        cells = grid.cells(grid.count)
        if len(cells):
            yield cells
    yield from _close(grid, end_s, volume)


def _close(grid: _Grid, time_s: float, volume: float) -> Iterator[Segments]:
    """The cells up to time_s, nothing flowing after it."""
    last_cell = int(np.ceil((time_s - grid.origin_s) / grid.cell_s - 1e-9))
    need = last_cell + 1 + grid.half
    if need >= grid.count:
        grid.extend(np.full(need - grid.count + 1, volume))
    cells = grid.cells(last_cell)
    if len(cells):
        # the last cell ends with the print (or at the wait), as the moves do
        cells.duration_s[-1] = min(cells.duration_s[-1], time_s - cells.start_s[-1])
        yield cells
