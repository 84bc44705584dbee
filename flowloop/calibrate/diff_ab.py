"""Differential A/B rotation_distance calibration from caliper readings.

Method (CmdrEmily, "Differential Calibration for A/B-steps on CoreXY
Printers", 2023): solid, symmetric, freestanding pylons printed in a row
shrink about their own centres, so the distance between their centres is
free of shrinkage. A caliper reading of the outside-to-outside distance
from pylon 1 to pylon k is d = scale * X + w + eps (X: nominal centre
distance, w: printed pylon width, eps: random error). With the nominal
outside-to-outside distance D = X + W, two rows cancel w:

    scale = (d2 - d1) / (D2 - D1)        new rotation_distance = old * scale

With more than two distances in a row, a least-squares line d = scale * D + c
over all of them gives scale, the printed width and residuals.

On CoreXY the row on the x = y diagonal moves only motor A (Klipper's
stepper_x) and the row on x = -y only motor B (stepper_y); on a cartesian
printer the rows lie along X and Y.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..errors import FlowloopError
from ..numbers import check_result, parse_numbers

# The paper's convergence target: 0.025 % (25 um per 100 mm).
CONVERGENCE_LIMIT = 2.5e-4
# Beyond this the readings are more likely wrong (swapped A/B, misread
# distance) than the belts that far off; FORCE/--force overrides.
MAX_SCALE_CHANGE = 0.02
# The most max_scale_change may be set to: a guard that lets a 20 % change
# through guards nothing (FORCE/--force is there for that).
MAX_SCALE_CHANGE_CEILING = 0.20
# A reading further than this from the median of its set is reported.
SLIP_THRESHOLD_MM = 0.05
# Median of n normal readings: its standard deviation is about
# sqrt(pi/2) * sigma / sqrt(n) (asymptotically; close enough from n = 3).
MEDIAN_EFFICIENCY = math.sqrt(math.pi / 2.0)
# How the error budget's random term is bounded (the paper uses 3 sigma).
COVERAGE_SIGMAS = 3.0

KINEMATICS = ("corexy", "cartesian")
# The paper's nominal D1 and D2 (mm): the defaults of the part and the commands.
NOMINAL_DISTANCES_MM = (10.0, 150.0)
AXIS_STEPPERS = {"a": "stepper_x", "b": "stepper_y"}
# D<k>= (mm): a row of pylons fits on a bed
NOMINAL_DISTANCE_PARAM = {"above": 0.0, "maximum": 1000.0}


# --- readings ------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class ReadingSet:
    """Repeated caliper readings of one outside-to-outside distance."""

    nominal_mm: float
    readings_mm: Tuple[float, ...]

    @property
    def median_mm(self) -> float:
        return float(np.median(self.readings_mm))

    def slipped(self, threshold_mm: float = SLIP_THRESHOLD_MM) -> Tuple[float, ...]:
        """Readings further than threshold_mm from the median of the set."""
        med = self.median_mm
        return tuple(r for r in self.readings_mm if abs(r - med) > threshold_mm)

    def spread_sigma_mm(self) -> Optional[float]:
        """Robust single-reading sigma (1.4826 * MAD); None below 3 readings."""
        if len(self.readings_mm) < 3:
            return None
        values = np.asarray(self.readings_mm)
        return float(1.4826 * np.median(np.abs(values - np.median(values))))


# --- error budget ----------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class ErrorBudget:
    """The paper's per-reading error budget (all in mm, worst case).

    The random caliper term is taken from the spread of the readings when
    there are at least 3 of them (never below the caliper's quantisation),
    otherwise from reading_error_mm (3 sigma of one reading). With 5
    readings spread as the paper assumes (3 sigma = 20 um) this is its
    budget: eps_max about 17 um, precision 0.025 % over D2 - D1 = 140 mm,
    accuracy 0.038 %.
    """

    bed_expansion_mm: float = 0.0024      # 1.2e-5/K steel, +-2 K, 100 mm
    filament_mm: float = 0.0029           # +-0.01 mm diameter, 0.5 mm line
    stepper_resolution_mm: float = 0.00078
    reading_error_mm: float = 0.020       # 3 sigma of one caliper reading
    caliper_resolution_mm: float = 0.01
    caliper_accuracy_mm: float = 0.02     # trueness over caliper_range_mm
    caliper_range_mm: float = 150.0

    def __post_init__(self):
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if not (math.isfinite(value) and value >= 0.0):
                raise FlowloopError(f"{field.name} must be a finite number >= 0")
        if self.caliper_range_mm <= 0.0:
            raise FlowloopError("caliper_range_mm must be positive")

    def reading_sigma_mm(self, reading_set: ReadingSet) -> float:
        quantisation = self.caliper_resolution_mm / math.sqrt(12.0)
        sigma = self.reading_error_mm / COVERAGE_SIGMAS
        spread = reading_set.spread_sigma_mm()
        if spread is not None:
            sigma = spread
        return max(sigma, quantisation)

    def measurement_mm(self, reading_set: ReadingSet) -> float:
        """Bound (3 sigma) of the median of the set."""
        n = len(reading_set.readings_mm)
        factor = MEDIAN_EFFICIENCY if n >= 3 else 1.0
        sigma = self.reading_sigma_mm(reading_set)
        return COVERAGE_SIGMAS * factor * sigma / math.sqrt(n)

    def eps_max_mm(self, reading_set: ReadingSet) -> float:
        """Worst-case error of one median distance: the terms added linearly."""
        return (self.bed_expansion_mm + self.filament_mm + self.stepper_resolution_mm
                + self.measurement_mm(reading_set))

    @property
    def trueness(self) -> float:
        return self.caliper_accuracy_mm / self.caliper_range_mm


# --- the estimator ---------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class AxisFit:
    """The scale of one motor (A or B) from one row of pylons."""

    scale: float
    precision: float          # worst-case random error of scale (fraction)
    uncertainty: float        # precision + caliper trueness (fraction)
    intercept_mm: float       # d = scale * D + intercept
    nominal_mm: Tuple[float, ...]
    medians_mm: Tuple[float, ...]
    residuals_mm: Tuple[float, ...]
    slipped: Tuple[Tuple[float, Tuple[float, ...]], ...]  # (nominal, readings)

    @property
    def uncertainty_pct(self) -> float:
        return 100.0 * self.uncertainty

    @property
    def uncertainty_um_per_100mm(self) -> float:
        return 1e5 * self.uncertainty

    @property
    def error_pct(self) -> float:
        return 100.0 * (self.scale - 1.0)

    def printed_width_mm(self, pylon_width_mm: float) -> float:
        """Printed pylon width: d = scale * (D - W) + w."""
        return self.intercept_mm + self.scale * pylon_width_mm

    def converged(self) -> bool:
        return is_converged(self.scale, self.uncertainty)


def is_converged(scale: float, uncertainty: float) -> bool:
    """The paper's stop rule: |scale - 1| below the uncertainty or 0.025 %."""
    return abs(scale - 1.0) < max(uncertainty, CONVERGENCE_LIMIT)


def fit_axis(reading_sets: Sequence[ReadingSet],
             budget: ErrorBudget = ErrorBudget()) -> AxisFit:
    """Scale of one axis from two or more reading sets of one row."""
    sets = sorted(reading_sets, key=lambda s: s.nominal_mm)
    if len(sets) < 2:
        raise FlowloopError("need readings of at least two distances (D1 and D2)")
    nominal = np.array([s.nominal_mm for s in sets], dtype=float)
    if not np.all(np.isfinite(nominal)) or np.any(nominal <= 0.0):
        raise FlowloopError("nominal distances must be positive numbers")
    if np.any(np.diff(nominal) <= 0.0):
        raise FlowloopError("nominal distances must differ (D2 > D1)")
    medians = np.array([s.median_mm for s in sets])
    if np.any(np.diff(medians) <= 0.0):
        pairs = ", ".join(f"d({s.nominal_mm:g})={m:.3f}"
                          for s, m in zip(sets, medians))
        raise FlowloopError(
            f"readings must grow with the nominal distance, got {pairs}")
    # overflow (a D2=1e308) gives a scale that is not finite: calibrate()
    # refuses it, so numpy need not warn
    with np.errstate(all="ignore"):
        centred = nominal - nominal.mean()
        sxx = float(np.dot(centred, centred))
        scale = float(np.dot(centred, medians - medians.mean()) / sxx)
        intercept = float(medians.mean() - scale * nominal.mean())
        residuals = medians - (scale * nominal + intercept)
        # Worst case of a linear estimator: sum of |weight| * eps_max; for
        # two distances this is the paper's (eps1 + eps2) / (D2 - D1).
        eps = np.array([budget.eps_max_mm(s) for s in sets])
        precision = float(np.sum(np.abs(centred) * eps) / sxx)
    slipped = tuple((s.nominal_mm, s.slipped()) for s in sets if s.slipped())
    return AxisFit(scale=scale, precision=precision,
                   uncertainty=precision + budget.trueness,
                   intercept_mm=intercept,
                   nominal_mm=tuple(float(v) for v in nominal),
                   medians_mm=tuple(float(v) for v in medians),
                   residuals_mm=tuple(float(v) for v in residuals),
                   slipped=slipped)


# --- a whole calibration step ----------------------------------------------

@dataclasses.dataclass(frozen=True)
class AxisResult:
    axis: str                 # "a" or "b"
    stepper: str              # Klipper section whose rotation_distance changes
    old_rotation_distance: float
    new_rotation_distance: float
    fit: AxisFit

    def as_dict(self) -> Dict:
        return {"axis": self.axis, "stepper": self.stepper,
                "old_rotation_distance": self.old_rotation_distance,
                "rotation_distance": self.new_rotation_distance,
                "scale": self.fit.scale,
                "error_pct": self.fit.error_pct,
                "uncertainty_pct": self.fit.uncertainty_pct,
                "uncertainty_um_per_100mm": self.fit.uncertainty_um_per_100mm,
                "converged": self.fit.converged(),
                "medians_mm": list(self.fit.medians_mm),
                "residuals_mm": list(self.fit.residuals_mm)}


@dataclasses.dataclass(frozen=True)
class Calibration:
    kinematics: str
    a: AxisResult
    b: AxisResult

    @property
    def converged(self) -> bool:
        return self.a.fit.converged() and self.b.fit.converged()

    def axes(self) -> Tuple[AxisResult, AxisResult]:
        return (self.a, self.b)

    def json_summary(self) -> Dict:
        """The CLI's --json object."""
        out: Dict = {}
        for r in self.axes():
            out[r.axis] = {"scale": r.fit.scale,
                           "rotation_distance": r.new_rotation_distance,
                           "uncertainty_pct": r.fit.uncertainty_pct}
        out["converged"] = self.converged
        return out

    def as_dict(self) -> Dict:
        return {"kinematics": self.kinematics, "a": self.a.as_dict(),
                "b": self.b.as_dict(), "converged": self.converged}

    def report_lines(self) -> List[str]:
        label = {"corexy": {"a": "A (x=y diagonal)", "b": "B (x=-y diagonal)"},
                 "cartesian": {"a": "X axis", "b": "Y axis"}}[self.kinematics]
        lines = []
        for r in self.axes():
            f = r.fit
            lines.append(
                f"{label[r.axis]} [{r.stepper}]: scale {f.scale:.6f} "
                f"({f.error_pct:+.4f} %, +-{f.uncertainty_pct:.4f} % = "
                f"{f.uncertainty_um_per_100mm:.0f} um/100 mm), rotation_distance "
                f"{r.old_rotation_distance:.6f} -> {r.new_rotation_distance:.6f}"
                + (" converged" if f.converged() else ""))
            if len(f.residuals_mm) > 2:
                res = ", ".join(f"{v * 1000:+.0f}" for v in f.residuals_mm)
                lines.append(f"  least-squares residuals (um): {res}")
            for nominal, readings in f.slipped:
                lines.append(f"  check the readings of {nominal:g} mm: "
                             f"{', '.join(f'{v:g}' for v in readings)} "
                             f"are far from the median (ignored by it)")
        if self.converged:
            lines.append("Converged: both scales are within the measurement "
                         "uncertainty of 1. Calibrate skew next.")
        else:
            lines.append("Not converged yet: apply the new values, re-home, "
                         "print the pylons again and measure.")
        return lines


def check_kinematics(kinematics: str) -> str:
    kin = str(kinematics).strip().lower()
    if kin not in KINEMATICS:
        raise FlowloopError(
            f"kinematics '{kinematics}' is not supported: differential A/B "
            f"calibration needs corexy or cartesian")
    return kin


def check_rotation_distance(value, name: str) -> float:
    try:
        rd = float(value)
    except (TypeError, ValueError):
        raise FlowloopError(f"{name}: '{value}' is not a number") from None
    if not (math.isfinite(rd) and rd > 0.0):
        raise FlowloopError(f"{name} must be a positive number, got {value}")
    return rd


def check_max_scale_change(max_scale_change: float) -> float:
    """The refusal threshold: above 0, at most MAX_SCALE_CHANGE_CEILING."""
    return check_result(max_scale_change, "max_scale_change", above=0.0,
                        maximum=MAX_SCALE_CHANGE_CEILING)


def calibrate(kinematics: str,
              rotation_distance_a: float, rotation_distance_b: float,
              readings_a: Sequence[ReadingSet], readings_b: Sequence[ReadingSet],
              budget: ErrorBudget = ErrorBudget(),
              max_scale_change: float = MAX_SCALE_CHANGE,
              force: bool = False, force_hint: str = "FORCE=1") -> Calibration:
    """Validate everything for both axes, then return the new values.

    Nothing is applied here; a caller applies both axes or neither.
    """
    kin = check_kinematics(kinematics)
    check_max_scale_change(max_scale_change)
    rds = {"a": check_rotation_distance(rotation_distance_a, "rotation_distance A"),
           "b": check_rotation_distance(rotation_distance_b, "rotation_distance B")}
    results = {}
    for axis, sets in (("a", readings_a), ("b", readings_b)):
        try:
            fit = fit_axis(sets, budget)
        except FlowloopError as e:
            raise FlowloopError(f"{axis.upper()}: {e}") from None
        # nan compares false with everything: refused here, FORCE or not
        check_result(fit.scale, f"{axis.upper()}: scale", above=0.0)
        if abs(fit.scale - 1.0) > max_scale_change and not force:
            raise FlowloopError(
                f"{axis.upper()}: scale {fit.scale:.5f} is {fit.error_pct:+.2f} % "
                f"from 1, more than {100 * max_scale_change:g} %: check the readings "
                f"and D1/D2, or add {force_hint}")
        # the option's own bound (Klipper: rotation_distance above 0)
        new_rd = check_result(rds[axis] * fit.scale,
                              f"{axis.upper()}: new rotation_distance", above=0.0)
        results[axis] = AxisResult(axis=axis, stepper=AXIS_STEPPERS[axis],
                                   old_rotation_distance=rds[axis],
                                   new_rotation_distance=new_rd, fit=fit)
    return Calibration(kinematics=kin, a=results["a"], b=results["b"])


MAX_DISTANCES = 9  # D1..D9: a row of up to 10 pylons


def numbered_reading_sets(axis: str, readings: Dict[int, str],
                          nominals: Dict[int, float]) -> List[ReadingSet]:
    """Reading sets from numbered parameters: readings[k] is what A<k>= (or
    B<k>=) gave, nominals[k] the distance D<k> (given or default)."""
    name = axis.upper()
    for k in (1, 2):
        if k not in readings:
            raise FlowloopError(f"{name}{k}=<readings> is missing")
    for k in readings:
        if not 1 <= k <= MAX_DISTANCES:
            raise FlowloopError(f"{name}{k}: distances are numbered 1 to "
                                f"{MAX_DISTANCES}")
        if nominals.get(k) is None:
            raise FlowloopError(f"{name}{k} needs D{k}=<nominal distance>")
    ks = sorted(readings)
    return reading_sets([nominals[k] for k in ks], [readings[k] for k in ks], axis,
                        numbers=ks)


def check_nominals_used(given: Sequence[int], used: Sequence[int]) -> None:
    """A D<k> given without A<k> or B<k> readings is a typo, not a default."""
    for k in sorted(set(given) - set(used)):
        raise FlowloopError(f"D{k} is given but neither A{k} nor B{k} readings")


def reading_sets(nominals: Sequence[float], readings: Sequence, axis: str,
                 numbers: Optional[Sequence[int]] = None) -> List[ReadingSet]:
    """Pair nominal distances with reading lists (strings or numbers);
    numbers are the user's names for them (D<k>, A<k>), default 1, 2, ..."""
    if len(nominals) != len(readings):
        raise FlowloopError(f"{axis.upper()}: {len(readings)} reading sets for "
                            f"{len(nominals)} distances")
    numbers = list(numbers or range(1, len(nominals) + 1))
    for i in range(1, len(nominals)):
        low, high = nominals[i - 1], nominals[i]
        if not high > low:
            raise FlowloopError(f"D{numbers[i]} ({high:g} mm) must be greater than "
                                f"D{numbers[i - 1]} ({low:g} mm)")
    return [ReadingSet(float(nominal),
                       parse_numbers(values, f"{axis.upper()}{k}", what="reading",
                                     positive=True, decimal_comma_refused=True))
            for k, nominal, values in zip(numbers, nominals, readings)]


# --- iteration history -----------------------------------------------------

def history_entry(calibration: Calibration, iteration: int) -> Dict:
    """One iteration as plain, JSON-able data."""
    entry = {"iteration": iteration, "kinematics": calibration.kinematics,
             "converged": calibration.converged}
    for r in calibration.axes():
        entry[r.axis] = {"stepper": r.stepper,
                         "old_rotation_distance": r.old_rotation_distance,
                         "rotation_distance": r.new_rotation_distance,
                         "scale": r.fit.scale,
                         "uncertainty_pct": r.fit.uncertainty_pct}
    return entry


def append_history(history: Sequence[Dict], calibration: Calibration,
                   keep: Optional[int] = None) -> List[Dict]:
    """A new history list with this calibration appended (input unchanged),
    numbered on from the last entry, trimmed to the last `keep` entries."""
    history = list(history)
    number = history[-1]["iteration"] + 1 if history else 1
    history.append(history_entry(calibration, number))
    return history[-keep:] if keep else history


def check_history(data, source: str) -> List[Dict]:
    """Earlier iterations as read back from JSON: a list of history_entry
    records, else a one-line FlowloopError."""
    if not isinstance(data, list):
        raise FlowloopError(f"history {source} is not a JSON list")
    for i, entry in enumerate(data, start=1):
        ok = (isinstance(entry, dict) and isinstance(entry.get("iteration"), int)
              and isinstance(entry.get("converged"), bool)
              and all(isinstance(entry.get(axis), dict)
                      and isinstance(entry[axis].get("scale"), (int, float))
                      and isinstance(entry[axis].get("rotation_distance"),
                                     (int, float))
                      for axis in ("a", "b")))
        if not ok:
            raise FlowloopError(f"history {source}: entry {i} is not an "
                                f"ab-calibrate iteration")
    return list(data)


def history_lines(history: Sequence[Dict]) -> List[str]:
    lines = []
    for e in history:
        lines.append(
            f"#{e['iteration']}: A scale {e['a']['scale']:.6f} rd "
            f"{e['a']['rotation_distance']:.6f}, B scale {e['b']['scale']:.6f} rd "
            f"{e['b']['rotation_distance']:.6f}"
            + (" converged" if e["converged"] else ""))
    return lines


# --- bed thermal equilibrium ------------------------------------------------

# WAIT_BED_EQUILIBRIUM's defaults ([diff_ab_calibrate] equilibrium_* options)
EQUILIBRIUM_TOLERANCE_PCT_PER_MIN = 0.5
EQUILIBRIUM_WINDOW_S = 120.0
EQUILIBRIUM_BAND_C = 2.0
EQUILIBRIUM_TIMEOUT_S = 1800.0

class BedEquilibrium:
    """Decides when the bed heater's power has stopped falling.

    The paper measures on a bed held within +-2 K at thermal equilibrium;
    the heater's power still falling means the bed and what it heats are
    still warming up. Feed it (time, power 0..1, temperature, target)
    samples; state() is one of:
      'off'          the heater has no target: nothing to wait for
      'heating'      the temperature is not yet within band_c of the target
      'settling'     at temperature, but not a whole window of samples yet
      'falling'      the power over the last window still falls faster than
                     the tolerance
      'equilibrium'  the power no longer falls (slope >= -tolerance)
    """

    def __init__(self, tolerance_pct_per_min: float = EQUILIBRIUM_TOLERANCE_PCT_PER_MIN,
                 window_s: float = EQUILIBRIUM_WINDOW_S,
                 band_c: float = EQUILIBRIUM_BAND_C):
        if not (math.isfinite(tolerance_pct_per_min) and tolerance_pct_per_min > 0):
            raise FlowloopError("TOLERANCE must be a positive number (% per minute)")
        if not (math.isfinite(window_s) and window_s > 0):
            raise FlowloopError("the equilibrium window must be a positive time")
        if not (math.isfinite(band_c) and band_c > 0):
            raise FlowloopError("the temperature band must be positive")
        self.tolerance_pct_per_min = tolerance_pct_per_min
        self.window_s = window_s
        self.band_c = band_c
        self._samples: List[Tuple[float, float]] = []   # (time, power) at temperature
        self._target = 0.0
        self._at_temperature = False

    def add(self, time_s: float, power: float, temperature_c: float,
            target_c: float) -> str:
        self._target = target_c
        self._at_temperature = bool(target_c) and abs(temperature_c - target_c) \
            <= self.band_c
        if not self._at_temperature:
            self._samples = []
        else:
            self._samples.append((time_s, power))
            start = time_s - self.window_s
            while len(self._samples) > 2 and self._samples[1][0] <= start:
                self._samples.pop(0)
        return self.state()

    def covered_s(self) -> float:
        if len(self._samples) < 2:
            return 0.0
        return self._samples[-1][0] - self._samples[0][0]

    def slope_pct_per_min(self) -> Optional[float]:
        """Power trend over the window, % of full power per minute."""
        if len(self._samples) < 3:
            return None
        t, p = np.array(self._samples).T
        t = t - t.mean()
        denom = float(np.dot(t, t))
        if denom <= 0.0:
            return None
        return float(np.dot(t, p - p.mean()) / denom) * 100.0 * 60.0

    def state(self) -> str:
        if not self._target:
            return "off"
        if not self._at_temperature:
            return "heating"
        if self.covered_s() < 0.95 * self.window_s:
            return "settling"
        slope = self.slope_pct_per_min()
        if slope is None or slope < -self.tolerance_pct_per_min:
            return "falling"
        return "equilibrium"
