"""The flow planner flowloop runs: the reference's timeline, in bulk numpy.

flowloop.gcode.reference_planner is the reference (checked against
Klipper's own toolhead code, one line at a time); this module is what
`flowloop annotate`, the bake and Moonraker's processor run: the same
events bit for bit, about twenty times faster. It uses the reference only
through its public surface (Planner's queue_move/flush_queue seams, Move,
HANDLED_COMMANDS and the timeline's types):

- the file is read in chunks of whole lines; the lines slicers write most
  (`G0`/`G1` with X Y Z E F words, `G92` with X Y Z E, `G10`/`G11`, `G2`/`G3`
  with I J K, comments, blank lines and M-commands Klipper's motion ignores)
  are tokenised and parsed with numpy for the whole chunk, and gcode_move's
  state (positions, G92 offsets, the feed rate) follows them with prefix
  sums; an arc becomes its segments' G1 rows (reference_planner.arc_segments,
  from the position the rows before it leave, followed row by row and
  checked once the run's positions are known); every other line goes to
  the reference Planner, which holds the state the two share;
- moves are built, limited and joined (toolhead.Move, calc_junction) as
  arrays; the lookahead's recurrences on squared speeds
  (x[i] = min(a[i], x[i-1] + d[i])) are solved in closed form with one
  minimum.accumulate and then relaxed to the exact sequential float result,
  so a tie decides as it does in Klipper (the events are bit for bit the
  reference's: tests/unit/test_planner_fast.py);
- the queue is flushed as Klipper's lazy flush would flush it at the end of
  each chunk: only moves whose speeds no later move can change leave it
  (a lazy flush is final: later moves never change what it flushed), the
  rest waits for the next chunk. Memory stays a chunk plus that queue.
"""

from __future__ import annotations

import itertools
import os
import pickle
import struct
from pathlib import Path
from typing import BinaryIO, Iterator, List, NamedTuple, Optional, Union

import numpy as np

from .ahead import ahead_of, read_exactly, read_into
from .reference_planner import (
    BARRIER_COMMANDS,
    HANDLED_COMMANDS,
    MAX_ABS_VALUE,
    Barrier,
    Event,
    Move,
    Planner,
    PrinterLimits,
    Segment,
    arc_segments,
    gcode_position,
)

# half a MB: a chunk's arrays stay within a core's L2 cache (2 MB here);
# 1 MB chunks planned the 25 MB bench file 15 % slower
CHUNK_BYTES = 1 << 19
# From this size on a file is planned in a process of its own
# (planned_ahead): whole `flowloop annotate` processes, medians of 20 pairs,
# process against thread, took 1.09x on a 1 MB file (the fork, the pidfd and
# the child's end cost some 3 ms, alone on a 22 kB file), 1.02x on 2 MB,
# 1.00x on 4 MB, 0.97x on 8 MB and 0.88-0.96x on the 25 MB bench file.
PROCESS_FROM_BYTES = 8 * CHUNK_BYTES
# Longest number word the bulk parser reads ("X-123.45678" is 11); longer ones
# go to the reference planner.
_WORD_BYTES = 24
# M-commands the reference planner acts on or waits for: such lines go to
# it, any other plain M<digits> line is ignored, as it ignores them.
_M_HANDLED = frozenset(name.encode() for name in
                       (*HANDLED_COMMANDS, *BARRIER_COMMANDS)
                       if name.startswith("M"))
# what a line is; every kind from _MOVE on has words, from _G10 on is a
# firmware retraction (_ARC_CW and _ARC_CCW: G2 and G3)
_OTHER, _SKIP, _MOVE, _G92, _ARC_CW, _ARC_CCW, _G10, _G11 = range(8)
# the words read: X Y Z E F (rows 0-4 of a chunk's values), and an arc's
# offsets to its centre, I J K (rows 5-7)
_AXES = b"XYZEFIJK"
_LETTER = np.full(256, -1, np.int8)
for _i, _c in enumerate(_AXES):
    _LETTER[_c] = _i


class Segments(NamedTuple):
    """Consecutive reference_planner.Segment records as arrays, field by field."""
    start_s: np.ndarray
    duration_s: np.ndarray
    flow_mm3_s: np.ndarray
    accel_s: np.ndarray
    decel_s: np.ndarray
    start_flow_mm3_s: np.ndarray
    end_flow_mm3_s: np.ndarray
    speed_mm_s: np.ndarray
    distance_mm: np.ndarray
    filament_mm: np.ndarray
    offset: np.ndarray

    def __len__(self) -> int:        # NamedTuple's would count the fields
        return len(self.start_s)

    def records(self) -> Iterator[Segment]:
        columns = [c.tolist() for c in self]
        for row in zip(*columns):
            yield Segment._make(row)


Batch = Union[Segments, Barrier]


def min_plus(a: np.ndarray, add: np.ndarray, x0: float) -> np.ndarray:
    """x[i] = min(a[i], x[i-1] + add[i]) with x[-1] = x0, equal to the
    sequential loop in float64 (the lookahead's speed recurrences).

    Closed form x[i] = P[i] + min(x0, min_{k<=i} a[k] - P[k]) (P the prefix
    sum of add), which rounds differently, then relaxed: an element is
    recomputed from its predecessor until none changes, which is the
    sequential result (a few rounds: chains of moves accelerating from one
    another are short)."""
    n = len(a)
    if n == 0:
        return a.astype(float)
    prefix = np.cumsum(add)
    x = a - prefix
    np.minimum.accumulate(x, out=x)
    np.minimum(x, x0, out=x)
    x += prefix
    # one sequential step from x: min(a, x[i-1] + add[i])
    new = np.empty(n)
    new[0] = x0 + add[0]
    np.add(x[:-1], add[1:], out=new[1:])
    np.minimum(a, new, out=new)
    changed = np.flatnonzero(new != x)
    x = new
    while changed.size:
        idx = changed + 1
        idx = idx[idx < n]
        if not idx.size:
            break
        cand = np.minimum(a[idx], x[idx - 1] + add[idx])
        differs = cand != x[idx]
        x[idx] = cand
        changed = idx[differs]
    return x


