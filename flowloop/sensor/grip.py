"""Grip: how much of the filament the extruder was told to push actually moved.

The estimator takes sensor samples (print time, filament mm measured by the
sensor) with the filament the extruder was commanded to have moved at the
same print times, and closes a window each time the commanded filament has
advanced `window_mm`. grip = measured / commanded over that window, divided
by the sensor calibration (sensor mm per extruder mm measured where the
feeder cannot slip), so a feeder that keeps up reads 1.0.

A slip does not wait for the window to fill: every SLIP_STEP_MM of
commanded filament the grip over the last SLIP_CHECK_MM is checked, and when
it reads below SLIP_GRIP the window ends there, as two judged windows: the
part before that stretch (if any) and the stretch that slipped. A window
closes early only on a slip, so one that keeps up is window_mm long. No
slip is looked for while the filament goes back in after a retraction (up
to where it was before it): that melts nothing new.

A window is not judged (grip None) when it contains a retraction (the
nominal E position, the planned motion without pressure advance, went back
by more than `retract_tolerance_mm`), or when
it took longer than `max_window_s` to collect `window_mm` (too little motion
to say anything). A judged window in which the sensor did not move at all
while the extruder did is reported as `stuck`: it is not grip 0, because a
seized sensor looks exactly the same.
"""

from __future__ import annotations

import collections
import itertools
import math
from typing import Deque, List, Optional, Sequence, Tuple

import numpy as np

from ..errors import FlowloopError
from ..window import JUDGED, RETRACTION, STUCK, TOO_LITTLE_MOTION, Window

FLOW_PERIOD_S = 0.25
# A slip is looked for over this much commanded filament (0.17 s at
# 7 mm^3/s), every SLIP_STEP_MM of it: with ~100 counts per mm the sensor's
# noise reads about 0.01 of grip there, and a feeder's transient lag
# (filament squeezed a few tens of micrometres at a change of speed) under
# 0.1, so only a real slip reads below SLIP_GRIP.
SLIP_CHECK_MM = 0.5
SLIP_STEP_MM = 0.125
SLIP_GRIP = 0.85
# [flow_sensor] options and their limits: the adapter reads them from here
DEFAULT_WINDOW_MM = 1.25
WINDOW_MM_RANGE = (0.1, 50.0)


