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
constant slope, each grid point's volume is its piece's polynomial in the
point's steps from the piece's first one (the coefficients gathered by each
point's piece, found by a running sum, not np.repeat, which copies each
point on its own), and each centred mean is the difference of two volumes.
The cells' start times are not stored: they are grid points, computed when
asked for (Cells.start_s, Cells.search).
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


class Cells:
    """Consecutive cells of the flow to melt: cell k runs from start_s[k] to
    the next cell's start (the last one to end_s) at flow_mm3_s[k]. They
    are grid points first.. of a grid from origin_s (grid_time); the start
    times are computed when asked for, and search() finds places among them
    without them (a long print has millions)."""
    __slots__ = ("origin_s", "first", "cell_s", "end_s", "flow_mm3_s")

    def __init__(self, origin_s: float, first: int, cell_s: float, end_s: float,
                 flow_mm3_s: np.ndarray):
        self.origin_s = origin_s
        self.first = first
        self.cell_s = cell_s
        self.end_s = end_s
        self.flow_mm3_s = flow_mm3_s

    def __len__(self) -> int:
        return len(self.flow_mm3_s)

    @property
    def begin_s(self) -> float:
        """The first cell's start."""
        return float(grid_time(self.origin_s, self.first, self.cell_s))

    @property
    def start_s(self) -> np.ndarray:
        return grid_time(self.origin_s, np.arange(self.first, self.first + len(self)),
                         self.cell_s)

    def search(self, keys: np.ndarray, side: str = "left") -> np.ndarray:
        """np.searchsorted(self.start_s, keys, side)."""
        return grid_search(keys, self.origin_s, self.first,
                           self.first + len(self), self.cell_s, side)


MeltEvent = Union[Lines, Cells, Barrier]


class _Pieces(NamedTuple):
    """A batch's flow as pieces of constant slope (each move's accel, cruise
    and decel), with the plastic volume left through the nozzle at each start.
    bounds_s: each move's four times (start, accel's end, cruise's end, end),
    a row each: a piece ends at the very float its move's next one starts."""
    bounds_s: np.ndarray
    start_s: np.ndarray
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
    at_start = np.stack((f0, fc, fc), axis=1).ravel()
    accel_end = start + accel
    cruise_end = accel_end + cruise
    bounds = np.stack((start, accel_end, cruise_end, cruise_end + decel), axis=1)
    starts = bounds[:, :3].ravel()
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
    return _Pieces(bounds, starts, before, at_start, slope,
                   volume_before + float(total[-1]))


def grid_time(origin_s: float, k, cell_s: float):
    """The time of grid point k (an index or an array of them): k * cell_s
    from origin_s, rounded as every grid time here is."""
    return np.multiply(k, cell_s, dtype=float) + origin_s


def grid_search(keys: np.ndarray, origin_s: float, first: int, stop: int,
                cell_s: float, side: str = "left") -> np.ndarray:
    """np.searchsorted(grid_time(origin_s, range(first, stop), cell_s), keys,
    side) without the grid: each place computed, then moved while a
    neighbour shows it wrong (rounding moves it by one at most)."""
    n = stop - first
    at = np.ceil((np.asarray(keys, float) - origin_s) / cell_s) - first
    np.clip(at, 0, n, out=at)
    at = at.astype(np.intp)
    right = side == "right"
    for _ in range(4):
        # too far: the point before is not below (left) / above (right) the key
        before = grid_time(origin_s, at - 1 + first, cell_s)
        back = (before > keys) if right else (before >= keys)
        back &= at > 0
        # not far enough: the point at is below (left) / not above (right)
        here = grid_time(origin_s, at + first, cell_s)
        on = (here <= keys) if right else (here < keys)
        on &= at < n
        if not (back.any() or on.any()):
            return at
        at -= back
        at += on
    raise AssertionError("grid_search did not settle")