class _Queue(NamedTuple):
    """Moves as arrays: what toolhead.Move holds after calc_junction."""
    ax: np.ndarray              # axes_r x, y, z, e
    ay: np.ndarray
    az: np.ndarray
    ae: np.ndarray
    move_d: np.ndarray
    accel: np.ndarray
    junction_deviation: np.ndarray
    max_cruise_v2: np.ndarray
    delta_v2: np.ndarray
    mcr_delta_v2: np.ndarray
    kinematic: np.ndarray
    filament_mm: np.ndarray
    flow_per_mm: np.ndarray
    offset: np.ndarray
    max_start_v2: np.ndarray    # NaN until joined to the move before
    max_mcr_start_v2: np.ndarray


_QUEUE_FIELDS = _Queue._fields
_MOVE_ATTRS = {"ax": None, "ay": None, "az": None, "ae": None,
               "move_d": "move_d", "accel": "accel",
               "junction_deviation": "junction_deviation",
               "max_cruise_v2": "max_cruise_v2", "delta_v2": "delta_v2",
               "mcr_delta_v2": "mcr_delta_v2", "kinematic": "is_kinematic_move",
               "filament_mm": "filament_mm", "flow_per_mm": "flow_per_mm",
               "offset": "offset"}


def _queue_of_moves(moves: List[Move]) -> _Queue:
    cols = {}
    for name, attr in _MOVE_ATTRS.items():
        if attr is None:
            axis = "xyze".index(name[1])
            cols[name] = np.array([m.axes_r[axis] for m in moves], float)
        else:
            dtype = bool if name == "kinematic" else (
                np.int64 if name == "offset" else float)
            cols[name] = np.array([getattr(m, attr) for m in moves], dtype)
    cols["max_start_v2"] = np.full(len(moves), np.nan)
    cols["max_mcr_start_v2"] = np.full(len(moves), np.nan)
    return _Queue(**cols)


def _concat(parts: List[_Queue]) -> _Queue:
    if len(parts) == 1:
        return parts[0]
    return _Queue(*(np.concatenate([getattr(p, f) for p in parts])
                    for f in _QUEUE_FIELDS))


def _take(q: _Queue, sl) -> _Queue:
    return _Queue(*(c[sl] for c in q))


class _StatePlanner(Planner):
    """The reference planner holding the state; its moves and flushes go to
    the bulk lookahead."""

    def __init__(self, limits: PrinterLimits, owner: BulkPlanner):
        super().__init__(limits)
        self.owner = owner

    def queue_move(self, m: Move) -> None:
        self.owner.scalar_moves.append(m)

    def flush_queue(self) -> None:
        self.owner.flush(lazy=False)


