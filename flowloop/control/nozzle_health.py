"""Nozzle health from grip: the hotend's melt capacity against its profile,
print after print.

With a profile, every judged grip window measures the hotend: the profile
says the hotend melts C_p(T) = min_grip * line(T) at temperature T (the
flow at which slip starts, the grip model's seed), and a hotend that melts
r * C_p(T) instead passes g(r) = mean(min(f, r * C_p(T))) / mean(f) of the
flow f it was asked for over the window. A print's ratio r = measured /
profile capacity is the r whose g(r) fits the windows' grips best (least
squares); windows that kept up far below the capacity say nothing about r,
windows near or above it pin it down.

The noise is measured, not assumed: windows whose peak flow the profile
says the hotend easily melts (below EASY_SHARE of C_p) should read grip 1,
and their scatter around 1 (RMS) is the sensor's grip noise sigma for this
print, feeder and calibration error included. The ratio's standard error
is sigma / sqrt(sum over windows of g'(r)^2), the least-squares error of a
one-parameter fit (its Fisher information).

A print gives no estimate, with the reason, when it had no profile, no
judged windows, too few easy windows to measure the noise, no window that
asked for more than the hotend melts (then it says only "at least"), or a
standard error above MAX_STANDARD_ERROR.

The evidence is a fixed-size sum (PrintEvidence: the squared residual and
the information at each ratio of RATIO_GRID, and the noise sums), so it is
kept for a print of any length, and the evidence between two moments is
the difference of two snapshots (`evidence_between`): klippy keeps one sum
per active profile, Moonraker takes it at a job's start and end.

Across prints (`judge`, per hotend and profile) a warning needs one of:
- persistence: the last PERSISTENT_PRINTS estimates each below
  1 - HEALTHY_MARGIN by more than Z_ONE_SIDED standard errors, or
- a trend: a weighted line through the last TREND_PRINTS estimates falls
  significantly (its slope Z_ONE_SIDED standard errors below 0, the error
  scaled up by the line's own scatter) and reaches the ratio at which the
  prints' own highest flows would slip below min_grip within
  TREND_HORIZON_PRINTS more prints, while the latest estimate is itself
  significantly below 1 - HEALTHY_MARGIN.
One print never warns: both need at least PERSISTENT_PRINTS estimates.
docs/nozzle_health.md works the numbers through.

What comes from outside (klippy's snapshots, a POST of a replayed print, the
stored history) is read whole here and refused with one line when any part
of it is not what a print can give (`PrintEvidence.from_dict`,
`post_request`); a stored print that no longer reads is skipped and said
(`load_history`), one record per job (`with_print`).
"""

from __future__ import annotations

import json
import math
import re
import uuid
from dataclasses import dataclass, field, replace
from typing import Any, Collection, Dict, List, Mapping, Optional, Sequence, Tuple
from urllib.parse import urlencode

import numpy as np

from ..errors import FlowloopError
from ..material.active import number_arg
from ..material.profile import (
    Line,
    Profile,
    check_name,
    check_working_point,
    min_grip_of,
    profile_line,
)
from ..report.dump import check_job_id
from ..window import Window
from .grip_model import DEFAULT_FILAMENT_AREA_MM2, judged_flow_mm3_s

