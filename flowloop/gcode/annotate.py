"""Autotemp annotations: the flow the next seconds will demand, written into
the G-code early enough for a hotend to heat before the flow arrives.

The flow planner (bulk_planner.py) turns the file into print time, and its flow
into the flow the hotend has to melt (melt.py: the mean over MELT_TIME_S,
not the spike of a move a few milliseconds long). That time is cut into
windows of `window_s`; each window's peak of it is announced by one command
placed about `lead_s` before the window in print time:

    AUTOTEMP_FLOW FLOW=<peak mm^3/s> LEAD=<s> DURATION=<s>

LEAD is the print time from the command's place in the file (the start of the
move that follows it) to the window's start, DURATION the window's length;
Klipper reads the command about READAHEAD_S before that move runs, so the
printer learns of the flow about `lead_s` ahead. FLOW is rounded up to 0.1.
Windows follow each other without gaps from the first extrusion to the end of
the print; neighbours with the same FLOW are merged (up to `lead_s` long).
Waits the file does not time (M109, G28, M600...) are barriers: a window after
one is announced after it, with a shorter LEAD.

Annotations are profile-independent: flow, not temperature. The first line of
an annotated file is a marker (MARKER_REGEX, also Moonraker's `ident` for a
file processor), so annotating twice changes nothing; the last line sums up
(peak flow, windows, print time).
"""

from __future__ import annotations

import bisect
import codecs
import contextlib
import math
import os
import re
import shutil
from dataclasses import dataclass, replace
from pathlib import Path
from typing import BinaryIO, Iterable, List, Optional, Tuple, Union

import numpy as np

from .. import files
from ..errors import FlowloopError
from .bulk_planner import Segments, planned_ahead
from .melt import MELT_TIME_S, Cells, Lines, melt_events
from .melt_window import check_melt_window
from .reference_planner import Barrier, Event, PrinterLimits

# v2: FLOW is the flow to melt (flowloop.gcode.melt: the mean over
# MELT_TIME_S), no longer the peak of any move; v1 files read as before.
FORMAT_VERSION = 2
DEFAULT_LEAD_S = 60.0
DEFAULT_WINDOW_S = 1.0
# How long before its move Klipper reads a command (toolhead BUFFER_TIME_HIGH).
READAHEAD_S = 1.0
MIN_LEAD_S = 2.0
MAX_LEAD_S = 120.0
MIN_WINDOW_S = 0.1
COMMAND = "AUTOTEMP_FLOW"
# Moonraker reads this much of a file's head when it looks for a marker.
HEADER_BYTES = 1024 * 1024
MARKER_REGEX = r"^; flowloop autotemp annotations (?P<version>v\d+)"
_MARKER = re.compile(MARKER_REGEX.encode(), re.MULTILINE)
_MARKER_TEXT = b"; flowloop autotemp annotations v"
SUMMARY_PREFIX = "; flowloop autotemp summary:"
FLOW_STEP_MM3_S = 0.1
# Commands kept before they are written out with the file between them (a
# thousand), which is read at once as far as this much further.
_INSERTS_HELD = 1024
_READ_AT_ONCE = 1 << 17


@dataclass(frozen=True)
class AnnotateSettings:
    lead_s: float = DEFAULT_LEAD_S
    window_s: float = DEFAULT_WINDOW_S
    # the time the flow is averaged over (flowloop.gcode.melt; the
    # printer's setting: flowloop.gcode.melt_window)
    melt_s: float = MELT_TIME_S

    def __post_init__(self):
        if not (isinstance(self.lead_s, (int, float))
                and MIN_LEAD_S <= self.lead_s <= MAX_LEAD_S):
            raise FlowloopError(f"lead must be {MIN_LEAD_S:g} to {MAX_LEAD_S:g} s,"
                                f" not {self.lead_s!r}")
        if not (isinstance(self.window_s, (int, float))
                and MIN_WINDOW_S <= self.window_s <= self.lead_s):
            raise FlowloopError(f"window must be {MIN_WINDOW_S:g} s to the lead"
                                f" ({self.lead_s:g} s), not {self.window_s!r}")
        try:
            check_melt_window(self.melt_s)
        except FlowloopError as e:
            raise FlowloopError(f"melt window {e}") from None

    @property
    def placement_s(self) -> float:
        """How far before its window a command sits in the file's print time."""
        return self.lead_s - READAHEAD_S


