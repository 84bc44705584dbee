"""The flow sensor's two calibrations, from slow extrusions it measured:
CALIBRATE_FLOW_SENSOR (sensor mm per extruder mm, one extrusion per speed,
a line through the origin) and CALIBRATE_EXTRUDER_ROTATION_DISTANCE (the
extruder's rotation_distance from a sensor whose counts_per_mm is trusted).
The klippy adapter (klippy_extras/flow_sensor/) runs the extrusions."""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Sequence, Tuple

from ..errors import FlowloopError
from ..numbers import check_result, parse_numbers

CALIBRATION_RANGE = (0.5, 2.0)    # sensor mm per extruder mm
MAX_CALIBRATION_SPREAD = 0.02
MAX_CALIBRATION_SPREAD_RANGE = (0.001, 0.2)
DEFAULT_CALIBRATION_SPEEDS = "0.5,1,2"
CALIBRATION_LENGTH_MM = 20.0
CALIBRATION_LENGTH_RANGE = (1.0, 200.0)
ROTATION_DISTANCE_LENGTH_MM = 50.0
ROTATION_DISTANCE_LENGTH_RANGE = (5.0, 500.0)
ROTATION_DISTANCE_SPEED_MM_S = 1.0
MAX_ROTATION_DISTANCE_CHANGE = 0.2


class ReversedSensor(FlowloopError):
    """The sensor counts the other way round: filament fed forward reads
    backwards (which way it counts depends on the side the axle sits)."""


def _check_direction(ratio: float) -> None:
    low, high = CALIBRATION_RANGE
    if low <= -ratio <= high:
        raise ReversedSensor(f"the sensor counts backwards (ratio {ratio:.4f}):"
                             " its direction is reversed")


@dataclass(frozen=True)
class CalibrationFit:
    calibration: float            # sensor mm per extruder mm
    speeds: Tuple[float, ...]
    ratios: Tuple[float, ...]
    spread: float                 # (max - min) / calibration

    def describe(self) -> str:
        per_speed = ", ".join(f"{s:g} mm/s: {r:.5f}"
                              for s, r in zip(self.speeds, self.ratios))
        return (f"sensor mm per extruder mm at {per_speed}; "
                f"spread {100 * self.spread:.2f}%")


# mm/s of an extrude-only calibration move: slow enough that the feeder
# keeps its grip, fast enough that a length ends (and the toolhead can plan
# it: Klipper divides by the speed squared)
CALIBRATION_SPEED_RANGE = (0.05, 10.0)
MIN_CALIBRATION_SPEED, MAX_CALIBRATION_SPEED = CALIBRATION_SPEED_RANGE


def parse_speeds(text: str = DEFAULT_CALIBRATION_SPEEDS) -> List[float]:
    """CALIBRATE_FLOW_SENSOR's SPEEDS: at least two, in 0.05..10 mm/s."""
    speeds = parse_numbers(text, "SPEEDS", what="speed", minimum_count=2,
                           positive=True)
    too_fast = [v for v in speeds if v > MAX_CALIBRATION_SPEED]
    if too_fast:
        raise FlowloopError(f"SPEEDS: speed {too_fast[0]:g} is above "
                            f"{MAX_CALIBRATION_SPEED:g} mm/s")
    too_slow = [v for v in speeds if v < MIN_CALIBRATION_SPEED]
    if too_slow:
        raise FlowloopError(f"SPEEDS: speed {too_slow[0]:g} is below "
                            f"{MIN_CALIBRATION_SPEED:g} mm/s")
    return list(speeds)


def fit_calibration(speeds: Sequence[float], commanded_mm: Sequence[float],
                    measured_mm: Sequence[float],
                    max_spread: float = MAX_CALIBRATION_SPREAD) -> CalibrationFit:
    """Sensor mm per extruder mm from slow extrusions, one per speed.

    The fit is the least-squares line through the origin (sum m*c / sum c^2).
    If the per-speed ratios disagree by more than max_spread of the fit, the
    feeder slipped at some speed (or the sensor did): no fit is returned.
    """
    if not (len(speeds) == len(commanded_mm) == len(measured_mm)) or len(speeds) < 2:
        raise FlowloopError("calibration needs at least two speeds")
    for values in (commanded_mm, measured_mm):
        for value in values:
            check_result(value, "an extrusion's length")
    if min(commanded_mm) <= 0:
        raise FlowloopError("the extruder did not move forward")
    ratios = [m / c for m, c in zip(measured_mm, commanded_mm)]
    num = sum(m * c for m, c in zip(measured_mm, commanded_mm))
    cal = num / sum(c * c for c in commanded_mm)
    _check_direction(cal)
    if cal <= 0.05:
        raise FlowloopError(f"the sensor saw almost no filament (ratio {cal:.4f})")
    spread = (max(ratios) - min(ratios)) / cal
    fit = CalibrationFit(cal, tuple(speeds), tuple(ratios), spread)
    if spread > max_spread:
        raise FlowloopError(f"{fit.describe()}: the speeds disagree by more than "
                            f"{100 * max_spread:.2f}%")
    low, high = CALIBRATION_RANGE
    if not low <= cal <= high:
        raise FlowloopError(f"{fit.describe()}: calibration {cal:.4f} is outside "
                            f"{low:g}..{high:g}; check counts_per_mm")
    return fit


@dataclass(frozen=True)
class RotationDistanceChange:
    ratio: float                  # filament measured / commanded
    rotation_distance: float
    calibration: float            # sensor mm per extruder mm from now on


def rotation_distance_correction(rotation_distance: float, commanded_mm: float,
                                 measured_mm: float,
                                 max_change: float = MAX_ROTATION_DISTANCE_CHANGE
                                 ) -> RotationDistanceChange:
    """New rotation_distance from a sensor whose counts_per_mm is trusted.

    The extruder moved measured/commanded of what it was told, so its real
    rotation_distance is that much larger. With the correction applied, the
    trusted sensor and the extruder agree: calibration is 1.0 again.
    """
    check_result(measured_mm, "the sensor's length")
    if not commanded_mm > 0:   # nan too
        raise FlowloopError("the extruder did not move forward")
    ratio = measured_mm / commanded_mm
    _check_direction(ratio)
    if not 1 - max_change <= ratio <= 1 + max_change:
        raise FlowloopError(f"the sensor measured {measured_mm:.3f} mm for "
                            f"{commanded_mm:.3f} mm commanded (ratio {ratio:.4f}), "
                            f"more than {100 * max_change:.0f}% off")
    # the option's own bound (Klipper: rotation_distance above 0), checked
    # before anything is applied
    new = check_result(rotation_distance * ratio, "rotation_distance", above=0.0)
    return RotationDistanceChange(ratio, new, 1.0)
