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
evidence for MELT_TIME_S and what a shorter burst does. The window is a
setting of the printer (flowloop.gcode.melt_window: `--melt-window`, else
`[autotemp] melt_window`, else MELT_TIME_S).

`melt_events()` turns the planner's events into the flow the annotator
announces: the move batches as they were (`Lines`: where commands may go)
and `Cells` of constant flow, CELL_S long, each the higher of the mean
flow over the MELT_TIME_S centred on its start and on its end (the plastic
volume integrated exactly from the trapezoids at those times; between them
the mean moves by at most the flow times CELL_S / MELT_TIME_S, 2 %, and only
where it rises or falls; on the bench's files it exceeds the cells by at
most 0.21 %, which the plan's FLOW_MARGIN of 0.5 % absorbs:
flowloop.control.autotemp).
Barriers cut the average: no flow is counted across a wait the file does not
time.

It costs a few array passes per cell: the moves' trapezoids become pieces of
constant slope, each piece's values are repeated over its grid times (no
search and no gather per cell), and each centred mean is the difference of
two volumes.
"""

from __future__ import annotations

from typing import Iterable, Iterator, List, NamedTuple, Union

import numpy as np

from .bulk_planner import Segments
from .melt_window import MELT_TIME_S
from .reference_planner import Barrier, Segment

CELL_S = 0.01
_RECORDS_PER_BATCH = 256


class Lines(NamedTuple):
    """A batch of the planner's moves: the lines commands may go before."""
    moves: Segments


class Cells(NamedTuple):
    """Consecutive cells of the flow to melt: cell k runs from start_s[k] to
    the next cell's start (the last one to end_s) at flow_mm3_s[k]."""
    start_s: np.ndarray
    end_s: float
    flow_mm3_s: np.ndarray

    def __len__(self) -> int:        # NamedTuple's would count the fields
        return len(self.start_s)


MeltEvent = Union[Lines, Cells, Barrier]


class _Pieces(NamedTuple):
    """A batch's flow as pieces of constant slope (each move's accel, cruise
    and decel), with the plastic volume left through the nozzle at each start."""
    start_s: np.ndarray
    length_s: np.ndarray
    volume_mm3: np.ndarray
    flow_mm3_s: np.ndarray
    slope_mm3_s2: np.ndarray
    end_volume_mm3: float


def _pieces(batch: Segments, volume_before: float) -> _Pieces:
    start, accel, decel = batch.start_s, batch.accel_s, batch.decel_s
    cruise = np.maximum(batch.duration_s - accel - decel, 0.0)
    # a move that does not add plastic (travel, retraction, unretraction) melts none
    whole = batch.filament_mm > 0.0
    f0 = np.where(whole, batch.start_flow_mm3_s, 0.0)
    fc = np.where(whole, batch.flow_mm3_s, 0.0)
    f1 = np.where(whole, batch.end_flow_mm3_s, 0.0)
    length = np.stack((accel, cruise, decel), axis=1).ravel()
    at_start = np.stack((f0, fc, fc), axis=1).ravel()
    starts = np.stack((start, start + accel, start + accel + cruise), axis=1).ravel()
    # each piece's 0.5 * (flow at start + at end) * length, and its slope,
    # (flow at end - at start) / length (0 where it has none; a cruise's is 0)
    volume = np.stack((0.5 * (f0 + fc) * accel, 0.5 * (fc + fc) * cruise,
                       0.5 * (fc + f1) * decel), axis=1).ravel()
    total = np.cumsum(volume)
    before = np.empty(len(total))
    before[0] = 0.0
    before[1:] = total[:-1]
    before += volume_before
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = np.stack((np.where(accel > 0.0, (fc - f0) / accel, 0.0),
                          np.zeros(len(fc)),
                          np.where(decel > 0.0, (f1 - fc) / decel, 0.0)),
                         axis=1).ravel()
    return _Pieces(starts, length, before, at_start, slope,
                   volume_before + float(total[-1]))


def volume_at(pieces: _Pieces, times: np.ndarray) -> np.ndarray:
    """Plastic (mm^3) left through the nozzle by each of times (increasing,
    within the batch or after it; one before it counts as at its start)."""
    # times[first[p]:first[p + 1]] fall in piece p. A piece of no length
    # that the next one starts with gets none (nor does it change where the
    # others start): only the others are searched for (the first and last
    # are kept: one before the batch counts as at its start)
    start, length = pieces.start_s, pieces.length_s
    keep = np.empty(len(start), bool)
    keep[0] = keep[-1] = True
    np.not_equal(length[1:-1], 0.0, out=keep[1:-1])
    keep[1:-1] |= start[2:] != start[1:-1]
    kept = np.flatnonzero(keep)
    first = np.maximum.accumulate(_search_grid(times, start[kept]))
    first[0] = 0
    counts = np.diff(np.append(first, len(times)))
    # each piece's value repeated over its times (a copy in order, not a
    # gather), then volume + u * (flow + 0.5 * slope * u) in place, u the
    # time into the piece within its length
    u = times - np.repeat(start[kept], counts)
    np.maximum(u, 0.0, out=u)
    np.minimum(u, np.repeat(length[kept], counts), out=u)
    out = np.repeat(0.5 * pieces.slope_mm3_s2[kept], counts)
    out *= u
    out += np.repeat(pieces.flow_mm3_s[kept], counts)
    out *= u
    out += np.repeat(pieces.volume_mm3[kept], counts)
    return out