# The ratios a print is judged at: measured / profile capacity.
RATIO_GRID = np.round(np.arange(0.30, 1.5001, 0.01), 4)
# A window whose peak flow is at most this share of the profile's capacity
# kept up on any hotend not worse than half its profile: its grip is noise.
EASY_SHARE = 0.5
MIN_NOISE_WINDOWS = 20
# One count of a ~128-count window: the least scatter a reading can have
# (a noiseless simulation would otherwise claim infinite precision).
MIN_GRIP_NOISE = 0.002
# The mean grip of the easy windows divides every grip: a sensor reading
# below this where the flow kept up is too far off to judge anything by.
MIN_GRIP_SCALE = 0.1
MAX_STANDARD_ERROR = 0.05
# A hotend within this of its profile is as the profile says: a profile's
# own measurement repeats to a few % (the window model itself reads the
# twin's ratio 0.2-0.5 % high, tests/unit/test_nozzle_health.py).
HEALTHY_MARGIN = 0.03
# One-sided 1 % per print: three prints in a row by chance, 1e-6.
Z_ONE_SIDED = 2.326
PERSISTENT_PRINTS = 3
TREND_PRINTS = 8
TREND_HORIZON_PRINTS = 5.0
EVIDENCE_VERSION = 1
GRID_SUMS = ("cross", "model_sq", "information")
# PrintEvidence's counters and scalar sums: what two snapshots subtract, what
# its dict holds beside the grid sums (one list for every place that walks them)
COUNTS = ("windows", "unjudged", "faulted", "no_temperature", "noise_windows")
SUMS = ("noise_sum", "noise_sum_sq", "grip_sq")
# The sums of squares (never below 0; a difference of two snapshots rounds)
SQUARE_SUMS = ("noise_sum_sq", "grip_sq", "model_sq", "information")
# Far beyond any printer's evidence (a window adds ~1, a year of windows is
# ~1e7) and far below where the estimate's arithmetic overflows.
MAX_COUNT = 10 ** 12
MAX_SUM = 1e15
EPOCH = re.compile(r"[0-9A-Za-z_-]{1,32}")
# The prints kept per hotend and profile (the verdict needs TREND_PRINTS)
MAX_PRINTS_KEPT = 50
# What an activation may seed the limiter's grip model with (the ratios a
# print can be judged at)
MIN_MELT_RATIO, MAX_MELT_RATIO = float(RATIO_GRID[0]), float(RATIO_GRID[-1])
MELT_RATIO_ACCEPTS = (f"a number from {MIN_MELT_RATIO:g} to {MAX_MELT_RATIO:g}"
                      f" (the hotend's melt capacity against its profile's)")


def _grid_zeros() -> np.ndarray:
    return np.zeros(len(RATIO_GRID))


def profile_capacity(line: Line, min_grip: float, temp_c: float) -> float:
    """The flow the profile says the hotend melts at temp_c before it slips."""
    return min_grip * line.flow_mm3_s(temp_c)


def window_grips(shares: np.ndarray, ratios: np.ndarray = RATIO_GRID
                 ) -> Tuple[np.ndarray, np.ndarray]:
    """g(r) and g'(r) at each ratio for one window whose equal pieces asked
    for `shares` of the profile's capacity."""
    mean = float(shares.mean())
    clipped = np.minimum(shares[None, :], ratios[:, None])
    grips = clipped.mean(axis=1) / mean
    slopes = (shares[None, :] > ratios[:, None]).mean(axis=1) / mean
    return grips, slopes