@dataclass(frozen=True)
class Summary:
    annotated: bool            # False: the file was annotated already, unchanged
    # (then the figures are its summary line's, zero without one)
    peak_flow_mm3_s: float
    windows: int
    print_time_s: float


def marker_line(settings: AnnotateSettings) -> str:
    return (f"; flowloop autotemp annotations v{FORMAT_VERSION}: {COMMAND} "
            f"FLOW=<peak mm^3/s> LEAD=<s> DURATION=<s>, lead {settings.lead_s:g} s,"
            f" window {settings.window_s:g} s, melt {settings.melt_s:g} s")


def is_annotated(head: bytes) -> bool:
    """Whether a file's head (its first HEADER_BYTES) carries the marker."""
    # the literal first (fast), then the line it is on
    at = head.find(_MARKER_TEXT)
    while at >= 0:
        if _MARKER.match(head, at):
            return True
        at = head.find(_MARKER_TEXT, at + 1)
    return False


def quantise_flow(flow_mm3_s: float) -> float:
    """Rounded up to FLOW_STEP_MM3_S: an announced peak is never below the real one."""
    steps = math.ceil(flow_mm3_s / FLOW_STEP_MM3_S - 1e-6)
    return max(0, steps) * FLOW_STEP_MM3_S


def command_line(flow_mm3_s: float, lead_s: float, duration_s: float) -> str:
    # LEAD is rounded down, DURATION up, so the window announced covers the real one.
    lead = math.floor(lead_s * 100 + 1e-6) / 100
    duration = math.ceil((duration_s + lead_s - lead) * 100 - 1e-6) / 100
    return f"{COMMAND} FLOW={flow_mm3_s:.1f} LEAD={lead:.2f} DURATION={duration:.2f}"


class _Window:
    __slots__ = ("start_s", "end_s", "flow", "insert_offset", "insert_time_s")

    def __init__(self, start_s, end_s, flow, insert_offset, insert_time_s):
        self.start_s = start_s
        self.end_s = end_s
        self.flow = flow
        self.insert_offset = insert_offset
        self.insert_time_s = insert_time_s