class BulkPlanner:
    """reference_planner.Planner's timeline from whole chunks of lines."""

    def __init__(self, limits: Optional[PrinterLimits] = None):
        limits = limits if limits is not None else PrinterLimits()
        self.limits = limits
        self.state = _StatePlanner(limits, self)
        self.out: List[Batch] = []
        self.parts: List[_Queue] = []           # new moves, not yet joined
        self.scalar_moves: List[Move] = []
        self.queue: Optional[_Queue] = None     # joined, not yet flushed
        self.lines = 0                          # lines read so far
        self._size = 0                          # of the chunk planned

    # --- reading ------------------------------------------------------------
    def chunk(self, data: bytes, offset: int,
              size: Optional[int] = None) -> List[Batch]:
        """Plan whole lines (data ends at a line end, or the file's end) that
        start at byte offset of the file; returns the batches completed.
        With size, the lines are data[:size] and at least _WORD_BYTES bytes
        follow them (read, not copied, past the lines' end)."""
        if data and size != 0:
            self._plan_chunk(data, offset, size)
        self.flush(lazy=True)
        out, self.out = self.out, []
        return out

    def finish(self) -> List[Batch]:
        self.flush(lazy=False)
        out, self.out = self.out, []
        return out

    def _plan_chunk(self, data: bytes, offset: int,
                    size: Optional[int] = None) -> None:
        if size is None:
            size = len(data)
            buf = np.frombuffer(data + b"\0" * _WORD_BYTES, np.uint8)
        else:
            buf = np.frombuffer(data, np.uint8)
        self._size = size
        # the bytes that end a word, at once: newline, space, ';', CR
        body = buf[:size]
        sep = np.flatnonzero((body == 10) | (body == 32) | (body == 59) | (body == 13))
        sep_byte = buf[sep]
        nl = sep[sep_byte == 10]
        starts = np.concatenate(([0], nl + 1))
        ends = np.concatenate((nl, [size]))
        if starts[-1] == size:          # data ends with its newline
            starts, ends = starts[:-1], ends[:-1]
        kinds = self._kinds(data, buf, starts, ends)
        words = self._words(buf, size, starts, ends, kinds, sep, sep_byte)
        first_line = self.lines
        self.lines += len(starts)
        other = np.flatnonzero(kinds == _OTHER)
        run_start = 0
        for stop in list(other) + [len(starts)]:
            if stop > run_start:
                self._run(run_start, stop, kinds, words, starts, ends, data,
                          offset, first_line)
            if stop < len(starts):
                self._scalar_line(data, starts, ends, stop, offset, first_line)
            run_start = stop + 1

    def _kinds(self, data, buf, starts, ends) -> np.ndarray:
        """What each line is: a move, a G92, nothing to plan, or other."""
        b0, b1, b2, b3 = (buf[starts + k] for k in range(4))
        length = ends - starts
        kinds = np.full(len(starts), _OTHER, np.int8)
        kinds[(length == 0) | (b0 == 59) | ((length == 1) & (b0 == 13))] = _SKIP
        move = (b0 == 71) & ((b1 == 48) | (b1 == 49)) & (b2 == 32)
        kinds[move] = _MOVE
        kinds[(b0 == 71) & (b1 == 57) & (b2 == 50) & (b3 == 32)] = _G92
        # arcs (gcode_arcs): expanded into their segments in the run
        kinds[(b0 == 71) & (b1 == 50) & (b2 == 32)] = _ARC_CW
        kinds[(b0 == 71) & (b1 == 51) & (b2 == 32)] = _ARC_CCW
        # firmware retraction: a bare G10 / G11 (with anything after it
        # Klipper may read another command: those go the slow way)
        retraction = np.flatnonzero((b0 == 71) & (b1 == 49)
                                    & ((b2 == 48) | (b2 == 49)))
        for i in retraction.tolist():
            code = data[starts[i]:ends[i]].split(b";", 1)[0].strip()
            if code == b"G10":
                kinds[i] = _G10
            elif code == b"G11":
                kinds[i] = _G11
        m_lines = np.flatnonzero(b0 == 77)
        for i in m_lines.tolist():      # few: M-commands are not moves
            head = data[starts[i]:ends[i]].split(b";", 1)[0].split()
            cmd = head[0] if head else b""
            if cmd[1:].isdigit() and cmd not in _M_HANDLED:
                kinds[i] = _SKIP
        # the chunk's own bytes (data runs on a little into the next one)
        chunk = data if len(data) == self._size else data[:self._size]
        if b"\0" in chunk or b"\t" in chunk or not chunk.isascii() \
                or (b"\r" in chunk and chunk.count(b"\r") > len(starts)):
            # binary, tabs, non-ASCII, stray CRs: such lines the slow way
            odd = ~_ascii_plain(buf[:self._size])
            odd_lines = np.searchsorted(starts, np.flatnonzero(odd), "right") - 1
            kinds[odd_lines] = _OTHER
        return kinds

    def _words(self, buf, size, starts, ends, kinds, sep, sep_byte):
        """X Y Z E F I J K values (NaN: absent) of move, G92 and arc lines,
        one row per letter; a line whose words do not read as simple numbers
        (or a move's or G92's with I J K) becomes other.
        sep: where the bytes that end words are (newline, space, ';', CR),
        sep_byte: which."""
        n = len(starts)
        values = np.full((len(_AXES), n), np.nan)
        arc = (kinds == _ARC_CW) | (kinds == _ARC_CCW)
        code = (kinds == _MOVE) | (kinds == _G92) | arc
        if not code.any():
            return values
        # the line each of them is on: the newlines before it
        is_nl = sep_byte == 10
        sep_line = np.cumsum(is_nl)
        sep_line -= is_nl
        # the code part of a line ends at its comment
        code_end = ends.copy()
        semi = np.flatnonzero(sep_byte == 59)
        if semi.size:
            semi_line = sep_line[semi]
            first = np.ones(len(semi), bool)
            first[1:] = semi_line[1:] != semi_line[:-1]
            code_end[semi_line[first]] = sep[semi[first]]
        # a word starts after a space and ends at the next of them (a CR
        # ends it too: one at its line's end is not part of the number)
        after = np.flatnonzero(sep_byte == 32)
        line = sep_line[after]
        word_start = sep[after]
        word_start += 1
        word_end = sep.take(after + 1, mode="clip")
        if len(after) and after[-1] == len(sep) - 1:
            word_end[-1] = size         # the data's last byte is a space
        keep = code[line] & (word_start < code_end[line]) & (word_end > word_start)
        word_start, line = word_start[keep], line[keep]
        length = word_end[keep] - word_start
        bad_lines = []
        cr = np.flatnonzero(sep_byte == 13)
        if cr.size:
            # a CR anywhere but at the end of its line
            cr_line = sep_line[cr]
            bad_lines.append(cr_line[sep[cr] != ends[cr_line] - 1])
        too_long = length > _WORD_BYTES
        if too_long.any():
            bad_lines.append(line[too_long])
            length = np.minimum(length, _WORD_BYTES)
        width = int(length.max()) if len(length) else 2
        numbers, ok = _read_numbers(buf, word_start, length, width)
        letter = _LETTER[buf[word_start]]
        ok &= (letter >= 0) & (length >= 2)
        bad_lines.append(line[~ok])
        bad_lines.append(line[(letter >= 5) & ~arc[line]])
        absurd = ~(np.abs(numbers) <= MAX_ABS_VALUE)
        bad_lines.append(line[ok & absurd])
        feed = ok & (letter == 4)
        bad_lines.append(line[feed & (numbers <= 0.0)])
        good = ok & ~absurd
        key = line[good] + letter[good].astype(np.int64) * n
        values.reshape(-1)[key] = numbers[good]
        # one word per axis and line (Klipper keeps the last, numpy may not):
        # as many values as words unless two share a place (a line with an
        # absurd word among its doubles is bad already)
        if np.count_nonzero(~np.isnan(values)) != len(key):
            counts = np.bincount(key, minlength=5 * n)
            bad_lines.append(np.flatnonzero(counts > 1) % n)
        # a G92 sets X Y Z E only: one with an F word is bad
        g92 = np.flatnonzero(kinds == _G92)
        if g92.size:
            bad_lines.append(g92[~np.isnan(values[4, g92])])
        bad = np.concatenate(bad_lines)
        kinds[bad] = _OTHER
        values[:, bad] = np.nan
        # a G92 without an axis sets them all: the reference does that
        g92 = np.flatnonzero(kinds == _G92)
        if g92.size:
            kinds[g92[np.isnan(values[:4, g92]).all(axis=0)]] = _OTHER
        return values

    def _scalar_line(self, data, starts, ends, i, offset, first_line) -> None:
        end = ends[i] + 1 if ends[i] < self._size else ends[i]
        raw = data[starts[i]:end]
        events = self.state.line(raw, offset + int(starts[i]),
                                 first_line + int(i) + 1)
        self._take_scalar_moves()
        self.out.extend(events)

    def _take_scalar_moves(self) -> None:
        if self.scalar_moves:
            self.parts.append(_queue_of_moves(self.scalar_moves))
            self.scalar_moves = []

    # --- gcode_move over a run of move and G92 lines --------------------------
    def _run(self, lo, hi, kinds, words, starts, ends, data, offset,
             first_line) -> None:
        if self._bulk_run(lo, hi, kinds, words, starts, offset):
            return
        kind = kinds[lo:hi]
        arcs = np.flatnonzero((kind == _ARC_CW) | (kind == _ARC_CCW)) + lo
        if not arcs.size:
            # an error or an odd move: the slow way, line by line
            for i in range(lo, hi):
                self._scalar_line(data, starts, ends, i, offset, first_line)
            return
        # arcs this run cannot expand at once: each through the reference,
        # the lines between them in bulk
        run_start = lo
        for stop in arcs.tolist() + [hi]:
            if stop > run_start:
                self._run(run_start, stop, kinds, words, starts, ends, data,
                          offset, first_line)
            if stop < hi:
                self._scalar_line(data, starts, ends, stop, offset, first_line)
            run_start = stop + 1

    def _bulk_run(self, lo, hi, kinds, words, starts, offset) -> bool:
        """gcode_move and the moves of lines lo..hi-1 at once; False (and
        nothing done) where they must go the slow way."""
        st = self.state
        ef = st.extrude_factor
        retracted = st.is_retracted
        step_e = step_speed = None
        kind = kinds[lo:hi]
        if st.absolute_coord and st.absolute_extrude \
                and not (kind >= _G10).any():
            # every line of the run, as a view: the ones with nothing to plan
            # (comments) give no value, and in absolute coordinates a
            # position is only ever carried over them
            if not (kind >= _MOVE).any():
                return True
            rows = np.arange(lo, hi)
            vals = words[:, lo:hi]
        else:
            rows = np.flatnonzero(kind >= _MOVE) + lo
            if not rows.size:
                return True
            kind = kinds[rows]
            vals = words[:, rows]
        arcs = None
        if ((kind == _ARC_CW) | (kind == _ARC_CCW)).any():
            expanded = self._expand_arcs(rows, kind, vals)
            if expanded is None:
                return False
            rows, kind, vals, arcs = expanded
        retractions = np.flatnonzero(kind >= _G10)
        if retractions.size:
            # firmware_retraction: a G10 acts only when not retracted, a G11
            # only when retracted; each that acts is an E-only move (its own
            # speed) that leaves the G-code E coordinate where it was
            keep = np.ones(len(rows), bool)
            step_e = np.full(len(rows), np.nan)
            step_speed = np.full(len(rows), np.nan)
            for r, k in zip(retractions.tolist(), kind[retractions].tolist()):
                if k == _G10 and not retracted:
                    length, speed = -st.retract_length, st.retract_speed
                elif k == _G11 and retracted:
                    length = st.retract_length + st.unretract_extra_length
                    speed = st.unretract_speed
                else:
                    keep[r] = False
                    continue
                retracted = not retracted
                step_e[r] = length * ef
                step_speed[r] = float(int(speed * 60)) * st.speed_factor
            rows, step_e, step_speed = rows[keep], step_e[keep], step_speed[keep]
            if not rows.size:
                st.is_retracted = retracted
                return True
            kind, vals = kind[keep], vals[:, keep]
        is_move = kind == _MOVE
        # (vals may be a view of the chunk's words, which a retry reads again)
        axis_vals = [vals[0], vals[1], vals[2], vals[3] * ef]
        last = [None] * 4
        base_rows = [None] * 4
        base_out = list(st.base_position)
        for axis in range(4):
            absolute = st.absolute_coord and (axis < 3 or st.absolute_extrude)
            last[axis], base_out[axis], base_rows[axis] = _axis_positions(
                axis_vals[axis], is_move, st.last_position[axis],
                st.base_position[axis], absolute, step_e if axis == 3 else None)
        if arcs is not None and not self._arcs_started_right(arcs, last, base_rows):
            return False
        # the feed rate each move runs at (a retraction's own, not kept)
        feed = vals[4]
        speeds = _ffill(feed * st.speed_factor, st.speed, ~np.isnan(feed))
        move_speeds = speeds
        if step_e is not None:
            stepping = ~np.isnan(step_e)
            is_move = is_move | stepping
            move_speeds = np.where(stepping, step_speed, speeds)
        moving = np.flatnonzero(is_move)
        if not moving.size:
            self._set_state(last, base_out, speeds)
            st.is_retracted = retracted
            return True
        # each axis's position after each move, and its change from the one
        # before (the first from where the last run left it)
        pos = [axis[moving] for axis in last]
        d = [_steps(p, c) for p, c in zip(pos, st.commanded_pos)]
        moves = self._moves(d, move_speeds[moving],
                            offset + starts[rows[moving]])
        if moves is None:               # an error or an odd move
            return False
        self._set_state(last, base_out, speeds)
        st.is_retracted = retracted
        st.commanded_pos = [p[-1] for p in pos]
        self.parts.append(moves)
        return True

    # --- gcode_arcs -------------------------------------------------------------
    def _expand_arcs(self, rows, kind, vals):
        """The run's rows with each arc's row replaced by its segments' G1
        rows (reference_planner.arc_segments, which the reference expands
        them with), and for each arc the index of its first segment and the
        position it started from; None: the slow way (relative coordinates,
        no centre, firmware retraction in the run).

        The G-code position each arc starts from is gcode_move's, followed
        row by row in Python floats as gcode_move keeps it (a move sets an
        axis to its word plus the origin, or adds the word in relative E; a
        G92 moves the origin; an arc's segments set it one after another).
        _arcs_started_right checks each arc's start against the positions
        the run's rows then give in bulk, so a slip in this loop sends the
        run the slow way rather than into the plan."""
        st = self.state
        if not st.absolute_coord or (kind >= _G10).any():
            return None
        ef = st.extrude_factor
        absolute_e = st.absolute_extrude
        last, base = list(st.last_position[:4]), list(st.base_position[:4])
        alpha, beta, _ = st.arc_axes
        is_arc = (kind == _ARC_CW) | (kind == _ARC_CCW)
        # the rows that move the position (comments carry it), as floats
        moving = np.flatnonzero((kind == _MOVE) | (kind == _G92) | is_arc)
        words = vals[:, moving].T.tolist()
        kinds = kind[moving].tolist()
        counts = np.ones(len(rows), np.intp)
        ends_of, extruded_of, started = [], [], []
        for r, k, word in zip(moving.tolist(), kinds, words):
            if k == _MOVE:
                for axis in range(4):
                    v = word[axis]
                    if v != v:                          # NaN: no word
                        continue
                    if axis < 3:
                        last[axis] = v + base[axis]
                    elif absolute_e:
                        last[3] = v * ef + base[3]
                    else:
                        last[3] += v * ef
                continue
            if k == _G92:
                for axis in range(4):
                    v = word[axis]
                    if v == v:
                        base[axis] = last[axis] - (v * ef if axis == 3 else v)
                continue
            planar = tuple(0.0 if c != c else c
                           for c in (word[5 + alpha], word[5 + beta]))
            if not (planar[0] or planar[1]):
                return None
            params = {a: word[i] for i, a in enumerate("XYZE") if word[i] == word[i]}
            current = gcode_position(last, base, ef)
            ends, extruded = arc_segments(current, params, planar, st.arc_axes,
                                          k == _ARC_CW, absolute_e,
                                          st.limits.arc_resolution)
            for axis in range(3):
                last[axis] = ends[-1][axis] + base[axis]
            if extruded is not None:
                if absolute_e:
                    last[3] = extruded[-1] * ef + base[3]
                else:
                    for e in extruded:
                        last[3] += e * ef
            counts[r] = len(ends)
            ends_of.append(ends)
            extruded_of.append(extruded)
            started.append(current)
        arc_rows = np.flatnonzero(is_arc)
        # the expanded rows: every row repeated as often as it has segments
        # (once, but for arcs; an arc's F stays on each), then the arcs'
        # rows given their segments' ends and E words
        first = np.cumsum(counts) - counts
        extrudes = np.zeros(len(counts), bool)
        extrudes[arc_rows[[e is not None for e in extruded_of]]] = True
        rows = np.repeat(rows, counts)
        kind = np.repeat(kind, counts)
        vals = np.repeat(vals[:5], counts, axis=1)
        at = np.flatnonzero(np.repeat(is_arc, counts))
        chain = itertools.chain.from_iterable
        vals[:3, at] = np.array(list(chain(chain(ends_of)))).reshape(-1, 3).T
        vals[3, at] = np.nan
        vals[3, np.repeat(extrudes, counts)] = list(chain(
            e for e in extruded_of if e is not None))
        kind[at] = _MOVE
        arcs = [(int(first[r]), current)
                for r, current in zip(arc_rows.tolist(), started)]
        return rows, kind, vals, arcs

    def _arcs_started_right(self, arcs, last, base_rows) -> bool:
        """Whether each arc started from the G-code position the rows
        before it give (last: each axis's position after each row, base_rows
        its origin; E only where it is absolute). An arc on the run's first
        row started from the state, as _expand_arcs read it."""
        st = self.state
        axes = 4 if st.absolute_extrude else 3
        for at, current in arcs:
            if not at:
                continue
            pos = gcode_position([float(a[at - 1]) for a in last],
                                 [float(b[at - 1]) if b is not None else 0.0
                                  for b in base_rows], st.extrude_factor)
            if pos[:axes] != current[:axes]:
                return False
        return True

    def _set_state(self, last, base, speeds) -> None:
        st = self.state
        st.last_position = [float(axis[-1]) for axis in last]
        st.base_position = [float(v) for v in base]
        st.speed = float(speeds[-1])

    def _moves(self, d, speed, offsets) -> Optional[_Queue]:
        """toolhead.Move and extruder.check_move for each row that moves."""
        st = self.state
        dx, dy, dz, de = d
        move_d = np.sqrt(dx * dx + dy * dy + dz * dz)
        still = move_d < 0.000000001
        if (still & ((dx != 0.0) | (dy != 0.0) | (dz != 0.0))).any():
            return None                 # a sub-nanometre move: the slow way
        moving = ~still | (de != 0.0)
        dx, dy, dz, de = dx[moving], dy[moving], dz[moving], de[moving]
        speed, offsets, still = speed[moving], offsets[moving], still[moving]
        move_d = np.where(still, np.abs(de), move_d[moving])
        kin = ~still
        accel = np.where(kin, st.max_accel, 99999999.9)
        velocity = np.where(kin, np.minimum(speed, st.max_velocity), speed)
        inv_move_d = 1.0 / move_d
        er = de * inv_move_d
        max_cruise_v2 = velocity * velocity
        delta_v2 = 2.0 * move_d * accel
        mcr_delta_v2 = 2.0 * move_d * st.mcr_pseudo_accel
        z = (dz != 0.0) & kin
        if z.any():
            z_ratio = move_d[z] / np.abs(dz[z])
            _limit_speed(z, st.max_z_velocity * z_ratio, st.max_z_accel * z_ratio,
                         move_d, max_cruise_v2, accel, delta_v2, mcr_delta_v2)
        extrudes = de != 0.0
        e_only = extrudes & (((dx == 0.0) & (dy == 0.0)) | (er < 0.0))
        if (e_only & (np.abs(de) > st.max_e_dist)).any():
            return None
        if (extrudes & ~e_only & (er > st.max_extrude_ratio)
                & (de > st.limits.nozzle_diameter * st.max_extrude_ratio)).any():
            return None
        if e_only.any():
            inv_extrude_r = 1.0 / np.abs(er[e_only])
            _limit_speed(e_only, st.max_e_velocity * inv_extrude_r,
                         st.max_e_accel * inv_extrude_r,
                         move_d, max_cruise_v2, accel, delta_v2, mcr_delta_v2)
        filament = self._filament(de)
        n = len(move_d)
        return _Queue(
            dx * inv_move_d, dy * inv_move_d, dz * inv_move_d, er, move_d,
            accel, np.full(n, st.junction_deviation), max_cruise_v2, delta_v2,
            mcr_delta_v2, kin, filament, filament * st.area * inv_move_d,
            offsets.astype(np.int64, copy=False), np.full(n, np.nan),
            np.full(n, np.nan))

    def _filament(self, de: np.ndarray) -> np.ndarray:
        """Net filament of each move: pushed back after a retraction it
        refills the nozzle first (sequential where something is retracted)."""
        st = self.state
        filament = np.where(de > 0.0, de, 0.0)
        retracted = st.retracted_mm
        negative = np.flatnonzero(de < 0.0)
        if not negative.size and retracted == 0.0:
            return filament
        if retracted == 0.0:
            # as slicers retract: the next move of E after each retraction
            # pushes back at least as much; it refills the nozzle and
            # nothing is retracted after it (what the loop below does then)
            moving = np.flatnonzero(de != 0.0)
            e = de[moving]
            back = np.flatnonzero(e < 0.0)
            refill = back + 1
            if refill[-1] < len(e):
                retraction = 0.0 - e[back]
                pushed = e[refill]
                if ((pushed > 0.0) & (pushed >= retraction)).all():
                    filament[moving[refill]] = pushed - retraction
                    return filament
        values = de.tolist()
        stops = negative.tolist() + [len(values)]
        i = 0 if retracted > 0.0 else stops[0]
        for stop in stops:
            # from i (a retraction, or the start) until nothing is retracted
            while i < len(values):
                v = values[i]
                if v < 0.0:
                    retracted -= v
                elif v > 0.0:
                    refill = min(v, retracted)
                    retracted -= refill
                    filament[i] = v - refill
                i += 1
                if retracted == 0.0 or i > stop:
                    break
            i = max(i, stop)
        st.retracted_mm = retracted
        return filament

    # --- toolhead lookahead ---------------------------------------------------
    def flush(self, lazy: bool) -> None:
        """Join new moves to the queue and flush it, as LookAheadQueue.flush
        (lazy: only what later moves cannot change)."""
        self._take_scalar_moves()
        parts = ([self.queue] if self.queue is not None else []) + self.parts
        self.parts = []
        if not parts:
            return
        joined = 0 if self.queue is None else len(self.queue.move_d)
        q = self._join(_concat(parts), joined)
        self.queue = q
        count = self._flush_count(q, lazy)
        if count:
            self._emit(q, count)
            self.queue = None if count == len(q.move_d) \
                else _take(q, slice(count, None))

    def _join(self, q: _Queue, joined: int) -> _Queue:
        """calc_junction for rows joined..end (rows before are joined)."""
        n = len(q.move_d)
        if joined == n:
            return q
        st = self.state
        # row r against row r - 1, for the rows from joined that have one:
        # as slices (whole arrays, masked at the end, not gathered)
        lo = max(joined, 1)
        cur, pr = slice(lo, n), slice(lo - 1, n - 1)
        a = np.zeros(n - joined)
        add = np.zeros(n - joined)
        add_mcr = np.zeros(n - joined)
        if lo < n:
            # a junction needs both moves kinematic; else 0
            has = q.kinematic[cur] & q.kinematic[pr]
            with np.errstate(all="ignore"):     # rows without a junction
                diff_r = q.ae[cur] - q.ae[pr]
                v2 = np.minimum(q.max_cruise_v2[cur], q.max_cruise_v2[pr])
                ea_v2 = np.where(diff_r != 0.0,
                                 (st.instant_corner_v / diff_r) ** 2, np.inf)
                v2 = np.minimum(np.minimum(v2, ea_v2), 999999999.9)
                cos = -(q.ax[cur] * q.ax[pr] + q.ay[cur] * q.ay[pr]
                        + q.az[cur] * q.az[pr])
                sin_d2 = np.sqrt(np.maximum(0.5 * (1.0 - cos), 0.0))
                cos_d2 = np.sqrt(np.maximum(0.5 * (1.0 + cos), 0.0))
                one_minus = 1.0 - sin_d2
                corner = (one_minus > 0.0) & (cos_d2 > 0.0) & has
                if corner.any():
                    r_jd = sin_d2 / one_minus
                    quarter_tan = 0.25 * sin_d2 / cos_d2
                    lim = np.minimum(
                        np.minimum(r_jd * q.junction_deviation[cur] * q.accel[cur],
                                   r_jd * q.junction_deviation[pr] * q.accel[pr]),
                        np.minimum(q.delta_v2[cur] * quarter_tan,
                                   q.delta_v2[pr] * quarter_tan))
                    v2 = np.where(corner, np.minimum(v2, lim), v2)
            a[lo - joined:] = np.where(has, v2, 0.0)
            # the reach from the move before, x[i] = min(a, x[i-1] +
            # delta[i-1]); a row without a junction is 0 and so starts the
            # chain again
            add[lo - joined:] = q.delta_v2[pr]
            add_mcr[lo - joined:] = q.mcr_delta_v2[pr]
        x0 = q.max_start_v2[joined - 1] if joined else 0.0
        x0_mcr = q.max_mcr_start_v2[joined - 1] if joined else 0.0
        max_start = q.max_start_v2.copy()
        max_mcr = q.max_mcr_start_v2.copy()
        max_start[joined:] = min_plus(a, add, x0)
        max_mcr[joined:] = min_plus(max_start[joined:], add_mcr, x0_mcr)
        return q._replace(max_start_v2=max_start, max_mcr_start_v2=max_mcr)

    def _flush_count(self, q: _Queue, lazy: bool) -> int:
        self._pass = _Backward(q)
        if not lazy:
            return len(q.move_d)
        return self._pass.lazy_count

    def _emit(self, q: _Queue, count: int) -> None:
        p = self._pass
        sl = slice(0, count)
        start_v2, cruise_v2 = p.start_v2[sl], p.cruise_v2(count)
        next_v2 = p.next_start_v2[sl]
        s = np.minimum(start_v2, cruise_v2)
        e = np.minimum(next_v2, cruise_v2)
        accel, move_d = q.accel[sl], q.move_d[sl]
        half_inv_accel = 0.5 / accel
        accel_d = (cruise_v2 - s) * half_inv_accel
        decel_d = (cruise_v2 - e) * half_inv_accel
        cruise_d = move_d - accel_d - decel_d
        start_v, cruise_v, end_v = np.sqrt(s), np.sqrt(cruise_v2), np.sqrt(e)
        accel_t = accel_d / ((start_v + cruise_v) * 0.5)
        cruise_t = cruise_d / cruise_v
        decel_t = decel_d / ((end_v + cruise_v) * 0.5)
        duration = accel_t + cruise_t + decel_t
        times = np.cumsum(np.concatenate(([self.state.print_time], duration)))
        self.state.print_time = float(times[-1])
        k = q.flow_per_mm[sl]
        self.out.append(Segments(
            times[:-1], duration, cruise_v * k, accel_t, decel_t, start_v * k,
            end_v * k, cruise_v, move_d, q.filament_mm[sl], q.offset[sl]))