@dataclass
class PrintEvidence:
    """What a print's windows say about its hotend, as sums over windows."""

    profile: str
    working_point: float
    min_grip: float
    epoch: str = field(default_factory=lambda: uuid.uuid4().hex[:12])
    windows: int = 0          # judged windows at a known temperature
    unjudged: int = 0         # not judged: retraction, too little motion, stuck
    faulted: int = 0          # closed while the sensor was faulted
    no_temperature: int = 0
    noise_windows: int = 0
    noise_sum: float = 0.0      # of grip - 1 over the easy windows
    noise_sum_sq: float = 0.0
    grip_sq: float = 0.0        # of grip^2 over the windows that asked
    # per ratio of RATIO_GRID, over the windows that asked for more than
    # its lowest: grip * g(r), g(r)^2, g'(r)^2
    cross: np.ndarray = field(default_factory=lambda: _grid_zeros())
    model_sq: np.ndarray = field(default_factory=lambda: _grid_zeros())
    information: np.ndarray = field(default_factory=lambda: _grid_zeros())

    def add(self, window: Window, line: Line,
            filament_area_mm2: float = DEFAULT_FILAMENT_AREA_MM2) -> None:
        """One closed grip window, judged against the profile line in force."""
        if window.faulted:
            self.faulted += 1
            return
        flow = judged_flow_mm3_s(window, filament_area_mm2)
        if flow is None:
            self.unjudged += 1
            return
        if window.temp_c is None:
            self.no_temperature += 1
            return
        capacity = profile_capacity(line, self.min_grip, float(window.temp_c))
        if capacity <= 0.0:
            self.no_temperature += 1  # below the profile's zero: no claim
            return
        self.windows += 1
        shares = _pieces(window.commanded_flows, flow) / capacity
        grip = float(window.grip)
        if shares.max() <= EASY_SHARE:
            self.noise_windows += 1
            self.noise_sum += grip - 1.0
            self.noise_sum_sq += (grip - 1.0) ** 2
        if shares.max() <= RATIO_GRID[0]:
            return  # kept up at every ratio judged: no ratio fits it better
        grips, slopes = window_grips(shares)
        self.grip_sq += grip * grip
        self.cross += grip * grips
        self.model_sq += grips * grips
        self.information += slopes * slopes

    def residual_sq(self, grip_scale: float = 1.0) -> np.ndarray:
        """The sum of squared residuals at each ratio, the grips divided by
        grip_scale (the sensor's calibration error, read where grip is 1)."""
        return (self.grip_sq / grip_scale ** 2 - 2.0 * self.cross / grip_scale
                + self.model_sq)

    def to_dict(self) -> Dict[str, Any]:
        """JSON-able (klippy's status, Moonraker's database)."""
        return {"version": EVIDENCE_VERSION, "profile": self.profile,
                "working_point": self.working_point, "min_grip": self.min_grip,
                "epoch": self.epoch,
                **{name: getattr(self, name) for name in COUNTS + SUMS},
                **{name: getattr(self, name).tolist() for name in GRID_SUMS}}

    @classmethod
    def from_dict(cls, data: Any) -> PrintEvidence:
        """Evidence as to_dict gave it, checked whole: every count a whole
        number in 0..MAX_COUNT, every sum finite within MAX_SUM (sums of
        squares not negative), the profile a profile name. FlowloopError
        (one line) for anything else."""
        try:
            return cls._checked(data)
        except FlowloopError as e:
            raise FlowloopError(f"not nozzle evidence: {e}") from None

    @classmethod
    def _checked(cls, data: Any) -> PrintEvidence:
        if not isinstance(data, Mapping):
            raise FlowloopError(f"an object is needed, got {_shown(data)}")
        version = data.get("version")
        if type(version) is not int or version != EVIDENCE_VERSION:
            raise FlowloopError(f"version {_shown(version)} is not "
                                f"{EVIDENCE_VERSION}")
        for name in ("profile", "working_point", "min_grip", "epoch",
                     *COUNTS, *SUMS, *GRID_SUMS):
            if name not in data:
                raise FlowloopError(f"{name} is missing")
        min_grip = _number(data["min_grip"], "min_grip")
        if not 0.0 < min_grip <= 1.0:
            raise FlowloopError(f"min_grip must be in (0, 1], got {min_grip:g}")
        epoch = data["epoch"]
        if not isinstance(epoch, str) or not EPOCH.fullmatch(epoch):
            raise FlowloopError(f"epoch {_shown(epoch)} is not 1-32 letters, "
                                f"digits, '_' or '-'")
        out = cls(check_name(data["profile"]),
                  check_working_point(data["working_point"]), min_grip, epoch)
        for name in COUNTS:
            setattr(out, name, _count(data[name], name))
        for name in SUMS:
            setattr(out, name, _number(data[name], name, name in SQUARE_SUMS))
        for name in GRID_SUMS:
            values = data[name]
            if not isinstance(values, list) or len(values) != len(RATIO_GRID):
                raise FlowloopError(f"{name} must be a list of {len(RATIO_GRID)}"
                                    f" numbers, got {_shown(values)}")
            setattr(out, name, np.array(
                [_number(v, name, name in SQUARE_SUMS) for v in values],
                dtype=np.float64))
        return out


def _shown(value: Any) -> str:
    """A value from outside as one short line of a refusal."""
    try:
        text = json.dumps(value)
    except (TypeError, ValueError, RecursionError):
        text = type(value).__name__
    return text if len(text) <= 40 else text[:37] + "..."