class _Candidates:
    """(print time, byte offset) of the lines a command may go before, in
    time order; the ones before the last useful one are dropped."""

    def __init__(self, time_s: float, offset: int):
        self.times = np.array([time_s], float)
        self.offsets = np.array([offset], np.int64)
        self.head = 0

    def reset(self, time_s: float, offset: int) -> None:
        self.__init__(time_s, offset)

    @property
    def last_offset(self) -> int:
        return int(self.offsets[-1])

    def add_many(self, times: np.ndarray, offsets: np.ndarray) -> None:
        head = self.head
        self.times = np.concatenate((self.times[head:], times))
        self.offsets = np.concatenate((self.offsets[head:], offsets))
        self.head = 0

    def first(self) -> Tuple[float, int]:
        return float(self.times[self.head]), int(self.offsets[self.head])

    def prune(self, target_s: float) -> None:
        """Keep from the last line at or before target_s (at least one)."""
        # the times never decrease: a search of all of them finds the last
        # at or before target_s, or one before head (then head stays)
        last = int(np.searchsorted(self.times, target_s, "right")) - 1
        if last > self.head:
            self.head = last

    def place(self, targets: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """prune(t), first() for each of targets (increasing), at once."""
        at = np.searchsorted(self.times, targets, "right") - 1
        np.maximum(at, self.head, out=at)
        self.head = int(at[-1])
        return self.times[at], self.offsets[at]


class Annotator:
    """Windows from planner events, each placed at a line of the file."""

    def __init__(self, settings: AnnotateSettings, src: BinaryIO, out: BinaryIO,
                 newline: bytes):
        self.settings = settings
        self.src = src
        self.out = out
        self.newline = newline
        self.copied = 0                  # bytes of src written to out
        self.block = memoryview(b"")     # of src, from byte block_start
        self.block_start = 0
        # lines a command may go before: move lines, the file's first line
        # and the line after each barrier
        self.candidates = _Candidates(0.0, 0)
        self.bin_start = 0.0
        self.bin_peak = 0.0
        self.pending: Optional[_Window] = None
        self.started = False             # a window with flow was seen
        self.windows = 0
        self.peak = 0.0
        self.end_s = 0.0
        self.last_byte = newline[-1:]    # of what was copied last
        # commands not written yet: their places and lines
        self.insert_at: List[int] = []
        self.insert_lines: List[bytes] = []

    # --- windows ------------------------------------------------------------------

    def lines(self, batch: Segments) -> None:
        """The move lines of a batch of the planner's moves: where commands
        may go (the flow comes as melt cells, flowloop.gcode.melt)."""
        offsets = batch.offset
        if not len(offsets):
            return
        new_line = np.empty(len(offsets), bool)
        new_line[0] = offsets[0] != self.candidates.last_offset
        new_line[1:] = offsets[1:] != offsets[:-1]
        self.candidates.add_many(batch.start_s[new_line], offsets[new_line])
        self.end_s = max(self.end_s, float(batch.start_s[-1] + batch.duration_s[-1]))

    def _advance_to(self, time_s: float) -> None:
        """Close every window that ends by time_s (the gap carries no flow)."""
        window = self.settings.window_s
        if time_s < self.bin_start + window:
            return
        self._close_bin(self.bin_start + window)
        if time_s >= self.bin_start + window:
            # one flowless window over the whole gap, on the grid
            steps = math.floor((time_s - self.bin_start) / window)
            self._close_bin(self.bin_start + steps * window)

    def _close_bin(self, end_s: float) -> None:
        start, flow = self.bin_start, quantise_flow(self.bin_peak)
        self.bin_start, self.bin_peak = end_s, 0.0
        if end_s <= start or (flow == 0.0 and not self.started):
            # no window to announce; no later one goes before this point
            self._prune(end_s - self.settings.placement_s)
            return
        self.started = True
        p = self.pending
        if p is not None and p.flow == flow and p.end_s == start \
                and end_s - p.start_s <= self.settings.lead_s:
            p.end_s = end_s
            return
        self._finish_pending()
        offset, time_s = self._place(start)
        self.pending = _Window(start, end_s, flow, offset, time_s)

    def cells(self, cells: Cells) -> None:
        """Consecutive cells of constant flow (the flow to melt), at once: the
        peak of each window they overlap, then the windows closed in order."""
        flow = cells.flow_mm3_s
        if not len(flow):
            return
        self._advance_to(cells.begin_s)
        window = self.settings.window_s
        last_end = cells.end_s
        count = int((last_end - self.bin_start) / window) + 3
        edges = np.cumsum(np.concatenate(([self.bin_start], np.full(count, window))))
        while edges[-1] < last_end:     # never short of the last cell
            more = np.cumsum(np.concatenate(([edges[-1]], np.full(count, window))))
            edges = np.concatenate((edges, more[1:]))
        # the window last_end is in (its end included) stays open
        final = max(int(np.searchsorted(edges, last_end, "left")) - 1, 0)
        edges = edges[:final + 2]
        # window m holds the cells that overlap it: from the first that ends
        # after its start to the last that starts before its end
        # (cell k ends where k + 1 starts, the last at last_end)
        lo = cells.search(edges[:-1], "right")
        lo -= lo > 0                    # among the starts but the first
        lo += edges[:-1] >= last_end
        hi = cells.search(edges[1:], "left")
        bounds = np.stack((lo, np.maximum(hi, lo)), axis=1).ravel()
        peaks = np.maximum.reduceat(np.append(flow, 0.0), bounds)[::2]
        raw = np.where(hi > lo, peaks, 0.0)
        top = float(raw.max())
        if top > self.peak:
            self.peak = top
        raw[0] = max(raw[0], self.bin_peak)
        self._close_bins(edges[:final + 1], raw[:final])
        self.bin_start, self.bin_peak = float(edges[final]), float(raw[final])

    def _close_bins(self, edges: np.ndarray, peaks: np.ndarray) -> None:
        """_close_bin for bins edges[k]..edges[k+1] with raw peaks[k], in
        order, at once: the bins are cut into windows (a run of equal flows
        is one window, or several where it outlasts the lead), the windows
        placed with one search and all but the last written out."""
        count = len(peaks)
        if not count:
            return
        steps = np.ceil(peaks / FLOW_STEP_MM3_S - 1e-6)
        # quantise_flow's values (+ 0.0: never -0.0)
        flows = np.maximum(steps, 0.0) * FLOW_STEP_MM3_S + 0.0
        # edges rise by window_s (>= MIN_WINDOW_S) from bin_start: always
        # apart, no bin of no length
        lead = self.settings.lead_s
        edge_list = edges.tolist()
        k = self._skip_lead_in(flows, edge_list, count)
        self.bin_start, self.bin_peak = edge_list[count], 0.0
        if k == count:
            return
        self.started = True
        # runs of equal flow from bin k: run_start[r]..run_start[r + 1]
        change = np.flatnonzero(flows[k + 1:] != flows[k:-1]) + (k + 1)
        run_start = np.concatenate(([k], change, [count]))
        flow_list = flows.tolist()
        # the bins where a new window starts
        new: List[int] = []
        p = self.pending
        first_end = int(run_start[1])
        if p is not None and p.flow == flow_list[k] and p.end_s == edge_list[k]:
            # the pending window takes the first bins of the first run
            stop = self._absorb(edge_list, k, first_end, p.start_s)
            p.end_s = edge_list[stop]
        else:
            stop = k
        while stop < first_end:
            new.append(stop)
            stop = self._absorb(edge_list, stop + 1, first_end, edge_list[stop])
        starts = run_start[1:-1]
        if starts.size:
            ends = run_start[2:]
            long_runs = np.flatnonzero(edges[ends] - edges[starts] > lead)
            if not long_runs.size:
                new.extend(starts.tolist())
            else:
                at = 0
                start_list, end_list = starts.tolist(), ends.tolist()
                for r in long_runs.tolist():
                    new.extend(start_list[at:r])
                    stop, end = start_list[r], end_list[r]
                    while stop < end:
                        new.append(stop)
                        stop = self._absorb(edge_list, stop + 1, end, edge_list[stop])
                    at = r + 1
                new.extend(start_list[at:])
        if not new:
            return
        first = np.array(new)
        start_s = edges[first]
        end_s = edges[np.append(first[1:], count)]
        insert_s, insert_at = self.candidates.place(start_s - self.settings.placement_s)
        self._finish_pending()
        self._write_windows(start_s[:-1], end_s[:-1], flows[first[:-1]],
                            insert_s[:-1], insert_at[:-1])
        self.pending = _Window(float(start_s[-1]), float(end_s[-1]),
                               flow_list[new[-1]], int(insert_at[-1]),
                               float(insert_s[-1]))

    def _absorb(self, edge_list: List[float], k: int, stop: int,
                start_s: float) -> int:
        """The first of bins k..stop-1 a window from start_s cannot take
        (it takes bins while it stays within the lead; stop: all)."""
        lead = self.settings.lead_s
        if edge_list[stop] - start_s <= lead:
            return stop
        lo, hi = k, stop
        while lo < hi:
            mid = (lo + hi) // 2
            if edge_list[mid + 1] - start_s <= lead:
                lo = mid + 1
            else:
                hi = mid
        return lo

    def _skip_lead_in(self, flows: np.ndarray, edge_list: list, count: int) -> int:
        """Before the first flow nothing is announced: the first bin to
        close (count when none flows), the source pruned up to it."""
        if self.started:
            return 0
        nonzero = np.flatnonzero(flows != 0.0)
        lead_in = int(nonzero[0]) if nonzero.size else count
        if lead_in:
            self._prune(edge_list[lead_in] - self.settings.placement_s)
        return lead_in

    def _write_windows(self, start_s, end_s, flow, insert_s, insert_at) -> None:
        """_finish_pending for windows that are over, given as arrays."""
        if not len(start_s):
            return
        start = np.maximum(start_s, insert_s)
        keep = end_s > start
        if not keep.all():
            start, end_s, flow = start[keep], end_s[keep], flow[keep]
            insert_s, insert_at = insert_s[keep], insert_at[keep]
        lead_s = start - insert_s
        duration_s = end_s - start
        # command_line's rounding
        lead = np.floor(lead_s * 100 + 1e-6) / 100
        duration = np.ceil((duration_s + lead_s - lead) * 100 - 1e-6) / 100
        numbers = zip(flow.tolist(), lead.tolist(), duration.tolist())
        self.windows += len(start)
        if type(self).emit is Annotator.emit:
            # emit's work for them all (command_line's text, as bytes)
            line = (f"{COMMAND} FLOW=%.1f LEAD=%.2f DURATION=%.2f".encode()
                    + self.newline)
            self.insert_at += insert_at.tolist()
            self.insert_lines += [line % n for n in numbers]
            if len(self.insert_at) >= _INSERTS_HELD:
                self._write_inserts()
            return
        for offset, time_s, (f, ld, d) in zip(insert_at.tolist(),
                                              insert_s.tolist(), numbers):
            self.emit(offset, time_s,
                      f"{COMMAND} FLOW={f:.1f} LEAD={ld:.2f} DURATION={d:.2f}")

    def _place(self, window_start_s: float) -> Tuple[int, float]:
        """The last line at least placement_s before the window (or the first
        one left, just after a barrier or at the start)."""
        self._prune(window_start_s - self.settings.placement_s)
        time_s, offset = self.candidates.first()
        return offset, time_s

    def _prune(self, target_s: float) -> None:
        """Forget move lines before the last one at or before target_s."""
        self.candidates.prune(target_s)

    def barrier(self, barrier: Barrier) -> None:
        self._advance_to(barrier.time_s)
        if barrier.time_s > self.bin_start:
            self._close_bin(barrier.time_s)
        self._finish_pending()
        self.candidates.reset(barrier.time_s, barrier.offset)
        self.bin_start, self.bin_peak = barrier.time_s, 0.0

    def finish(self) -> None:
        self._advance_to(self.end_s)
        if self.end_s > self.bin_start:
            self._close_bin(self.end_s)
        self._finish_pending()

    # --- output -------------------------------------------------------------------

    def _finish_pending(self) -> None:
        p = self.pending
        if p is None:
            return
        self.pending = None
        start = max(p.start_s, p.insert_time_s)
        if p.end_s <= start:
            return      # over before any line could announce it (a wait, a dwell)
        line = command_line(p.flow, start - p.insert_time_s, p.end_s - start)
        self.emit(p.insert_offset, p.insert_time_s, line)
        self.windows += 1

    def emit(self, offset: int, time_s: float, line: str) -> None:
        """Write a command before the line at byte offset (print time time_s)."""
        # kept, then written a thousand at a time (_write_inserts)
        self.insert_at.append(offset)
        self.insert_lines.append(line.encode() + self.newline)
        if len(self.insert_at) >= _INSERTS_HELD:
            self._write_inserts()

    def _write_inserts(self) -> None:
        """Copy the source up to each command kept, then the command: what
        copy_to and a write for each do, a run of them at a time."""
        offsets, lines = self.insert_at, self.insert_lines
        self.insert_at, self.insert_lines = [], []
        i = 0
        if self.copied <= offsets[0] \
                and all(a <= b for a, b in zip(offsets, offsets[1:])):
            # (a file's commands go in order) the source up to the places
            # of a run, read at once and cut at them
            while i < len(offsets):
                end = self.block_start + len(self.block)
                k = bisect.bisect_right(offsets, end + _READ_AT_ONCE, i)
                if k == i or not self._write_run(offsets[i:k], lines[i:k]):
                    break
                i = k
        if i < len(offsets):
            self._write_one_by_one(offsets[i:], lines[i:])

    def _write_run(self, offsets: List[int], lines: List[bytes]) -> bool:
        """_write_inserts for places in order from the one copied to at
        most _READ_AT_ONCE past the block read; False (and nothing written)
        if the file ends before the last."""
        block, block_start, copied = self.block, self.block_start, self.copied
        last = offsets[-1]
        if last > block_start + len(block):
            more = self.src.read(last - block_start - len(block))
            if copied < block_start + len(block):
                more = bytes(block[copied - block_start:]) + more
            block = self.block = memoryview(more)
            block_start = self.block_start = copied
            if last > block_start + len(block):
                return False
        places = [a - block_start for a in offsets]
        parts: List[Union[bytes, memoryview]] = [b""] * (2 * len(places))
        parts[::2] = [block[a:b] for a, b in
                      zip([copied - block_start] + places, places)]
        parts[1::2] = lines
        if last > copied:
            self.last_byte = block[places[-1] - 1:places[-1]]
        self.copied = last
        self.out.write(b"".join(parts))
        return True

    def _write_one_by_one(self, offsets: List[int], lines: List[bytes]) -> None:
        parts: List[Union[bytes, memoryview]] = []
        append = parts.append
        block, block_start, copied = self.block, self.block_start, self.copied
        end = block_start + len(block)
        piece = None                    # the last one copied
        for offset, line in zip(offsets, lines):
            if copied < offset <= end:   # within the block read
                piece = block[copied - block_start:offset - block_start]
                append(piece)
                copied = offset
            while copied < offset:
                at = copied - block_start
                if at >= len(block):
                    block_start += len(block)
                    block = memoryview(self.src.read(1 << 20))
                    end = block_start + len(block)
                    if not block:
                        break
                    at = 0
                stop = min(len(block), offset - block_start)
                piece = block[at:stop]
                append(piece)
                copied += stop - at
            append(line)
        if piece is not None:
            self.last_byte = piece[-1:]
        self.block, self.block_start, self.copied = block, block_start, copied
        self.out.write(b"".join(parts))

    def drop_byte_order_mark(self) -> None:
        """A UTF-8 byte-order mark is left out: the marker must be the file's
        first bytes (is_annotated, Moonraker's `ident`), and no command goes
        before the first line after it."""
        head = self.src.read(len(codecs.BOM_UTF8))
        if head == codecs.BOM_UTF8:
            self.copied = self.block_start = len(head)
            self.candidates = _Candidates(0.0, len(head))
        elif self.src.seekable():
            self.src.seek(-len(head), os.SEEK_CUR)   # read in whole blocks, as before
        else:
            self.block = memoryview(head)

    def copy_to(self, offset: Optional[int]) -> None:
        """Copy the source up to byte offset (None: to its end), read in
        blocks of a MB."""
        if self.insert_at:
            self._write_inserts()
        while offset is None or self.copied < offset:
            at = self.copied - self.block_start
            if at >= len(self.block):
                self.block_start += len(self.block)
                self.block = memoryview(self.src.read(1 << 20))
                if not self.block:
                    break
                at = 0
            stop = len(self.block) if offset is None \
                else min(len(self.block), offset - self.block_start)
            if stop > at:
                self.out.write(self.block[at:stop])
                self.copied += stop - at
                self.last_byte = self.block[stop - 1:stop]


def feed(annotator: Annotator, events: Iterable[Union[Event, Segments]]) -> None:
    """The planner's events into an annotator, as the flow to melt
    (flowloop.gcode.melt), then its last windows closed."""
    for event in melt_events(events, annotator.settings.melt_s):
        if isinstance(event, Barrier):
            annotator.barrier(event)
        elif isinstance(event, Lines):
            annotator.lines(event.moves)
        else:
            annotator.cells(event)
    annotator.finish()


def annotate_stream(events: Iterable[Union[Event, Segments]], src: BinaryIO,
                    out: BinaryIO,
                    settings: AnnotateSettings = AnnotateSettings(),
                    newline: bytes = b"\n") -> Summary:
    """Write src to out with annotations; events are src's planner events.

    src is read from its start as the events reach further into it.
    """
    a = Annotator(settings, src, out, newline)
    a.drop_byte_order_mark()
    out.write(marker_line(settings).encode() + newline)
    feed(a, events)
    a.copy_to(None)
    summary = Summary(True, quantise_flow(a.peak), a.windows, a.end_s)
    if a.last_byte != newline[-1:]:
        out.write(newline)
    out.write((f"{SUMMARY_PREFIX} peak_flow_mm3_s={summary.peak_flow_mm3_s:.1f}"
               f" windows={summary.windows} print_time_s={summary.print_time_s:.1f}"
               ).encode() + newline)
    return summary


_SUMMARY = re.compile(
    re.escape(SUMMARY_PREFIX).encode() + rb" peak_flow_mm3_s=(?P<peak>[0-9.]+)"
    rb" windows=(?P<windows>\d+) print_time_s=(?P<time>[0-9.]+)\s*$")


def read_summary(tail: bytes) -> Optional[Summary]:
    """The summary an annotated file ends with (give its last bytes), if any."""
    lines = tail.rstrip().splitlines()
    match = _SUMMARY.match(lines[-1]) if lines else None
    if match is None:
        return None
    return Summary(True, float(match["peak"]), int(match["windows"]),
                   float(match["time"]))


def newline_of(path: Path) -> bytes:
    with open(path, "rb") as f:
        first = f.readline(1 << 16)
    return b"\r\n" if first.endswith(b"\r\n") else b"\n"


def annotate_file(src: Path, dst: Optional[Path] = None,
                  limits: Optional[PrinterLimits] = None,
                  settings: AnnotateSettings = AnnotateSettings()) -> Summary:
    """Annotate src into dst (None: in place). The output appears whole or not
    at all (a temporary file beside it, then a rename)."""
    limits = limits if limits is not None else PrinterLimits()
    src, dst = Path(src), Path(dst if dst is not None else src)
    if dst.is_symlink():
        # write where the link points, as Moonraker's own processors do
        dst = Path(os.path.realpath(dst))
    try:
        with open(src, "rb") as f:
            head = f.read(HEADER_BYTES)
    except OSError as e:
        raise FlowloopError(f"{src}: cannot read: {e.strerror}") from None
    if is_annotated(head):
        if dst.resolve() != src.resolve():
            files.replace_atomically(dst, lambda out: _copy(src, out), src)
        with open(src, "rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - 4096))
            known = read_summary(f.read())
        return replace(known, annotated=False) if known else Summary(False, 0.0, 0, 0.0)
    newline = newline_of(src)
    summary = None

    def write(out: BinaryIO) -> None:
        nonlocal summary
        # the planner runs ahead in a process (or a thread) of its own
        # (flowloop.gcode.ahead), stopped before the files close, whatever happens
        with open(src, "rb") as copy, \
                contextlib.closing(planned_ahead(src, limits)) as events:
            try:
                summary = annotate_stream(events, copy, out, settings, newline)
            except FlowloopError as e:
                raise FlowloopError(f"{src}: {e}") from None
    files.replace_atomically(dst, write, src)
    assert summary is not None
    return summary


def _copy(src: Path, out: BinaryIO) -> None:
    with open(src, "rb") as f:
        shutil.copyfileobj(f, out, 1 << 20)