class _Backward:
    """LookAheadQueue.flush's backward pass over a whole queue."""

    def __init__(self, q: _Queue):
        n = len(q.move_d)
        delta, mcr_delta = q.delta_v2, q.mcr_delta_v2
        start = min_plus(q.max_start_v2[::-1], delta[::-1], 0.0)[::-1]
        mcr = min_plus(q.max_mcr_start_v2[::-1], mcr_delta[::-1], 0.0)[::-1]
        self.start_v2 = start
        self.next_start_v2 = np.concatenate((start[1:], [0.0]))
        next_mcr = np.concatenate((mcr[1:], [0.0]))
        reachable = self.next_start_v2 + delta
        reach_mcr = next_mcr + mcr_delta
        sat = mcr < reach_mcr
        after_unassigned = np.zeros(n, bool)
        after_unassigned[:-1] = ~sat[1:]
        peak = sat & ((mcr + mcr_delta > next_mcr) | after_unassigned)
        peak_value = np.where(peak, (mcr + reach_mcr) * 0.5, 0.0)
        # the peak_cruise_v2 each assigned move sees: the nearest peak at or
        # after it (scanning backward), 0 before the first
        at = np.where(peak, np.arange(n), n)
        nearest = np.minimum.accumulate(at[::-1])[::-1]
        seen = np.concatenate((peak_value, [0.0]))[nearest]
        self.sat = sat
        self.assigned = np.minimum(np.minimum((start + reachable) * 0.5,
                                              q.max_cruise_v2), seen)
        self.lazy_count = 0
        peaks = np.flatnonzero(peak)
        sats = np.flatnonzero(sat)
        if len(peaks) >= 2:
            # scanning backward: the first peak met after another (nonzero) one
            later_value = peak_value[peaks[1:]]
            candidates = peaks[:-1][later_value != 0.0]
            if candidates.size:
                i = candidates[-1]
                self.lazy_count = int(sats[np.searchsorted(sats, i, "right")])

    def cruise_v2(self, count: int) -> np.ndarray:
        """Cruise of the first count moves: assigned ones their own, the
        others the lowest since the last assigned one (0 before the first)."""
        sat = self.sat[:count]
        values = np.where(sat, self.assigned[:count], self.start_v2[:count])
        segment = np.cumsum(sat)
        keyed = np.empty(count + 1, complex)
        keyed[0] = 0.0
        keyed[1:] = -segment + 1j * values
        return np.minimum.accumulate(keyed)[1:].imag


