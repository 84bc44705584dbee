"""Linear delta kinematics and the tower endstop solver behind ENDSTOP_CALIBRATE.

Conventions follow Klipper's delta kinematics: tower i stands at
(radius*cos(angle_i), radius*sin(angle_i)); its carriage hangs an arm of
arm_length_i; the carriage sits at height position_endstop_i +
sqrt(arm_length_i**2 - radius**2) when homed (the "absolute endstop").

A probe is recorded as the believed toolhead position (x, y, z) where it
triggered. What the steppers really know is how far each carriage travelled
down from its endstop, and that travel does not depend on the configured
endstops. The solver looks for the three position_endstop values that, through
the exact forward kinematics, put every recorded travel at the bed height.
"""

from __future__ import annotations

import dataclasses
import math
from typing import List, Optional, Sequence, Tuple

import numpy as np

from ..errors import FlowloopError
from ..host.klipper_config import KlipperConfig
from ..numbers import check_result

TOWERS = ("stepper_a", "stepper_b", "stepper_c")
DEFAULT_ANGLES_DEG = (210.0, 330.0, 90.0)
# Max |height| left after the endstop fit before radius/angles are suspected.
DEFAULT_GEOMETRY_WARNING_MM = 0.02
# Spread and mean height within which ENDSTOP_CALIBRATE changes nothing.
DEFAULT_TOLERANCE_MM = 0.01
# Probes per point (SAMPLES=, the samples option): the median is used
MAX_SAMPLES = 100

Triple = Tuple[float, float, float]


def _triple(values: Sequence[float], what: str) -> Triple:
    out = tuple(float(v) for v in values)
    if len(out) != 3:
        raise FlowloopError(f"{what} needs 3 values, got {len(out)}")
    if not all(math.isfinite(v) for v in out):
        raise FlowloopError(f"{what} must be finite numbers, got {list(out)}")
    return out  # type: ignore[return-value]