def _grid_times(origin_s: float, first: int, stop: int,
                cell_s: float) -> np.ndarray:
    """origin_s + k * cell_s for k in first..stop-1, in place (no
    temporaries: the grid is millions of points on a long print)."""
    times = np.arange(first, stop, dtype=float)
    times *= cell_s
    times += origin_s
    return times


def _search_grid(times: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """np.searchsorted(times, keys, "left") for times evenly spaced (the
    grid): each place computed, then checked against its neighbours (a
    search only where that fails)."""
    m = len(times)
    if m < 2:
        return np.searchsorted(times, keys, "left")
    step = (times[-1] - times[0]) / (m - 1)
    at = np.ceil((keys - times[0]) / step)
    np.clip(at, 0, m, out=at)
    at = at.astype(np.intp)
    # the first time at or after each key: the one before is earlier
    before = at - 1
    np.maximum(before, 0, out=before)
    right = times[before] < keys
    right |= at == 0
    after = np.minimum(at, m - 1)
    later = times[after] >= keys
    later |= at == m
    right &= later
    if not right.all():
        wrong = np.flatnonzero(~right)
        at[wrong] = np.searchsorted(times, keys[wrong], "left")
    return at


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
    """The volume on a grid of CELL_S from an origin (0, or a barrier), and
    the cells whose means it gives."""

    def __init__(self, origin_s: float, volume: float, melt_s: float,
                 cell_s: float):
        self.origin_s = origin_s
        self.cell_s = cell_s
        self.half = max(1, round(0.5 * melt_s / cell_s))   # cells in h
        # V at grid points first..: the points before the origin hold its
        # volume, so every mean is V[j + h] - V[j - h]
        self.first = -self.half
        self.volume = np.full(self.half + 1, volume)
        self.count = 1                      # grid points known from the origin
        self.next_cell = 0

    def extend(self, values: np.ndarray) -> None:
        if len(values):
            self.volume = np.concatenate((self.volume, values))
            self.count += len(values)

    def cells(self, until_cell: int, end_s: float = np.inf) -> Cells:
        """Cells next_cell..until_cell-1 whose volumes are known; none ends
        after end_s."""
        h = self.half
        last = min(until_cell, self.count - 1 - h)     # cell k needs V[k+1+h]
        if last <= self.next_cell:
            return Cells(np.empty(0), 0.0, np.empty(0))
        k0 = self.next_cell
        v = self.volume
        # the mean centred on grid points k0..last
        lo, hi = k0 - h - self.first, last + h + 1 - self.first
        mean = np.subtract(v[lo + 2 * h:hi], v[lo:hi - 2 * h])
        mean /= 2 * h * self.cell_s
        flow = np.maximum(mean[:-1], mean[1:])
        start = _grid_times(self.origin_s, k0, last, self.cell_s)
        self.next_cell = last
        keep = last - h - self.first                  # what later cells still need
        self.volume = v[keep:]
        self.first += keep
        # the last cell ends where the next one starts, on the same grid
        return Cells(start, min(self.origin_s + last * self.cell_s, end_s), flow)


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
        pieces = _pieces(event, volume)
        end_s = float(event.start_s[-1] + event.duration_s[-1])
        first = grid.count
        last = int(np.floor((end_s - grid.origin_s) / cell_s))
        if last >= first:
            times = _grid_times(grid.origin_s, first, last + 1, cell_s)
            grid.extend(volume_at(pieces, times))
        volume = pieces.end_volume_mm3
        cells = grid.cells(grid.count)
        if len(cells):
            yield cells
    yield from _close(grid, end_s, volume)


def _close(grid: _Grid, time_s: float, volume: float) -> Iterator[Cells]:
    """The cells up to time_s, nothing flowing after it (the last one ends
    with the print, or at the wait, as the moves do)."""
    last_cell = int(np.ceil((time_s - grid.origin_s) / grid.cell_s - 1e-9))
    need = last_cell + 1 + grid.half
    if need >= grid.count:
        grid.extend(np.full(need - grid.count + 1, volume))
    cells = grid.cells(last_cell, time_s)
    if len(cells):
        yield cells
