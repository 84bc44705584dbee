"""A host-side twin of the EMS22 flow sensor for demos and closed-loop tests.

It turns the extruder's commanded filament position (sampled at the sensor's
sample times) into the exact bytes the MCU would send: 24-bit SPI reads in
flowloop's record layout, so the simulated path runs through the same
decoder and grip estimator as the real sensor.

The filament model: the hotend melts at most what a material profile's line
(`flowloop.material.profile.Line`, the one melt line of the project) gives
at the hotend temperature. When the demanded flow (smoothed over
`melt_time_s`, the hotend's lag) exceeds it, the feeder slips and only
capacity/demand of the commanded filament moves. Retractions always move.

The hotend temperature is either given (the nozzle is at its target at
once) or, with a `HotendModel` (flowloop.control.hotend, the one thermal
model), simulated from the heater's target: heating takes time, the dead
time and lag delay it, and the filament that moves cools the nozzle.
"""

from __future__ import annotations

import math
from typing import List, Optional, Sequence, Tuple

import numpy as np

from ..control.hotend import HotendModel
from ..errors import FlowloopError
from ..material.profile import FlowLine, Line
from . import ems22

# The twin's default hotend: 10 mm^3/s at 200 C, 0.2 mm^3/s more per degree
DEFAULT_MELT_LINE = FlowLine(slope_mm3_s_per_c=0.2, temp_c=200.0,
                             flow_mm3_s=10.0).line()
DEFAULT_NOISE_COUNTS = 0.34   # 0.12 deg RMS per the datasheet
SENSOR_SCALE_RANGE = (0.5, 2.0)


MELT_SCALE_RANGE = (0.1, 2.0)
# The twin's melt lag: how long its melt takes to follow a change of demand
# (a first-order lag on the demand it melts against)
DEFAULT_MELT_TIME_S = 0.05
MELT_TIME_RANGE = (0.01, 2.0)


def scaled_line(line: Line, scale: float) -> Line:
    """The same melt line melting `scale` times as much at every temperature
    (a twin weaker or stronger than its profile says)."""
    ceiling = None if line.ceiling is None else scaled_line(line.ceiling, scale)
    return Line(scale * line.slope_mm3_s_per_c, scale * line.intercept_mm3_s,
                ceiling)


def melt_grip(melt: Line, demand_mm3_s: float, temp_c: float) -> float:
    """Share of commanded filament that moves at this demand."""
    capacity = max(0.0, melt.flow_mm3_s(temp_c))
    if demand_mm3_s <= capacity:
        return 1.0
    return capacity / demand_mm3_s


def raw_reads(frames: np.ndarray, bit_offset: int, idle_do: int = 1) -> np.ndarray:
    """24-bit reads for frames at a bit offset (0 or 1), DI tied low: the
    spi_read_model result, computed in bulk."""
    frames = np.asarray(frames, dtype=np.int64)
    word = (frames << (8 - bit_offset)) | ((idle_do << 23) if bit_offset else 0)
    return np.stack([(word >> 16) & 0xFF, (word >> 8) & 0xFF, word & 0xFF],
                    axis=1).astype(np.uint8)


class SimulatedEms22:
    def __init__(self, melt: Line = DEFAULT_MELT_LINE,
                 counts_per_mm: float = ems22.DEFAULT_COUNTS_PER_MM,
                 sensor_scale: float = 1.0,
                 noise_counts: float = DEFAULT_NOISE_COUNTS,
                 spi_mode: int = 2, filament_area_mm2: float = 2.405,
                 melt_time_s: float = DEFAULT_MELT_TIME_S, seed: int = 0,
                 hotend: Optional[HotendModel] = None):
        self.melt = melt
        self.hotend = hotend
        self.counts_per_mm = counts_per_mm
        self.sensor_scale = sensor_scale
        self.noise_counts = noise_counts
        self.bit_offset = ems22.bit_offset_for_mode(spi_mode)
        self.filament_area_mm2 = filament_area_mm2
        self.melt_time_s = melt_time_s
        self.rng = np.random.default_rng(seed)
        self.filament_mm = 0.0      # filament that really moved
        self.demand_mm3_s = 0.0     # smoothed demand
        self.fault: Optional[str] = None
        self.next_index = 0
        self.sequence = 0
        self._last: Optional[Tuple[float, float]] = None

    def set_fault(self, fault: Optional[str]) -> None:
        """Make the twin misbehave: 'missing', 'magnet', 'parity' or None."""
        if fault not in (None, "missing", "magnet", "parity"):
            raise FlowloopError(f"unknown simulated fault '{fault}'")
        self.fault = fault

    def temp_c(self, target_c: float) -> float:
        """The nozzle temperature: the hotend model's, else the target."""
        return target_c if self.hotend is None else self.hotend.temp_c

    def advance(self, times: Sequence[float], commanded_mm: Sequence[float],
                temp_c: float) -> np.ndarray:
        """True filament position at each sample time (mm). temp_c is the
        nozzle temperature, or with a hotend model the heater's target."""
        hotend = self.hotend
        if hotend is not None and len(times):
            hotend.set_target(times[0], temp_c)
        out = np.empty(len(times))
        for i, (t, c) in enumerate(zip(times, commanded_mm)):
            if self._last is not None:
                t0, c0 = self._last
                dt, dc = t - t0, c - c0
                if dt > 0:
                    alpha = 1.0 - math.exp(-dt / self.melt_time_s)
                    demand = max(0.0, dc) / dt * self.filament_area_mm2
                    self.demand_mm3_s += alpha * (demand - self.demand_mm3_s)
                nozzle_c = temp_c if hotend is None else hotend.temp_c
                grip = (melt_grip(self.melt, self.demand_mm3_s, nozzle_c)
                        if dc > 0 else 1.0)
                self.filament_mm += dc * grip
                if hotend is not None and dt > 0:
                    melted = max(0.0, dc * grip) / dt * self.filament_area_mm2
                    hotend.advance(t, melted)
            self._last = (t, c)
            out[i] = self.filament_mm
        return out

    def frames(self, filament_mm: np.ndarray) -> np.ndarray:
        counts = filament_mm * self.counts_per_mm * self.sensor_scale
        if self.noise_counts > 0:
            counts = counts + self.rng.normal(0.0, self.noise_counts, len(counts))
        position = np.rint(counts).astype(np.int64) % ems22.POSITIONS
        frames = position << ems22.POSITION_SHIFT | ems22.OCF
        if self.fault == "magnet":
            frames |= ems22.MAGINC | ems22.MAGDEC
        frames |= ems22.parity_bits(frames)
        if self.fault == "parity":
            frames ^= 1 << 9
        if self.fault == "missing":
            frames[:] = 0xFFFF
        return frames

    def messages(self, times: Sequence[float], commanded_mm: Sequence[float],
                 temp_c: float) -> List[Tuple[int, bytes]]:
        """(sequence, sensor_bulk_data payload) for one sample per time."""
        if not len(times):
            return []
        frames = self.frames(self.advance(times, commanded_mm, temp_c))
        raws = raw_reads(frames, self.bit_offset)
        if self.fault == "missing":
            raws[:] = 0xFF
        # read when the host will time them (pipeline.due_times): plain
        records = [(ems22.PLAIN_TCODE, bytes(r)) for r in raws]
        payloads = ems22.pack_messages(self.next_index, records, self.bit_offset)
        self.next_index += len(records)
        out = []
        for payload in payloads:
            out.append((self.sequence, payload))
            self.sequence = (self.sequence + 1) & 0xFFFF
        return out