def _limit_speed(mask, speed, accel, move_d, max_cruise_v2, accel_arr,
                 delta_v2, mcr_delta_v2) -> None:
    """toolhead Move.limit_speed on the rows of mask, in place."""
    speed2 = speed * speed
    max_cruise_v2[mask] = np.minimum(max_cruise_v2[mask], speed2)
    accel_arr[mask] = np.minimum(accel_arr[mask], accel)
    delta_v2[mask] = 2.0 * move_d[mask] * accel_arr[mask]
    mcr_delta_v2[mask] = np.minimum(mcr_delta_v2[mask], delta_v2[mask])


def _steps(positions: np.ndarray, before: float) -> np.ndarray:
    """Each position less the one before it (before the first: before)."""
    steps = np.empty(len(positions))
    steps[0] = positions[0] - before
    np.subtract(positions[1:], positions[:-1], out=steps[1:])
    return steps


def _ffill(values: np.ndarray, first: float,
           known: Optional[np.ndarray] = None) -> np.ndarray:
    """NaN replaced by the last value before it (first before any); known:
    where values are not NaN, if known."""
    given = np.flatnonzero(~np.isnan(values) if known is None else known)
    if not len(given):
        return np.full(len(values), first, float)
    # first until the first value given, each value given until the next
    held = np.empty(len(given) + 1)
    held[0] = first
    held[1:] = values[given]
    counts = np.empty(len(given) + 1, np.intp)
    counts[0] = given[0]
    np.subtract(given[1:], given[:-1], out=counts[1:-1])
    counts[-1] = len(values) - given[-1]
    return np.repeat(held, counts)