@dataclasses.dataclass(frozen=True)
class DeltaGeometry:
    """The delta parameters Klipper reads from [printer] and [stepper_a/b/c]."""

    radius: float
    arm_lengths: Triple
    position_endstops: Triple
    angles_deg: Triple = DEFAULT_ANGLES_DEG

    def __post_init__(self) -> None:
        if not (math.isfinite(self.radius) and self.radius > 0.0):
            raise FlowloopError(f"delta_radius must be above 0, got {self.radius}")
        arms = _triple(self.arm_lengths, "arm_length")
        for name, arm in zip(TOWERS, arms):
            if arm <= self.radius:
                raise FlowloopError(
                    f"{name} arm_length {arm} must be above delta_radius {self.radius}")
        object.__setattr__(self, "arm_lengths", arms)
        object.__setattr__(self, "position_endstops",
                           _triple(self.position_endstops, "position_endstop"))
        object.__setattr__(self, "angles_deg", _triple(self.angles_deg, "angle"))

    # --- fixed parts of the geometry ---------------------------------------

    @property
    def towers(self) -> np.ndarray:
        """Tower XY positions, shape (3, 2)."""
        rad = np.radians(self.angles_deg)
        return self.radius * np.column_stack((np.cos(rad), np.sin(rad)))

    @property
    def abs_endstops(self) -> np.ndarray:
        """Carriage heights at the endstops."""
        arms = np.asarray(self.arm_lengths)
        return np.asarray(self.position_endstops) + np.sqrt(arms**2 - self.radius**2)

    def with_endstops(self, position_endstops: Sequence[float]) -> DeltaGeometry:
        return dataclasses.replace(self, position_endstops=tuple(position_endstops))

    # --- kinematics ----------------------------------------------------------

    def carriage_heights(self, xyz: Sequence[float]) -> np.ndarray:
        """Inverse kinematics: carriage heights that put the effector at xyz."""
        x, y, z = (float(v) for v in xyz)
        d2 = (self.towers[:, 0] - x) ** 2 + (self.towers[:, 1] - y) ** 2
        reach2 = np.asarray(self.arm_lengths) ** 2 - d2
        if np.any(reach2 <= 0.0):
            raise FlowloopError(f"point ({x:.3f}, {y:.3f}) is out of the arms' reach")
        return z + np.sqrt(reach2)

    def position(self, carriage_heights: Sequence[float]) -> np.ndarray:
        """Forward kinematics: effector position for the given carriage heights.

        The three arm spheres meet in two points; the effector is the lower one.
        """
        centres = np.column_stack((self.towers, np.asarray(carriage_heights, float)))
        arms = np.asarray(self.arm_lengths)
        p1, p2, p3 = centres
        d = np.linalg.norm(p2 - p1)
        ex = (p2 - p1) / d
        i = float(ex @ (p3 - p1))
        ey = p3 - p1 - i * ex
        j = float(np.linalg.norm(ey))
        ey = ey / j
        ez = np.cross(ex, ey)
        u = (arms[0] ** 2 - arms[1] ** 2 + d**2) / (2.0 * d)
        v = (arms[0] ** 2 - arms[2] ** 2 + i**2 + j**2) / (2.0 * j) - i * u / j
        w2 = arms[0] ** 2 - u**2 - v**2
        if w2 < 0.0:
            raise FlowloopError("carriage heights out of reach of the arms")
        base = p1 + u * ex + v * ey
        w = math.sqrt(w2) * (1.0 if ez[2] < 0.0 else -1.0)
        return base + w * ez

    def travel(self, xyz: Sequence[float]) -> np.ndarray:
        """How far each carriage is below its endstop with the effector at xyz.

        This is what the steppers count, so it holds whatever the endstops are.
        """
        return self.abs_endstops - self.carriage_heights(xyz)

    def position_from_travel(self, travel: Sequence[float]) -> np.ndarray:
        return self.position(self.abs_endstops - np.asarray(travel, float))

    def dz_dcarriages(self, xyz: Sequence[float]) -> np.ndarray:
        """d(effector z)/d(carriage height) for each tower at xyz.

        From |P - C_i|^2 = L_i^2: (P - C_i).dP = (z - c_i) dc_i for each arm.
        """
        p = np.asarray(xyz, float)
        carriages = self.carriage_heights(p)
        centres = np.column_stack((self.towers, carriages))
        normals = p - centres
        dp_dc = np.linalg.solve(normals, np.diag(p[2] - carriages))
        return dp_dc[2]


def probe_points(angles_deg: Sequence[float], radius: float, opposite: bool = True,
                 centre: bool = True) -> List[Tuple[float, float]]:
    """ENDSTOP_CALIBRATE's probe XY points, in this order: the centre, then
    `radius` from it towards each tower, then (opposite) `radius` away from
    each tower, where a wrong tower angle shows."""
    directions = list(angles_deg)
    if opposite:
        directions += [a + 180.0 for a in angles_deg]
    points = [(0.0, 0.0)] if centre else []
    for angle in directions:
        a = math.radians(angle)
        points.append((radius * math.cos(a), radius * math.sin(a)))
    return points


# --- the endstop solver -------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class EndstopSolution:
    position_endstop: Triple
    position_endstop_before: Triple
    heights_before_mm: Tuple[float, ...]  # probed height above the bed, per probe
    heights_after_mm: Tuple[float, ...]  # the same, predicted with the new endstops
    tower_probe_index: Tuple[int, int, int]  # the probe nearest each tower
    iterations: int
    geometry_warning: Optional[str]

    @property
    def residual_mm(self) -> float:
        """RMS of the heights left after the fit (0 when the model explains all)."""
        return float(np.sqrt(np.mean(np.square(self.heights_after_mm))))

    @property
    def spread_before_mm(self) -> float:
        return float(np.ptp(self.heights_before_mm))

    @property
    def spread_after_mm(self) -> float:
        return float(np.ptp(self.heights_after_mm))

    @property
    def corrections_mm(self) -> Triple:
        return tuple(  # type: ignore[return-value]
            new - old for new, old in zip(self.position_endstop,
                                          self.position_endstop_before))

    def to_json(self) -> dict:
        return {
            "position_endstop": {name: value for name, value
                                 in zip(TOWERS, self.position_endstop)},
            "residual_mm": self.residual_mm,
            "spread_before_mm": self.spread_before_mm,
            "spread_after_mm": self.spread_after_mm,
        }


