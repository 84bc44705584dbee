"""Simulated prints for the nozzle health tests and docs/nozzle_health.md:
the twin (flowloop.sensor.twin) melts a share of what the profile says,
its hotend the thermal model, its filament read as the EMS22 would (counts,
noise), the grip windows closed by the sensor's estimator."""

from __future__ import annotations

import dataclasses
from typing import List, Sequence, Tuple

import numpy as np

from flowloop.control.hotend import HotendModel
from flowloop.control.nozzle_health import profile_capacity
from flowloop.material.profile import min_grip_of, profile_from_dict, profile_line
from flowloop.sensor import ems22
from flowloop.sensor.grip import FLOW_PIECE_S, GripEstimator
from flowloop.sensor.twin import DEFAULT_NOISE_COUNTS, SimulatedEms22, scaled_line
from flowloop.window import Window
from tests.samples import twin_known

PROFILE = profile_from_dict(twin_known())    # 6 mm^3/s at 210 degC, 0.12/degC
LINE = profile_line(PROFILE)
MIN_GRIP = min_grip_of(PROFILE)
AREA = 2.405
TEMP_C = 210.0
SAMPLE_S = 0.004
BATCH_S = 0.1
# (share of the profile's capacity, seconds): a part's layer, printed at
# the capacity the limiter's model allows (1.0), perimeters slower, travel
LAYER: Tuple[Tuple[float, float], ...] = (
    (0.35, 4.0), (0.0, 0.4), (1.0, 3.0), (0.0, 0.3), (0.9, 2.0),
    (0.0, 0.3), (0.45, 3.0), (0.0, 0.5))


def simulate_print(ratio: float, seed: int = 0, layers: int = 6,
                   noise_counts: float = DEFAULT_NOISE_COUNTS,
                   program: Sequence[Tuple[float, float]] = LAYER,
                   temp_c: float = TEMP_C) -> List[Window]:
    """The grip windows of one print on a hotend melting `ratio` of its
    profile's capacity."""
    rng = np.random.default_rng(seed)
    hotend = HotendModel(temp_c=temp_c, target_c=temp_c)
    melt = scaled_line(LINE, MIN_GRIP * ratio)
    twin = SimulatedEms22(melt, filament_area_mm2=AREA, hotend=hotend,
                          noise_counts=0.0)
    grip = GripEstimator(filament_area_mm2=AREA)
    capacity = profile_capacity(LINE, MIN_GRIP, temp_c)
    cpm = ems22.DEFAULT_COUNTS_PER_MM
    # the flow over time, one value per sample
    speeds = np.concatenate([np.full(int(round(s / SAMPLE_S)),
                                     share * capacity / AREA)
                             for share, s in list(program) * layers])
    times = (np.arange(len(speeds)) + 1) * SAMPLE_S
    commanded = np.cumsum(speeds) * SAMPLE_S
    windows: List[Window] = []
    step = int(round(BATCH_S / SAMPLE_S))
    for i in range(0, len(times), step):
        t, c = times[i:i + step], commanded[i:i + step]
        moved = twin.advance(t, c, temp_c)
        counts = np.rint(moved * cpm + rng.normal(0.0, noise_counts, len(t))) \
            if noise_counts > 0 else np.rint(moved * cpm)
        windows += grip.add(t, counts / cpm, c, temp_c=hotend.temp_c)
    return [with_flows(w, times, commanded) for w in windows]


def with_flows(window: Window, times: np.ndarray, commanded: np.ndarray
               ) -> Window:
    """The window with its commanded flow over time in pieces of about
    FLOW_PIECE_S, as the sensor's pipeline gives it to a subscriber that
    wants them (flowloop.sensor.grip.window_flows)."""
    start, end = window.start_time, window.end_time
    count = max(1, int(round((end - start) / FLOW_PIECE_S)))
    edges = np.linspace(start, end, count + 1)
    position = np.interp(edges, times, commanded)
    flows = np.maximum(np.diff(position), 0.0) * AREA * count / (end - start)
    return dataclasses.replace(window, commanded_flows=tuple(flows.tolist()))