def _number(value: Any, name: str, square: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not -MAX_SUM <= value <= MAX_SUM:   # also refuses NaN
        raise FlowloopError(f"{name} must be a number within +/-{MAX_SUM:g}, "
                            f"got {_shown(value)}")
    if square and value < 0:
        raise FlowloopError(f"{name} is a sum of squares, got {_shown(value)}")
    return float(value)


def _count(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) \
            or not 0 <= value <= MAX_COUNT:
        raise FlowloopError(f"{name} must be a whole number in 0..{MAX_COUNT}, "
                            f"got {_shown(value)}")
    return value


def _pieces(commanded_flows: Sequence[float], mean_mm3_s: float) -> np.ndarray:
    """The window's commanded flow over time, scaled to its mean (the planned
    motion leaves out pressure advance); one piece when it has none."""
    flows = np.asarray(commanded_flows, dtype=np.float64)
    total = flows.mean() if len(flows) else 0.0
    if total <= 0.0:
        return np.array([mean_mm3_s])
    return flows * (mean_mm3_s / total)


def evidence_between(start: Optional[PrintEvidence],
                     end: Optional[PrintEvidence]) -> Optional[PrintEvidence]:
    """The evidence gathered between two snapshots of one sum; all of `end`
    when it is a sum begun after `start` was taken (another profile, or
    klippy restarted), None when there is none at the end."""
    if end is None:
        return None
    if start is None or start.epoch != end.epoch:
        return end
    out = PrintEvidence(end.profile, end.working_point, end.min_grip, end.epoch)
    for name in COUNTS:
        count = getattr(end, name) - getattr(start, name)
        if count < 0:
            raise FlowloopError(f"not nozzle evidence: the start counts more "
                                f"{name} than the end of the same sum")
        setattr(out, name, count)
    for name in SUMS + GRID_SUMS:
        value = getattr(end, name) - getattr(start, name)
        if name in SQUARE_SUMS:   # rounding, or a start from another sum
            value = np.maximum(value, 0.0) if name in GRID_SUMS else max(value, 0.0)
        setattr(out, name, value)
    return out


@dataclass(frozen=True)
class PrintEstimate:
    """One print's melt capacity against its profile, or why there is none."""

    profile: str
    ratio: Optional[float] = None            # measured / profile capacity
    standard_error: Optional[float] = None
    grip_noise: Optional[float] = None       # the measured sigma of grip
    at_least: Optional[float] = None         # the highest share any window asked
    windows: int = 0
    min_grip: float = 0.9
    reason: str = ""                         # why no estimate ("" : one)
    # what the limiter's grip model believed at the print's end, against
    # the profile (None: not known); an estimate or not, the next print's
    # model starts from it (carried_ratio)
    model_ratio: Optional[float] = None

    @property
    def known(self) -> bool:
        """The print gave an estimate (a ratio, and no reason against it)."""
        return self.ratio is not None and not self.reason

    @property
    def limit_ratio(self) -> Optional[float]:
        """The ratio below which this print's highest flows would read grip
        below min_grip (grip = r / share)."""
        return None if self.at_least is None else self.min_grip * self.at_least

    def to_dict(self) -> Dict[str, Any]:
        def rounded(v: Optional[float], digits: int = 4) -> Optional[float]:
            return None if v is None else round(v, digits)
        return {"profile": self.profile, "ratio": rounded(self.ratio),
                "standard_error": rounded(self.standard_error, 5),
                "grip_noise": rounded(self.grip_noise, 5),
                "at_least": rounded(self.at_least), "windows": self.windows,
                "min_grip": self.min_grip, "reason": self.reason,
                "model_ratio": rounded(self.model_ratio)}

    @classmethod
    def from_dict(cls, data: Any) -> PrintEstimate:
        """An estimate as to_dict gave it (a stored print); FlowloopError for
        one that is not (a missing or non-finite number, a wrong type)."""
        if not isinstance(data, Mapping):
            raise FlowloopError(f"not a nozzle health estimate: {_shown(data)}")
        try:
            out = cls(profile=check_name(data["profile"]),
                      ratio=_opt(data.get("ratio"), "ratio"),
                      standard_error=_opt(data.get("standard_error"),
                                          "standard_error"),
                      grip_noise=_opt(data.get("grip_noise"), "grip_noise"),
                      at_least=_opt(data.get("at_least"), "at_least"),
                      windows=_count(data.get("windows", 0), "windows"),
                      min_grip=_number(data.get("min_grip", 0.9), "min_grip"),
                      reason=data.get("reason", ""),
                      model_ratio=_opt(data.get("model_ratio"), "model_ratio"))
        except KeyError as e:
            raise FlowloopError(f"not a nozzle health estimate: {e} is "
                                f"missing") from None
        except FlowloopError as e:
            raise FlowloopError(f"not a nozzle health estimate: {e}") from None
        if not isinstance(out.reason, str):
            raise FlowloopError(f"not a nozzle health estimate: reason "
                                f"{_shown(out.reason)}")
        return out


def _opt(value: Any, name: str) -> Optional[float]:
    return None if value is None else _number(value, name)


def melt_ratio_arg(value: Any, parameter: str = "melt_ratio") -> float:
    """A melt ratio a request gives (an activation's seed for the grip
    model), refused in one line unless a print could have measured it."""
    return number_arg(parameter, value, MELT_RATIO_ACCEPTS, MIN_MELT_RATIO,
                      MAX_MELT_RATIO)


def _measurable(ratio: Optional[float]) -> bool:
    return ratio is not None and MIN_MELT_RATIO <= ratio <= MAX_MELT_RATIO


def newest_ratio(estimates: Sequence[PrintEstimate]) -> Optional[float]:
    """The ratio of the newest print (oldest first) that gave an estimate a
    print can give, or None: what a job's history entry shows."""
    for e in reversed(estimates):
        if e.known and _measurable(e.ratio):
            return e.ratio
    return None


def carried_ratio(estimates: Sequence[PrintEstimate]) -> Optional[float]:
    """What the next activation seeds the limiter's grip model with (None:
    the profile's line): from the newest print (oldest first) that knew
    anything, what the model believed at its end (the latest knowledge, and
    there whether or not the print gave an estimate: a print with too few
    easy windows to measure the noise still taught the model), else its
    estimate."""
    for e in reversed(estimates):
        if _measurable(e.model_ratio):
            return e.model_ratio
        if e.known and _measurable(e.ratio):
            return e.ratio
    return None


def estimate(evidence: Optional[PrintEvidence],
             model_ratio: Optional[float] = None) -> PrintEstimate:
    """The print's ratio and its standard error, or the reason there is
    none; with model_ratio (what the limiter's model believed at the print's
    end) beside, when the print had a profile."""
    if evidence is None:
        return PrintEstimate("", reason="no active profile during the print: "
                             "nothing to compare the hotend with")
    with np.errstate(all="ignore"):
        found = _estimate(evidence)
    numbers = (found.ratio, found.standard_error, found.grip_noise)
    if not all(v is None or math.isfinite(v) for v in numbers):
        # sums no print gives (each finite, together out of any sensor's range)
        found = PrintEstimate(evidence.profile, windows=evidence.windows,
                              min_grip=evidence.min_grip,
                              reason="the evidence's sums give no finite estimate")
    return replace(found, model_ratio=model_ratio_of(model_ratio))


def model_ratio_of(value: Any) -> Optional[float]:
    """The melt ratio klippy's limiter says its model believes
    (`model_melt_ratio` of flowrate_limiter/nozzle_evidence), None for
    anything but a finite number: it is kept beside the estimate, never in
    place of one."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value):
        return None
    return float(value)


def _estimate(ev: PrintEvidence) -> PrintEstimate:
    base = dict(profile=ev.profile, windows=ev.windows, min_grip=ev.min_grip)
    if ev.windows == 0:
        if ev.faulted:
            why = (f"the sensor was faulted for all {ev.faulted} windows: "
                   f"grip was never judged")
        else:
            why = "no judged grip window at a known temperature"
        return PrintEstimate(**base, reason=why)
    if ev.noise_windows < MIN_NOISE_WINDOWS:
        return PrintEstimate(**base, reason=(
            f"{ev.noise_windows} windows below {EASY_SHARE:.0%} of the profile's "
            f"capacity, {MIN_NOISE_WINDOWS} needed to measure the sensor's noise"))
    noise = max(MIN_GRIP_NOISE, math.sqrt(ev.noise_sum_sq / ev.noise_windows))
    asked = np.nonzero(ev.information > 0.0)[0]
    at_least = (float(RATIO_GRID[min(asked[-1] + 1, len(RATIO_GRID) - 1)])
                if len(asked) else None)
    base.update(grip_noise=noise, at_least=at_least)
    grip_scale = 1.0 + ev.noise_sum / ev.noise_windows
    if not grip_scale > MIN_GRIP_SCALE:
        return PrintEstimate(**base, reason=(
            f"the sensor read a mean grip of {grip_scale:.3g} where the flow "
            f"kept up: check its calibration"))
    residual = ev.residual_sq(grip_scale)
    k = int(np.argmin(residual))
    kept_up = ev.information <= 0.0
    share = "none" if at_least is None else f"{at_least:.0%}"
    said = (f"every window kept up within the sensor's noise (the highest "
            f"asked for {share} of the profile's capacity): the hotend melts "
            f"at least that")
    # a slip must fit better than keeping up by more than the noise allows
    flat = float(residual[kept_up].min()) if kept_up.any() else float(residual[-1])
    if kept_up[k] or (flat - residual[k]) / noise ** 2 < Z_ONE_SIDED ** 2:
        return PrintEstimate(**base, reason=said)
    ratio = _refined(residual, k)
    information = float(np.interp(ratio, RATIO_GRID, ev.information))
    se = noise / math.sqrt(max(information, ev.information[k] * 1e-3))
    if se > MAX_STANDARD_ERROR:
        return PrintEstimate(**base, ratio=ratio, standard_error=se, reason=(
            f"too little evidence: standard error {se:.3f} above "
            f"{MAX_STANDARD_ERROR:g} (few windows near the capacity, or a "
            f"noisy sensor: grip noise {noise:.4f})"))
    return PrintEstimate(**base, ratio=ratio, standard_error=float(se))


def _refined(residual: np.ndarray, k: int) -> float:
    """The minimum between grid ratios: a parabola through three."""
    if k == 0 or k == len(residual) - 1:
        return float(RATIO_GRID[k])
    a, b, c = residual[k - 1], residual[k], residual[k + 1]
    bend = a - 2 * b + c
    step = float(RATIO_GRID[1] - RATIO_GRID[0])
    offset = 0.5 * (a - c) / bend if bend > 0 else 0.0
    return float(RATIO_GRID[k] + max(-0.5, min(0.5, offset)) * step)


def evidence_of(windows: Sequence[Window], profile: Optional[Profile],
                working_point: float = 0.5, min_grip: Optional[float] = None,
                filament_area_mm2: float = DEFAULT_FILAMENT_AREA_MM2
                ) -> Optional[PrintEvidence]:
    """The evidence of a print's windows under one profile (None: none)."""
    if profile is None:
        return None
    grip = min_grip_of(profile, min_grip)
    evidence = PrintEvidence(profile.name, working_point, grip)
    line = profile_line(profile, working_point)
    for window in windows:
        evidence.add(window, line, filament_area_mm2)
    return evidence


# --- across prints -------------------------------------------------------------

@dataclass(frozen=True)
class Verdict:
    """Whether the hotend's capacity is persistently below its profile."""

    warn: bool
    rule: str            # "persistent", "trend" or "" (no warning)
    text: str            # one line for the user
    prints: int          # estimates judged


def _significantly_low(e: PrintEstimate) -> bool:
    return (e.ratio is not None and e.standard_error is not None
            and e.ratio + Z_ONE_SIDED * e.standard_error < 1.0 - HEALTHY_MARGIN)


def judge(history: Sequence[PrintEstimate]) -> Verdict:
    """The verdict over one hotend's estimates for one profile, oldest first
    (prints without an estimate are left out)."""
    known = [e for e in history if e.known]
    latest = known[-PERSISTENT_PRINTS:]
    if len(known) < PERSISTENT_PRINTS:
        return Verdict(False, "", f"{len(known)} prints with an estimate, "
                       f"{PERSISTENT_PRINTS} needed", len(known))
    now = known[-1]
    said = (f"melt capacity {now.ratio:.0%} of the profile "
            f"(+/- {now.standard_error:.1%})")
    if all(_significantly_low(e) for e in latest):
        return Verdict(True, "persistent", (
            f"{said}; the last {PERSISTENT_PRINTS} prints each below "
            f"{1 - HEALTHY_MARGIN:.0%} beyond their noise: a partial clog, a "
            f"worn nozzle or the wrong nozzle?"), len(known))
    trend = _trend(known[-TREND_PRINTS:])
    if trend is not None and _significantly_low(now):
        return Verdict(True, "trend", (
            f"{said}, falling {-trend[0]:.1%} a print: the print's highest "
            f"flows slip below min_grip in about {trend[1]:.1f} prints"),
            len(known))
    return Verdict(False, "", said, len(known))


def _trend(recent: Sequence[PrintEstimate]) -> Optional[Tuple[float, float]]:
    """(slope per print, prints until the limit) of a significant fall that
    reaches the prints' limit ratio within TREND_HORIZON_PRINTS; else None."""
    if len(recent) < PERSISTENT_PRINTS + 1:
        return None
    x = np.arange(len(recent), dtype=np.float64)
    y = np.array([e.ratio for e in recent])
    w = 1.0 / np.array([e.standard_error for e in recent]) ** 2
    xm = np.sum(w * x) / np.sum(w)
    sxx = np.sum(w * (x - xm) ** 2)
    slope = float(np.sum(w * (x - xm) * (y - np.sum(w * y) / np.sum(w))) / sxx)
    intercept = float(np.sum(w * y) / np.sum(w)) - slope * xm
    chi2 = float(np.sum(w * (y - intercept - slope * x) ** 2))
    scale = max(1.0, math.sqrt(chi2 / (len(recent) - 2)))
    slope_se = scale / math.sqrt(sxx)
    if slope + Z_ONE_SIDED * slope_se >= 0.0:
        return None
    limits = [e.limit_ratio for e in recent if e.limit_ratio is not None]
    if not limits:
        return None
    now = intercept + slope * x[-1]
    prints_left = (now - max(limits)) / -slope
    if prints_left > TREND_HORIZON_PRINTS:
        return None
    return slope, max(0.0, prints_left)


# --- toolchangers: one hotend per tool ---------------------------------------

def tool_hotend(hotend: str, extruder: str) -> str:
    """The hotend a tool's prints are judged as: the printer's `hotend:`
    for `extruder`, that and the tool's name for every other tool."""
    return hotend if extruder == "extruder" else f"{hotend} {extruder}"


def printed_between(before: Optional[Dict[str, Any]],
                    after: Optional[Dict[str, Any]]) -> bool:
    """A tool's evidence (PrintEvidence.to_dict, or None without a profile)
    counted a grip window of any kind between two asks (judged, unjudged,
    faulted, without temperature): the tool printed in between. A job
    judges only the tools that did."""
    if after is None:
        return False
    return before is None or any(after.get(name) != before.get(name)
                                 for name in ("epoch",) + COUNTS)


# --- what is stored and what comes from outside ------------------------------

@dataclass(frozen=True)
class PostedPrint:
    """A print's evidence posted from elsewhere (a replayed or offline
    print), checked whole."""

    job_id: str
    start: Optional[PrintEvidence]
    end: Optional[PrintEvidence]


def post_request(given: Mapping[str, Any],
                 profiles: Collection[str]) -> PostedPrint:
    """The arguments of a nozzle health POST (job_id, start, evidence), every
    part checked before anything is stored: a job id as Moonraker's history
    gives them, evidence as klippy gives it, for a profile stored here
    (`profiles`). FlowloopError (one line) for anything else."""
    job_id = check_job_id(given.get("job_id"))
    start, end = (None if given.get(key) is None else
                  PrintEvidence.from_dict(given[key])
                  for key in ("start", "evidence"))
    if end is None and start is not None:
        raise FlowloopError("a start without evidence (argument 'evidence')")
    if start is not None and end is not None and start.epoch == end.epoch \
            and start.profile != end.profile:
        raise FlowloopError("the start and the evidence are one sum but name "
                            "two profiles")
    if end is not None and end.profile not in profiles:
        raise FlowloopError(f"no profile named {label(end.profile)}: evidence "
                            f"is kept for stored profiles only")
    evidence_between(start, end)    # refuses a start that counts past the end
    return PostedPrint(job_id, start, end)


def with_print(prints: Sequence[Dict[str, Any]],
               entry: Dict[str, Any]) -> List[Dict[str, Any]]:
    """The stored prints with `entry` added: one record per job (the job's
    earlier record replaced), the newest MAX_PRINTS_KEPT kept."""
    kept = [p for p in prints if p.get("job_id") != entry.get("job_id")]
    return (kept + [entry])[-MAX_PRINTS_KEPT:]


def load_history(stored: Any) -> Tuple[List[Dict[str, Any]],
                                       List[PrintEstimate], List[str]]:
    """(the stored prints that read, their estimates, why each other one
    does not): a print that no longer reads is skipped, never blocks the
    ones after it."""
    prints = stored.get("prints") if isinstance(stored, Mapping) else None
    if not isinstance(prints, list):
        return [], [], [f"the history is not a list of prints: {_shown(stored)}"]
    kept: List[Dict[str, Any]] = []
    estimates: List[PrintEstimate] = []
    problems: List[str] = []
    for k, entry in enumerate(prints):
        try:
            estimates.append(PrintEstimate.from_dict(entry))
        except FlowloopError as e:
            problems.append(f"print {k}: {e}")
            continue
        kept.append(entry)
    return kept, estimates, problems


def warning_text(verdict: Verdict, prints: Sequence[Dict[str, Any]]) -> str:
    """The warning in words: the verdict, then the last prints' melt capacity
    (one sentence each, no doubled punctuation)."""
    said = verdict.text if verdict.text[-1:] in ".?!" else f"{verdict.text}."
    ratios = [p["ratio"] for p in prints[-8:] if p.get("ratio") is not None]
    if not ratios:
        return said
    evidence = ", ".join(f"{r:.0%}" for r in ratios)
    return (f"{said} Melt capacity against the profile over the last prints: "
            f"{evidence}.")


@dataclass(frozen=True)
class HealthWarning:
    """What a warning verdict tells the user: the console line and the
    notification every print it holds, a Moonraker announcement (`announce`)
    once, when it starts."""

    title: str
    text: str
    url: str
    announce: bool


def was_warning(stored: Any) -> bool:
    """A stored history whose last verdict warned."""
    verdict = stored.get("verdict") if isinstance(stored, Mapping) else None
    return isinstance(verdict, Mapping) and verdict.get("warn") is True


def health_warning(hotend: str, profile: str, prints: Sequence[Dict[str, Any]],
                   verdict: Verdict, warned_before: bool
                   ) -> Optional[HealthWarning]:
    """The warning a verdict gives (None: it does not warn); announced only
    when the history's verdict before this print did not warn, so a warning
    that goes on is announced once and one that comes back after clearing
    is announced again."""
    if not verdict.warn:
        return None
    return HealthWarning(
        title=(f"flowloop: nozzle health, hotend {label(hotend)}, "
               f"profile {label(profile)}"),
        text=warning_text(verdict, prints), url=plot_path(hotend, profile),
        announce=not warned_before)


def history_record(hotend: str, profile: str, prints: Sequence[Dict[str, Any]],
                   verdict: Verdict) -> Dict[str, Any]:
    """One hotend's history for one profile as it is stored."""
    return {"hotend": hotend, "profile": profile, "prints": list(prints),
            "verdict": verdict.__dict__}


def check_history(record: Any) -> Dict[str, Any]:
    """A history as history_record gives it, checked whole before it is
    stored; FlowloopError (one line) for anything else."""
    if not isinstance(record, Mapping) or set(record) != {
            "hotend", "profile", "prints", "verdict"}:
        raise FlowloopError(f"not a nozzle health history: {_shown(record)}")
    hotend = record["hotend"]
    if not isinstance(hotend, str) or not hotend.strip():
        raise FlowloopError(f"not a nozzle health history: hotend "
                            f"{_shown(hotend)}")
    check_name(record["profile"])
    prints, _, problems = load_history(record)
    if problems:
        raise FlowloopError(f"not a nozzle health history: {problems[0]}")
    if len(prints) > MAX_PRINTS_KEPT:
        raise FlowloopError(f"not a nozzle health history: {len(prints)} "
                            f"prints, at most {MAX_PRINTS_KEPT} are kept")
    if any(p["profile"] != record["profile"] for p in prints):
        raise FlowloopError("not a nozzle health history: a print of another "
                            "profile")
    verdict = record["verdict"]
    if not isinstance(verdict, Mapping) or not isinstance(verdict.get("warn"),
                                                          bool):
        raise FlowloopError(f"not a nozzle health history: verdict "
                            f"{_shown(verdict)}")
    return dict(record)


def plot_path(hotend: str, profile: str) -> str:
    """The health plot's address on Moonraker: absolute, so it resolves from
    a UI served by the same host (nginx proxies /server/ to Moonraker)."""
    query = urlencode({"profile": profile, "hotend": hotend})
    return f"/server/flowloop/nozzle_health/plot?{query}"


def label(name: str) -> str:
    """A name as one line of text that is safe as HTML too: JSON-quoted,
    ASCII, with <, >, & and ' as JSON escapes (a console line, an
    announcement's title: no forged line, no markup)."""
    text = json.dumps(name)
    for ch in "<>&'":
        text = text.replace(ch, f"\\u{ord(ch):04x}")
    return text