class GripEstimator:
    def __init__(self, window_mm: float = DEFAULT_WINDOW_MM,
                 calibration: float = 1.0,
                 filament_area_mm2: float = 2.405, max_window_s: float = 2.0,
                 retract_tolerance_mm: float = 0.02,
                 stuck_tolerance_mm: float = 0.02):
        if window_mm <= 0:
            raise FlowloopError(f"grip_window must be above 0, not {window_mm}")
        if calibration <= 0:
            raise FlowloopError(f"calibration must be above 0, not {calibration}")
        self.window_mm = window_mm
        self.calibration = calibration
        self.filament_area_mm2 = filament_area_mm2
        self.max_window_s = max_window_s
        self.retract_tolerance_mm = retract_tolerance_mm
        self.stuck_tolerance_mm = stuck_tolerance_mm
        # the open window's start, then a point every SLIP_STEP_MM since
        self._steps: List[Tuple[float, float, float]] = []
        self._next_step = 0.0   # commanded filament of the next point
        self.grip: Optional[float] = None
        self._temp_c: Optional[float] = None
        self.last_window: Optional[Window] = None
        self._start: Optional[Tuple[float, float, float]] = None
        self._high = 0.0
        # after a retraction, where the filament was before it: going back
        # in melts nothing new, so no slip is looked for below it
        self._refill = -math.inf
        self._recent: Deque[Tuple[float, float, float]] = collections.deque()

    def reset(self) -> None:
        self._start = None
        self._steps.clear()
        self._refill = -math.inf
        self.grip = None
        self._recent.clear()

    def add(self, times: Sequence[float], sensor_mm: Sequence[float],
            commanded_mm: Sequence[float], temp_c: Optional[float] = None,
            nominal_mm: Optional[Sequence[float]] = None,
            breaks: Optional[Sequence[bool]] = None) -> List[Window]:
        """Feed samples in time order; return the windows they closed.

        sensor_mm is raw sensor filament (counts / counts_per_mm); the
        calibration is applied here. commanded_mm is what the extruder
        stepper was at (pressure advance included): grip is measured
        against it. nominal_mm, the planned E position without pressure
        advance (the extruder's trapq), decides what a retraction is, so the
        ~0.1 mm that pressure advance pulls back at a slowing corner does not
        close the window; without it the commanded position decides. temp_c,
        the hotend temperature when the batch was taken, is carried into the
        windows it closes. breaks marks samples whose sensor position may be
        off by whole turns from the ones before (Samples.breaks): the open
        window is dropped and a new one starts there.
        """
        self._temp_c = temp_c
        # plain floats: numpy scalars cost several times more per operation
        times, sensor_mm, commanded_mm = (
            _plain(times), _plain(sensor_mm), _plain(commanded_mm))
        nominal_mm = commanded_mm if nominal_mm is None else _plain(nominal_mm)
        if breaks is None or not np.any(breaks):
            breaks = itertools.repeat(False)
        else:
            breaks = _plain(breaks)
        cal = self.calibration
        measured_mm = [v / cal for v in sensor_mm]
        window_mm, max_window_s = self.window_mm, self.max_window_s
        retract_mm = self.retract_tolerance_mm
        back = int(round(SLIP_CHECK_MM / SLIP_STEP_MM))
        min_slip_mm = SLIP_CHECK_MM / 2.0
        closed, high, refill, kept_from = [], self._high, self._refill, None
        steps = self._steps
        next_step = self._next_step
        for i, (t, m, c, n, b) in enumerate(zip(times, measured_mm, commanded_mm,
                                                nominal_mm, breaks)):
            if b:
                self._start, kept_from = None, i
            if self._start is None:
                self._start, high = (t, m, c), n
                steps[:], next_step = [(t, m, c)], c + SLIP_STEP_MM
                continue
            t0, m0, c0 = self._start
            if n < high - retract_mm:
                closed.append(self._close(t, m, c, None, RETRACTION))
                refill, high = max(refill, high), n
                steps[:], next_step = [(t, m, c)], c + SLIP_STEP_MM
                continue
            if n > high:
                high = n
            if c >= next_step:
                # the grip over the last SLIP_CHECK_MM (across the start of
                # this window if it kept up), from where the filament is
                # back to where it was before a retraction
                if n < refill:
                    steps.clear()
                steps.append((t, m, c))
                next_step += SLIP_STEP_MM
                if next_step <= c:
                    next_step = c + SLIP_STEP_MM
                if len(steps) > back:
                    ts, ms, cs = steps[-1 - back]
                    del steps[:-1 - back]
                    if m - ms < SLIP_GRIP * (c - cs) and c - c0 >= min_slip_mm:
                        if cs - c0 >= min_slip_mm:
                            # the part before the stretch that slipped
                            closed.append(self._judge(ts, ms, cs))
                        # (too little before it, or the stretch began in the
                        # window before, which kept up: this window whole)
                        closed.append(self._judge(t, m, c))
                        # the next slip is judged over a whole stretch again
                        steps[:] = [(t, m, c)]
                        continue
            if c - c0 >= window_mm:
                closed.append(self._judge(t, m, c))
            elif t - t0 > max_window_s:
                closed.append(self._close(t, m, c, None, TOO_LITTLE_MOTION))
                steps[:], next_step = [(t, m, c)], c + SLIP_STEP_MM
        self._high, self._refill, self._next_step = high, refill, next_step
        if kept_from is not None:
            self._recent.clear()
        else:
            kept_from = 0
        self._note_recent(times[kept_from:], measured_mm[kept_from:],
                          commanded_mm[kept_from:])
        return closed

    def _judge(self, t, m, c) -> Window:
        """Close the open window at a sample as judged (or stuck)."""
        measured, commanded = m - self._start[1], c - self._start[2]
        if abs(measured) <= self.stuck_tolerance_mm:
            return self._close(t, m, c, None, STUCK)
        return self._close(t, m, c, measured / commanded, JUDGED)

    def _close(self, t, m, c, grip, reason) -> Window:
        t0, m0, c0 = self._start
        flow = (m - m0) * self.filament_area_mm2 / (t - t0) if t > t0 else None
        window = Window(t0, t, c - c0, m - m0, grip, reason, flow, self._temp_c)
        self.last_window = window
        self.grip = grip
        self._start = (t, m, c)
        return window

    def _note_recent(self, times: List[float], measured: List[float],
                     commanded: List[float]) -> None:
        """Keep the samples of the last FLOW_PERIOD_S (for flows())."""
        recent = self._recent
        recent.extend(zip(times, measured, commanded))
        if not recent:
            return
        oldest = recent[-1][0] - FLOW_PERIOD_S
        while len(recent) > 2 and recent[1][0] <= oldest:
            recent.popleft()

    @property
    def filament_position(self) -> Optional[float]:
        return self._recent[-1][1] if self._recent else None

    @property
    def last_time(self) -> Optional[float]:
        return self._recent[-1][0] if self._recent else None

    def flows(self, period_s: float = FLOW_PERIOD_S) -> Tuple[float, float]:
        """(measured, commanded) volumetric flow in mm^3/s over the last
        period (at most FLOW_PERIOD_S: no older points are kept)."""
        if len(self._recent) < 2:
            return 0.0, 0.0
        t1, m1, c1 = self._recent[-1]
        t0, m0, c0 = next(p for p in self._recent if p[0] >= t1 - period_s)
        if t1 - t0 <= 0:
            return 0.0, 0.0
        area = self.filament_area_mm2
        return (area * (m1 - m0) / (t1 - t0), area * (c1 - c0) / (t1 - t0))