def _check_probes(probes: Sequence[Sequence[float]]) -> np.ndarray:
    pts = np.asarray([tuple(p) for p in probes], dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise FlowloopError("each probe needs x, y and z")
    if len(pts) < 3:
        raise FlowloopError(f"need at least 3 probes (near each tower), got {len(pts)}")
    if not np.all(np.isfinite(pts)):
        bad = next(p for p in pts if not np.all(np.isfinite(p)))
        raise FlowloopError(f"probe {tuple(bad)} is not finite")
    return pts


def solve_endstops(geometry: DeltaGeometry, probes: Sequence[Sequence[float]],
                   bed_z: Optional[Sequence[float]] = None,
                   geometry_warning_mm: float = DEFAULT_GEOMETRY_WARNING_MM,
                   tolerance_mm: float = 1e-10, max_iterations: int = 50
                   ) -> EndstopSolution:
    """Find the position_endstop values that put every probe on the bed.

    probes: believed (x, y, z) of the toolhead when each probe triggered, under
    `geometry`. bed_z: the z each probe should have had (0 for a nozzle
    touching the bed; the probe's z_offset for a probe). Gauss-Newton on the
    exact forward kinematics: the carriage travels are fixed, the endstops move.
    """
    pts = _check_probes(probes)
    target = np.zeros(len(pts)) if bed_z is None else np.asarray(bed_z, float)
    if target.shape != (len(pts),) or not np.all(np.isfinite(target)):
        raise FlowloopError("bed_z needs one finite value per probe")
    travels = [geometry.travel(p) for p in pts]
    heights_before = pts[:, 2] - target

    def heights_and_jacobian(endstops):
        trial = geometry.with_endstops(endstops)
        positions = [trial.position_from_travel(t) for t in travels]
        heights = np.array([p[2] for p in positions]) - target
        # An endstop moves its carriage by the same amount at every travel.
        jac = np.array([trial.dz_dcarriages(p) for p in positions])
        return heights, jac

    endstops = np.asarray(geometry.position_endstops, float)
    iterations = 0
    while True:
        heights, jac = heights_and_jacobian(endstops)
        if np.linalg.cond(jac) > 1e8:
            raise FlowloopError("the probe points do not tell the three towers apart:"
                                " probe near each tower")
        step = np.linalg.lstsq(jac, -heights, rcond=None)[0]
        endstops = endstops + step
        iterations += 1
        if np.max(np.abs(step)) < tolerance_mm:
            break
        if iterations >= max_iterations:
            raise FlowloopError(f"endstop fit did not converge in {max_iterations}"
                                " iterations: check the probe heights")
    # finite before anything is staged (a position_endstop is any finite mm)
    endstops = np.array([check_result(e, f"{name}: position_endstop")
                         for name, e in zip(TOWERS, endstops)])
    heights_after, _ = heights_and_jacobian(endstops)
    towers = geometry.towers
    nearest = tuple(int(np.argmin(np.hypot(pts[:, 0] - tx, pts[:, 1] - ty)))
                    for tx, ty in towers)
    warning = None
    worst = float(np.max(np.abs(heights_after)))
    if worst > geometry_warning_mm:
        warning = (f"probes still disagree by up to {worst:.3f} mm after the endstop"
                   " fit: delta_radius or tower angles are off, run DELTA_CALIBRATE")
    return EndstopSolution(
        position_endstop=tuple(float(e) for e in endstops),  # type: ignore[arg-type]
        position_endstop_before=geometry.position_endstops,
        heights_before_mm=tuple(float(h) for h in heights_before),
        heights_after_mm=tuple(float(h) for h in heights_after),
        tower_probe_index=nearest,  # type: ignore[arg-type]
        iterations=iterations,
        geometry_warning=warning)


def naive_endstop_update(position_endstops: Sequence[float],
                         tower_heights_mm: Sequence[float]) -> Triple:
    """One round of the classic per-tower loop, for comparison.

    Each tower's endstop is lowered by the height probed near that tower, as
    if that point depended on its own tower only. Because a point near tower A
    also hangs on B and C, this undershoots the tilt and needs many rounds.
    """
    return tuple(e - h for e, h in zip(_triple(position_endstops, "position_endstop"),
                                       _triple(tower_heights_mm, "tower height")))


# --- synthetic printers ---------------------------------------------------------


def simulate_probe_z(believed: DeltaGeometry, true: DeltaGeometry,
                     xy_points: Sequence[Sequence[float]],
                     bed_z: float = 0.0) -> np.ndarray:
    """Believed z at which a printer really built as `true` touches the bed.

    The toolhead is lowered at each believed (x, y); it touches when the true
    effector position (same carriage travels, true geometry) is at bed_z.
    """
    out = []
    for x, y in xy_points:
        z = 0.0
        for _ in range(50):
            real = true.position_from_travel(believed.travel((x, y, z)))
            error = real[2] - bed_z
            z -= error  # dz_real/dz_believed is 1 to first order
            if abs(error) < 1e-13:
                break
        out.append(z)
    return np.asarray(out)


# --- reading the geometry from a printer.cfg --------------------------------------


def geometry_from_config(config: KlipperConfig) -> DeltaGeometry:
    """The delta geometry klippy would build from this config.

    stepper_b/c take arm_length and position_endstop from stepper_a when they
    have none; angles default to 210, 330 and 90 degrees.
    """
    kinematics = config.get("printer", "kinematics", "").strip()
    if kinematics != "delta":
        found = kinematics or "none"
        raise FlowloopError(f"not a delta printer config ([printer] kinematics:"
                            f" {found})")
    for name in TOWERS:
        if not config.has_section(name):
            raise FlowloopError(f"delta config has no [{name}] section")
    radius = config.getfloat("printer", "delta_radius", above=0.0)
    arm_a = config.getfloat("stepper_a", "arm_length", above=radius)
    endstop_a = config.getfloat("stepper_a", "position_endstop")
    arms = tuple(config.getfloat(name, "arm_length", arm_a, above=radius)
                 for name in TOWERS)
    endstops = tuple(config.getfloat(name, "position_endstop", endstop_a)
                     for name in TOWERS)
    angles = tuple(config.getfloat(name, "angle", default)
                   for name, default in zip(TOWERS, DEFAULT_ANGLES_DEG))
    return DeltaGeometry(radius, arms, endstops, angles)  # type: ignore[arg-type]


# --- what the klippy command decides ------------------------------------------------


def median_of_samples(rows: Sequence[Sequence[float]], samples: int) -> np.ndarray:
    """Median, column by column, of each run of `samples` consecutive rows."""
    table = np.asarray([tuple(r) for r in rows], dtype=float)
    if samples < 1 or table.ndim != 2 or len(table) % samples:
        raise FlowloopError(f"{len(table)} probe results do not split into groups"
                            f" of {samples} samples")
    return np.median(table.reshape(len(table) // samples, samples, -1), axis=1)


@dataclasses.dataclass(frozen=True)
class FlatnessCheck:
    spread_mm: float
    mean_height_mm: float
    tolerance_mm: float

    @property
    def within_tolerance(self) -> bool:
        """Flat (spread) and at the right height (mean) within the tolerance."""
        return (self.spread_mm <= self.tolerance_mm
                and abs(self.mean_height_mm) <= self.tolerance_mm)


def check_flatness(heights_mm: Sequence[float], tolerance_mm: float) -> FlatnessCheck:
    heights = np.asarray(heights_mm, dtype=float)
    return FlatnessCheck(float(np.ptp(heights)), float(np.mean(heights)),
                         float(tolerance_mm))