def volume_on_grid(pieces: _Pieces, origin_s: float, first: int, stop: int,
                   cell_s: float) -> np.ndarray:
    """Plastic (mm^3) left through the nozzle at grid points first..stop-1
    (grid_time; one before the batch counts as at its start, one after it
    or between two moves as at the last move's end)."""
    n = stop - first
    start = pieces.start_s
    count = len(start)
    # segments of the grid: before the batch, then each piece and the gap
    # after it (none, mostly: a move starts where the last one ends);
    # the grid points from a piece's start on are in its segment, from its
    # end on in the gap's. Within a move a piece ends where the next
    # starts: each move's four bounds are searched once, then spread out
    # (start, accel end twice, cruise end twice, end).
    found = grid_search(pieces.bounds_s.ravel(), origin_s, first, stop, cell_s)
    np.maximum.accumulate(found, out=found)
    seg_first = np.empty(2 * count + 1, np.intp)
    seg_first[0] = 0
    seg_first[1:].reshape(-1, 6)[:] = found.reshape(-1, 4)[:, _SPREAD]
    counts = np.diff(np.append(seg_first, n))
    # each segment's volume in its own grid steps j: A + j * (B + C * j)
    # (a piece's volume + u * (flow + slope / 2 * u) at u = e + j * cell_s,
    # e from the piece's start to its first grid point; a gap's is flat)
    vol, flow = pieces.volume_mm3, pieces.flow_mm3_s
    half_slope = 0.5 * pieces.slope_mm3_s2
    e = grid_time(origin_s, seg_first[1::2] + first, cell_s) - start
    a = np.empty(2 * count + 1)
    b = np.zeros(2 * count + 1)
    c = np.zeros(2 * count + 1)
    a[0] = vol[0]
    a[1::2] = vol + e * (flow + half_slope * e)
    b[1::2] = cell_s * (flow + 2.0 * half_slope * e)
    c[1::2] = half_slope * (cell_s * cell_s)
    a[2:-1:2] = vol[1:]
    a[-1] = pieces.end_volume_mm3
    seg = _segment_of_each(seg_first, counts, n)
    j = np.arange(n)
    j -= seg_first.take(seg)
    j = j.astype(float)
    out = c.take(seg)
    out *= j
    out += b.take(seg)
    out *= j
    out += a.take(seg)
    return out


# a move's four bounds as its three pieces' starts and ends
_SPREAD = np.array([0, 1, 1, 2, 2, 3])


def _segment_of_each(seg_first: np.ndarray, counts: np.ndarray, n: int
                     ) -> np.ndarray:
    """np.repeat(np.arange(len(counts)), counts) for segments in order that
    hold n points from seg_first on: each segment's index added where it
    starts, less the last one's, then summed up (np.repeat copies each
    point on its own, five times slower on a batch of short moves)."""
    held = np.flatnonzero(counts)
    seg = np.zeros(n, np.intp)
    if not len(held):
        return seg
    seg[0] = held[0]
    seg[seg_first[held[1:]]] = np.diff(held)
    np.cumsum(seg, out=seg)
    return seg


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
            return Cells(self.origin_s, self.next_cell, self.cell_s, 0.0, np.empty(0))
        k0 = self.next_cell
        v = self.volume
        # the mean centred on grid points k0..last
        lo, hi = k0 - h - self.first, last + h + 1 - self.first
        mean = np.subtract(v[lo + 2 * h:hi], v[lo:hi - 2 * h])
        mean /= 2 * h * self.cell_s
        flow = np.maximum(mean[:-1], mean[1:])
        self.next_cell = last
        keep = last - h - self.first                  # what later cells still need
        self.volume = v[keep:]
        self.first += keep
        # the last cell ends where the next one starts, on the same grid
        return Cells(self.origin_s, k0, self.cell_s,
                     min(grid_time(self.origin_s, last, self.cell_s), end_s), flow)


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
            grid.extend(volume_on_grid(pieces, grid.origin_s, first, last + 1,
                                       cell_s))
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