def _axis_positions(vals, is_move, last0, base0, absolute, steps=None):
    """gcode_move's position of one axis after each row (moves set it, G92
    rows move its origin, steps (firmware retraction, E only) move it and its
    origin together), the origin after the last row, and the origin after
    each row (None where the axis is relative: nothing asks for it)."""
    given = ~np.isnan(vals)
    g92 = given & ~is_move
    if steps is None:
        stepping = np.zeros(len(vals), bool)
        special = np.flatnonzero(g92)
    else:
        stepping = ~np.isnan(steps)
        special = np.flatnonzero(g92 | stepping)
    if absolute and not special.size:
        # the values given are all moves': each from the origin
        return _ffill(vals + base0, last0, given), base0, \
            np.broadcast_to(np.float64(base0), vals.shape)
    moves = given & is_move
    if not absolute:
        add = np.where(moves, vals, np.where(stepping, steps, 0.0)) \
            if steps is not None else np.where(moves, vals, 0.0)
        last = np.cumsum(np.concatenate(([last0], add)))[1:]
        base = base0
        for i in special.tolist():
            if stepping[i]:
                before = float(last[i - 1]) if i else last0
                base = base + (float(last[i]) - before)
            else:
                base = float(last[i]) - float(vals[i])
        return last, base, None
    # each G92 or step starts a new origin from the position at that row
    bases = [base0]
    at_step = np.full(len(vals), np.nan)
    cur_last, cur_base, prev = last0, base0, -1
    move_rows = np.flatnonzero(moves)
    before = np.searchsorted(move_rows, special) - 1
    last_move = np.full(len(special), -1)
    if move_rows.size:
        last_move = np.where(before >= 0, move_rows[np.maximum(before, 0)], -1)
    zero = vals[special]
    if not stepping.any() and last_move[0] >= 0 \
            and (last_move[1:] > special[:-1]).all() \
            and ((zero == 0.0) & ~np.signbit(zero)).all():
        # only G92 to 0 (`G92 E0`), each after a move: the loop below makes
        # each origin (move + origin) - 0, the one before plus the move's
        # value, which is a running sum, rounded as the loop rounds it
        bases = np.cumsum(np.concatenate(([base0], vals[last_move])))
        cur_base = float(bases[-1])
    else:
        for i, k, v in zip(special.tolist(), last_move.tolist(),
                           vals[np.maximum(last_move, 0)].tolist()):
            if k > prev:
                cur_last = v + cur_base
            if stepping[i]:
                new_last = cur_last + float(steps[i])
                cur_base = cur_base + (new_last - cur_last)
                cur_last = new_last
                at_step[i] = cur_last
            else:
                cur_base = cur_last - float(vals[i])
            bases.append(cur_base)
            prev = i
    # the origin of each row: the specials at or before it
    epoch = np.zeros(len(vals), np.intp)
    epoch[special] = 1
    np.cumsum(epoch, out=epoch)
    base_of_row = np.asarray(bases)[epoch]
    known = np.where(moves, vals + base_of_row, at_step)
    return _ffill(known, last0), cur_base, base_of_row