def _plain(values) -> list:
    return values.tolist() if isinstance(values, np.ndarray) else list(values)


# The extruder stepper's position is read this often and interpolated in
# between: over 10 ms a hotend's E acceleration (~100 mm/s^2) bends it by a
# few micrometres, and a host call per sample (1000/s) is what it saves.
COMMANDED_SPACING_S = 0.010


def positions_at(times: Sequence[float], position_at,
                 spacing_s: float = COMMANDED_SPACING_S) -> np.ndarray:
    """position_at(t) (e.g. klippy's extruder.find_past_position) at each
    time, called every spacing_s from the first time (and at the last) and
    linearly interpolated in between."""
    times = np.asarray(times, dtype=np.float64)
    if not len(times):
        return np.zeros(0)
    first, last = float(times[0]), float(times[-1])
    at = [first + i * spacing_s
          for i in range(int((last - first) / spacing_s) + 1)]
    if at[-1] < last:
        at.append(last)
    return np.interp(times, at, [position_at(t) for t in at])


def trapq_positions(moves: Sequence[Tuple[float, float, float, float, float,
                                             float]],
                    times: Sequence[float]) -> Optional[np.ndarray]:
    """The nominal position along one axis at each time, from trapq moves
    (print_time, move_t, start_v, accel, start_position, axis_r) in any
    order (Klipper's trapq_extract_old gives them newest first). Before the
    first move the position is its start, after a move its end; None
    without moves."""
    if not len(moves):
        return None
    m = np.array(sorted(moves), dtype=np.float64)
    start, move_t, start_v, accel, position, axis_r = m.T
    times = np.asarray(times, dtype=np.float64)
    i = np.clip(np.searchsorted(start, times, side="right") - 1, 0, len(m) - 1)
    dt = np.clip(times - start[i], 0.0, move_t[i])
    return position[i] + axis_r[i] * (start_v[i] + 0.5 * accel[i] * dt) * dt


# A window's commanded flow is taken in pieces this long: about how long a
# hotend takes to melt what it is fed (a shorter peak above its capacity
# does not slip the feeder on its own).
FLOW_PIECE_S = 0.05


def window_flows(moves, start_time: float, end_time: float,
                 filament_area_mm2: float,
                 piece_s: float = FLOW_PIECE_S) -> Tuple[float, ...]:
    """The planned volumetric flow (mm^3/s) from start_time to end_time in
    equal pieces of about piece_s, from trapq moves (as trapq_positions
    takes them); () without moves."""
    if end_time <= start_time:
        return ()
    count = max(1, int(round((end_time - start_time) / piece_s)))
    edges = np.linspace(start_time, end_time, count + 1)
    position = trapq_positions(moves, edges)
    if position is None:
        return ()
    flows = np.maximum(np.diff(position), 0.0) * (
        filament_area_mm2 * count / (end_time - start_time))
    return tuple(flows.tolist())


class SampleRate:
    """Good samples since start, and per second over about the last second."""

    def __init__(self, span_s: float = 1.0):
        self.span_s = span_s
        self.total = 0
        # (time, total) at the first and last sample of each batch
        self._marks: Deque[Tuple[float, int]] = collections.deque()

    def add(self, times: Sequence[float]) -> None:
        if not len(times):
            return
        marks = self._marks
        marks.append((float(times[0]), self.total + 1))
        self.total += len(times)
        marks.append((float(times[-1]), self.total))
        while len(marks) > 2 and marks[1][0] <= marks[-1][0] - self.span_s:
            marks.popleft()

    def per_second(self) -> float:
        marks = self._marks
        if len(marks) < 2 or marks[-1][0] <= marks[0][0]:
            return 0.0
        return (marks[-1][1] - marks[0][1]) / (marks[-1][0] - marks[0][0])
