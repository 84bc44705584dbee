"""Probe rounds and points to a flat delta bed from +-1.5 mm endstop errors.

Three ways to use the same probes, on the same synthetic printers, in one run:
- this solver (exact endstop fit, flowloop.calibrate.delta.solve_endstops), 4 points;
- the per-tower loop (lower each endstop by its tower's height), 3 points;
- a 6-parameter coordinate-descent fit (radius, two angles, three endstops,
  as DELTA_CALIBRATE does) of the same 4 points, and of 7 points.

A round is: probe with the current config, fit, apply. The bed counts as flat
when the true nozzle height over a 19-point check pattern inside the probe
radius has a spread under 0.01 mm. Figures are ratios against the solver
(the goal: one round, 4 points).
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from flowloop.calibrate import delta
from flowloop.errors import FlowloopError
from tests.bench.size import pick

FLAT_MM = 0.01
MAX_ROUNDS = 12
PRINTERS = pick(8, 1)
PROBE_RADIUS = 100.0


def check_points(radius: float):
    points = [(0.0, 0.0)]
    for ring, count in ((radius / 2, 6), (radius, 12)):
        for k in range(count):
            a = 2 * math.pi * k / count
            points.append((ring * math.cos(a), ring * math.sin(a)))
    return points


def true_spread(believed, true, points) -> float:
    return float(np.ptp(delta.simulate_probe_z(believed, true, points)))


# --- the three methods: (believed geometry, probes) -> new believed geometry ------


def solver(believed, probes):
    solution = delta.solve_endstops(believed, probes)
    return believed.with_endstops(solution.position_endstop)


def naive(believed, probes):
    towers = [probes[i][2] for i in (1, 2, 3)]
    return believed.with_endstops(
        delta.naive_endstop_update(believed.position_endstops, towers))


def coordinate_descent(believed, probes, min_step=1e-6, max_evals=20000):
    """Six parameters by coordinate descent on the squared height errors."""
    travels = [believed.travel(p) for p in probes]
    names = ("radius", "angle_a", "angle_b", "endstop_a", "endstop_b", "endstop_c")

    def build(v):
        return delta.DeltaGeometry(v[0], believed.arm_lengths, tuple(v[3:6]),
                                   (v[1], v[2], believed.angles_deg[2]))

    def error(v):
        try:
            g = build(v)
            return sum(g.position_from_travel(t)[2] ** 2 for t in travels)
        except FlowloopError:
            return math.inf

    values = [believed.radius, *believed.angles_deg[:2], *believed.position_endstops]
    steps = [1.0] * len(names)
    best = error(values)
    evals = 0
    while max(steps) > min_step and evals < max_evals:
        for i in range(len(names)):
            improved = False
            for sign in (1.0, -1.0):
                trial = list(values)
                trial[i] += sign * steps[i]
                e = error(trial)
                evals += 1
                if e < best:
                    values, best, improved = trial, e, True
                    break
            steps[i] *= 1.5 if improved else 0.5
    return build(values)


@dataclasses.dataclass
class Outcome:
    rounds: int
    points: int
    seconds: float


def run(method, believed, true, points, counted, checks) -> Outcome:
    """counted: the probe points the method reads per round."""
    used = 0
    spent = 0.0
    for rounds in range(1, MAX_ROUNDS + 1):
        z = delta.simulate_probe_z(believed, true, points)
        probes = [(x, y, h) for (x, y), h in zip(points, z)]
        used += counted
        start = time.perf_counter()
        believed = method(believed, probes)
        spent += time.perf_counter() - start
        if true_spread(believed, true, checks) < FLAT_MM:
            return Outcome(rounds, used, spent)
    return Outcome(MAX_ROUNDS + 1, used, spent)


def test_probe_rounds_to_a_flat_bed(bench):
    rng = np.random.default_rng(6)
    base = delta.DeltaGeometry(140.0, (300.0, 300.0, 300.0), (300.0, 300.0, 300.0))
    four = delta.probe_points(base.angles_deg, PROBE_RADIUS, opposite=False)
    three = four  # the per-tower loop reads the three tower points only
    seven = delta.probe_points(base.angles_deg, PROBE_RADIUS)
    checks = check_points(PROBE_RADIUS)
    methods = {
        "solver, 4 points": (solver, four, 4),
        "per-tower loop, 3 points": (naive, three, 3),
        "6-parameter descent, 4 points": (coordinate_descent, four, 4),
        "6-parameter descent, 7 points": (coordinate_descent, seven, 7),
    }
    outcomes = {name: [] for name in methods}
    for _ in range(PRINTERS):
        errors = rng.uniform(-1.5, 1.5, size=3)
        true = base.with_endstops(np.add(base.position_endstops, errors))
        for name, (method, points, counted) in methods.items():
            outcomes[name].append(run(method, base, true, points, counted, checks))

    def mean(name, field):
        return float(np.mean([getattr(o, field) for o in outcomes[name]]))

    baseline = "solver, 4 points"
    bench.figure("endstop_calibrate solver rounds (mean)", mean(baseline, "rounds"),
                 goal="1")
    bench.figure("endstop_calibrate solver probe points (mean)",
                 mean(baseline, "points"), goal="4")
    for name in methods:
        if name == baseline:
            continue
        never = sum(o.rounds > MAX_ROUNDS for o in outcomes[name])
        note = ""
        if never:
            note = f", not flat in {MAX_ROUNDS} rounds on {never}/{PRINTERS}"
        bench.ratio(f"endstop_calibrate rounds, {name}{note}", mean(name, "rounds"),
                    mean(baseline, "rounds"))
        bench.ratio(f"endstop_calibrate probe points, {name}", mean(name, "points"),
                    mean(baseline, "points"))
        bench.ratio(f"endstop_calibrate fit time per round, {name}",
                    mean(name, "seconds") / mean(name, "rounds"),
                    mean(baseline, "seconds") / mean(baseline, "rounds"), unit="s")
    # What the comparison is about: the exact fit is done after one round.
    assert all(o.rounds == 1 for o in outcomes[baseline])