def _read_numbers(buf, start, length, width):
    """The numbers after each word's letter ([-+]digits[.digits]) as float()
    reads them, and whether the word is one. An integer mantissa below 2^53
    (exact in float64) divided by an exact power of ten is the correctly
    rounded value, which is float()'s; longer mantissas are read by float()."""
    n = len(start)
    mantissa = np.zeros(n)
    frac = np.zeros(n, np.int16)
    digits = np.zeros(n, np.int16)
    dots = np.zeros(n, np.int16)
    seen_dot = np.zeros(n, bool)
    # a word is read while its characters are number characters; it is one
    # if that lasts to its end
    alive = np.ones(n, bool)
    read = np.zeros(n, np.int16)
    negative = np.zeros(n, bool)
    for c in range(1, width):
        ch = buf[start + c]
        value = ch - np.uint8(48)
        is_digit = (value < 10) & alive
        is_dot = (ch == 46) & alive
        if c == 1:
            negative = (ch == 45) & alive
            alive &= is_digit | is_dot | negative | (ch == 43)
        else:
            alive &= is_digit | is_dot
        read += alive
        mantissa = np.where(is_digit, mantissa * 10.0 + value, mantissa)
        frac += is_digit & seen_dot
        digits += is_digit
        dots += is_dot
        seen_dot |= is_dot
    ok = (read >= length - 1) & (digits > 0) & (dots <= 1)
    values = mantissa / _POWERS[np.minimum(frac, 22)]
    values = np.where(negative, -values, values)
    for i in np.flatnonzero(ok & (digits > 15)).tolist():
        values[i] = float(bytes(buf[start[i] + 1:start[i] + length[i]]))
    return values, ok


