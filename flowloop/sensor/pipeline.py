"""The flow sensor's pipeline, host-free: sensor_bulk_data payloads in,
grip windows and a status out.

decode (ems22.Decoder: records, unwrapped counts, error kinds) -> time
(each record's MCU clock, then print time) -> filament (sign, counts per mm)
-> grip windows (grip.GripEstimator) -> faults (ems22.FaultMonitor) -> the
status policy (grip is not reported while the sensor is faulted, and a
window closed while faulted goes out unjudged, reason FAULT). Every window
carries the fault's name (Window.fault): subscribers learn of a fault by
that one path, from a window of no filament when none closed (samples that
are all bad close none).

Both of [flow_sensor]'s sources feed it the same way: the real EMS22 the
payloads its MCU sent, the simulated twin the payloads it made. What it needs
of the printer it asks through one narrow interface (Motion): the extruder's
commanded and planned positions, the hotend's temperature and the planned
moves a window spans. The klippy adapter (klippy_extras/flow_sensor/)
keeps the MCU, the trapq reads, the step clock and the commands.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable, List, Optional, Tuple

import numpy as np

from ..window import FAULT, TOO_LITTLE_MOTION, Window
from . import ems22
from . import grip as fl_grip

# (print_time, move_t, start_v, accel, start_x, x_r): a trapq move
Move = Tuple[float, float, float, float, float, float]


@dataclass(frozen=True)
class SampleTiming:
    """How the source's records map to MCU clocks (query_ems22's terms) and
    clocks to print time (klippy's mcu.clock_to_print_time)."""
    start_clock: int
    rest_ticks: int
    time_shift: int
    clock_to_print_time: Callable[[float], float]


def due_times(timing: SampleTiming, next_index: int,
              before: float) -> List[float]:
    """Print times of the reads the MCU's timer schedules from record
    next_index on, up to (not at) print time `before`: when a twin that
    samples as the MCU would owes its next records. Each read comes when
    the host will time a plain record's (ems22.PLAIN_TCODE)."""
    times: List[float] = []
    to_time, rest = timing.clock_to_print_time, timing.rest_ticks
    start = timing.start_clock + ems22.read_delay_ticks(ems22.PLAIN_TCODE,
                                                        timing.time_shift)
    while True:
        t = to_time(start + (next_index + len(times)) * rest)
        if t >= before:
            return times
        times.append(t)


class Motion:
    """What the pipeline asks of the printer (the adapter implements it)."""

    def commanded_at(self, times: np.ndarray) -> np.ndarray:
        """The extruder's commanded filament position at each print time."""
        raise NotImplementedError

    def planned_moves(self, start: float, end: float) -> List[Move]:
        """The extruder's planned moves (its trapq) from start to end."""
        raise NotImplementedError

    def temp_c(self) -> float:
        """The hotend's temperature now (what windows are stamped with)."""
        raise NotImplementedError


@dataclass(frozen=True)
class Settings:
    counts_per_mm: float = ems22.DEFAULT_COUNTS_PER_MM
    direction_sign: float = 1.0           # +1 forward, -1 reverse
    spi_mode: int = ems22.DEFAULT_SPI_MODE
    sample_period_s: float = ems22.DEFAULT_SAMPLE_PERIOD_S
    window_mm: float = fl_grip.DEFAULT_WINDOW_MM
    calibration: float = 1.0
    fault_samples: int = ems22.DEFAULT_FAULT_SAMPLES


@dataclass(frozen=True)
class Batch:
    """What one feed produced: the closed windows as subscribers get them,
    a fault that started (its name, once), and the good samples."""
    windows: Tuple[Window, ...] = ()
    fault_started: Optional[str] = None
    times: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    sensor_mm: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    commanded_mm: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    calibration: float = 1.0

    def dump_rows(self) -> List[Tuple[float, float, float]]:
        """(print time, sensor filament in extruder mm, commanded mm) per
        good sample, as flow_sensor/dump_flow sends them."""
        cal = self.calibration
        return [(round(t, 6), round(s / cal, 5), round(c, 5))
                for t, s, c in zip(np.asarray(self.times).tolist(),
                                   np.asarray(self.sensor_mm).tolist(),
                                   np.asarray(self.commanded_mm).tolist())]


class SensorPipeline:
    def __init__(self, settings: Settings):
        self.settings = settings
        self.decoder = ems22.Decoder(
            bit_offset=ems22.bit_offset_for_mode(settings.spi_mode),
            max_counts_per_record=ems22.max_counts_per_record(
                settings.sample_period_s, settings.counts_per_mm))
        self.grip = fl_grip.GripEstimator(window_mm=settings.window_mm,
                                          calibration=settings.calibration)
        self.faults = ems22.FaultMonitor(settings.fault_samples)
        self.rate = fl_grip.SampleRate()
        # whether windows get their commanded flows (a subscriber wants them)
        self.want_flows = False
        self._status: Optional[dict] = None   # until the next change
        self._fault_told: Optional[str] = None  # the last window's fault

    # --- what the adapter drives -----------------------------------------------
    def restart(self) -> None:
        """A new MCU query: records count from 0 again."""
        self.decoder.reset()
        self._status = None

    def set_calibration(self, calibration: float) -> None:
        """Sensor mm per extruder mm from now on (grip starts afresh)."""
        self.grip.calibration = calibration
        self.grip.reset()
        self._status = None

    def set_filament_area(self, area_mm2: float) -> None:
        self.grip.filament_area_mm2 = area_mm2
        self._status = None    # the flows are in mm^3/s

    def feed(self, messages, timing: SampleTiming, motion: Motion) -> Batch:
        """Decode (sequence, payload) pairs from the source and judge them."""
        self._status = None
        samples = self.decoder.decode(messages)
        started = self.faults.update(samples)
        valid = samples.valid
        windows: List[Window] = []
        if not valid.any():
            windows = self._fault_change(samples, timing, windows)
            return Batch(tuple(windows), started,
                         calibration=self.grip.calibration)
        clocks = ems22.sample_clocks(samples, timing.start_clock,
                                     timing.rest_ticks,
                                     timing.time_shift)[valid]
        times = ems22.print_times(clocks, timing.clock_to_print_time)
        sensor_mm = (self.settings.direction_sign * samples.counts[valid]
                     / self.settings.counts_per_mm)
        commanded = motion.commanded_at(times)
        nominal = fl_grip.trapq_positions(
            motion.planned_moves(float(times[0]), float(times[-1])), times)
        for window in self.grip.add(times, sensor_mm, commanded,
                                    motion.temp_c(), nominal,
                                    samples.breaks[valid]):
            started = self.faults.note_window(window.reason) or started
            windows.append(self._judged(window, motion))
        windows = self._fault_change(samples, timing, windows)
        self.rate.add(times)
        return Batch(tuple(windows), started, times, sensor_mm,
                     np.asarray(commanded), self.grip.calibration)

    def _judged(self, window: Window, motion: Motion) -> Window:
        """The window as subscribers get it: unjudged while faulted, else
        with what it asked for over time (read while the trapq still holds
        the moves) if a subscriber learns the capacity from it."""
        fault = self.faults.fault
        if fault is not None:
            return dataclasses.replace(window, grip=None, reason=FAULT,
                                       fault=fault)
        if window.grip is not None and self.want_flows:
            return dataclasses.replace(window, commanded_flows=fl_grip.window_flows(
                motion.planned_moves(window.start_time, window.end_time),
                window.start_time, window.end_time,
                self.grip.filament_area_mm2))
        return window

    def _fault_change(self, samples, timing: SampleTiming,
                      windows: List[Window]) -> List[Window]:
        """The batch's windows, and a window of no filament at its last
        record if the fault started or cleared and no window says so."""
        fault = self.faults.fault
        if windows:
            self._fault_told = windows[-1].fault
        if fault == self._fault_told or not len(samples.status):
            return windows
        self._fault_told = fault
        clock = ems22.sample_clocks(samples, timing.start_clock,
                                    timing.rest_ticks, timing.time_shift)[-1:]
        at = float(ems22.print_times(clock, timing.clock_to_print_time)[0])
        return windows + [Window(at, at, 0.0, 0.0, None, TOO_LITTLE_MOTION,
                                 fault=fault)]

    # --- what the adapter reads ------------------------------------------------
    @property
    def fault(self) -> Optional[str]:
        return self.faults.fault

    @property
    def calibration(self) -> float:
        return self.grip.calibration

    @property
    def time_lost(self) -> bool:
        """The MCU lost count of its reads: the query must restart."""
        return self.decoder.time_lost

    def position_at_or_after(self, print_time: float) -> Optional[float]:
        """The filament the sensor measured (sensor mm: before the
        calibration, what the calibrations compare with the extruder's)
        once samples reach print_time (less a sample period), else None."""
        last = self.grip.last_time
        if last is None or last < print_time - self.settings.sample_period_s:
            return None
        return self.grip.filament_position * self.grip.calibration

    def status(self) -> dict:
        """[flow_sensor]'s get_status(): grip is hidden while faulted."""
        if self._status is None:
            self._status = self._compute_status()
        return self._status

    def _compute_status(self) -> dict:
        measured, commanded = self.grip.flows()
        position = self.grip.filament_position
        position = None if position is None else round(float(position), 4)
        grip = self.grip.grip
        fault = self.faults.fault
        return {
            'grip': None if grip is None or fault else round(float(grip), 4),
            'measured_flow': round(float(measured), 3),
            'commanded_flow': round(float(commanded), 3),
            'filament_position': position,
            'sample_rate': round(self.rate.per_second(), 1),
            'samples': self.rate.total,
            'errors': dict(self.faults.errors),
            'fault': fault,
            'calibration': round(self.grip.calibration, 6),
        }

    def fault_message(self, name: str, fault: str) -> str:
        return (f"flow_sensor {name}: fault '{fault}' ({self.faults.limit}"
                " consecutive bad samples, or stuck windows); grip is not"
                " judged until it clears")