_POWERS = 10.0 ** np.arange(23)


def _ascii_plain(buf: np.ndarray) -> np.ndarray:
    """Bytes the bulk path reads: printable ASCII, newline, CR at line end."""
    ok = (buf >= 32) & (buf < 127)
    ok |= buf == 10
    ok |= buf == 13
    return ok


def plan_batches(f: BinaryIO, limits: Optional[PrinterLimits] = None,
                 chunk_bytes: int = CHUNK_BYTES) -> Iterator[Batch]:
    """Segments (as arrays) and barriers of a G-code file opened in binary."""
    planner = BulkPlanner(limits)
    offset, rest = 0, b""
    # A file that can seek is read from each chunk's first line on, a little
    # past chunk_bytes: the lines are planned where they were read (no
    # copy), and a line cut at the end is read again with the next chunk.
    seekable = f.seekable()
    base = f.tell() if seekable else 0
    while True:
        if seekable and not rest:
            data = f.read(chunk_bytes + _WORD_BYTES)
            if not data:
                break
            cut = data.rfind(b"\n", 0, chunk_bytes) + 1
            if cut and len(data) >= cut + _WORD_BYTES:
                yield from planner.chunk(data, offset, cut)
                offset += cut
                f.seek(base + offset)
                continue
            f.seek(base + offset)       # the end, or a line longer than a chunk
        data = f.read(chunk_bytes)
        if not data:
            break
        data = rest + data
        cut = data.rfind(b"\n") + 1
        if cut == 0:
            rest = data
            continue
        rest = data[cut:]
        yield from planner.chunk(data[:cut], offset)
        offset += cut
        if seekable:
            f.seek(base + offset)
            rest = b""
    if rest:
        yield from planner.chunk(rest, offset)
    yield from planner.finish()


def plan_file(f: BinaryIO, limits: Optional[PrinterLimits] = None,
              chunk_bytes: int = CHUNK_BYTES) -> Iterator[Event]:
    """reference_planner.plan_file's events, planned in bulk."""
    for batch in plan_batches(f, limits, chunk_bytes):
        if isinstance(batch, Barrier):
            yield batch
        else:
            yield from batch.records()


# --- to another process -----------------------------------------------------------

_BATCH = struct.Struct("<cq")


def write_batch(batch: Batch, pipe: BinaryIO) -> None:
    """batch as bytes read_batch reads back: a Segments as its length and
    its columns' raw bytes (the same floats, bit for bit, and no pickling
    of a million of them), a Barrier pickled."""
    if isinstance(batch, Segments):
        pipe.write(_BATCH.pack(b"S", len(batch)))
        for column in batch:
            pipe.write(memoryview(np.ascontiguousarray(column)).cast("B"))
        return
    data = pickle.dumps(batch)
    pipe.write(_BATCH.pack(b"B", len(data)))
    pipe.write(data)


def read_batch(pipe: BinaryIO) -> Batch:
    """The batch write_batch wrote."""
    kind, size = _BATCH.unpack(read_exactly(pipe, _BATCH.size))
    if kind == b"B":
        return pickle.loads(read_exactly(pipe, size))
    # one block, a row per column (float64, and the offsets' int64)
    block = np.empty((len(Segments._fields), size))
    read_into(pipe, block)
    columns = list(block)
    columns[-1] = columns[-1].view(np.int64)
    return Segments(*columns)


def planned_ahead(src: Path, limits: Optional[PrinterLimits] = None,
                  chunk_bytes: int = CHUNK_BYTES) -> Iterator[Batch]:
    """plan_batches of the file at src, planned ahead of its consumer in a
    process or a thread of its own (flowloop.gcode.ahead.ahead_of). Close
    it when done: that stops the planner, wherever it runs."""
    def batches() -> Iterator[Batch]:
        with open(src, "rb") as f:
            yield from plan_batches(f, limits, chunk_bytes)
    return ahead_of(batches, write_batch, read_batch,
                    worth_a_process=os.path.getsize(src) >= PROCESS_FROM_BYTES)
