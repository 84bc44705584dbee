"""Rotation_distance error left after two calibration rounds, and run times.

Simulated CoreXY printers with belt errors up to +-0.3 %, pylons that shrink
0.3-0.6 %, caliper noise 3 sigma = 20 um and, in 1 reading out of 20, a
slipped jaw (+0.1..0.5 mm). Three ways to turn the same readings into a new
rotation_distance, two rounds each:
- this estimator: median of 5 readings, (d2 - d1) / (D2 - D1) (baseline);
- the spreadsheet way: mean of the readings, same difference formula;
- "measure and trim": a solid 150 mm bar printed on the same diagonal,
  scale = measured / 150 (its shrinkage stays in the result).
Figures are residual motion errors in um per 100 mm (mean over printers), as
ratios against this estimator. Timings: the estimator against the bare
difference formula, and rendering the pylon G-code against joining the same
moves with plain f-strings.
"""

from __future__ import annotations

import time

import numpy as np

from flowloop.calibrate import diff_ab, pylons
from tests.bench.size import pick

PRINTERS = pick(300, 5)
DISTANCES = (10.0, 150.0)
NOMINAL_RD = 40.0


def readings(rng, motion, shrink):
    s = pylons.along_row_positions(DISTANCES, 4.0)
    width = 4.0 * (1 - shrink) - 0.02
    out = []
    for k in (1, 2):
        true = motion * (s[k] - s[0]) * 1.0 + width
        values = true + rng.normal(0, 0.02 / 3, 5)
        slipped = rng.random(5) < 0.05
        values[slipped] += rng.uniform(0.1, 0.5, slipped.sum())
        out.append(values)
    return out


def scale_median(rng, motion, shrink):
    r = readings(rng, motion, shrink)
    return diff_ab.fit_axis([diff_ab.ReadingSet(d, tuple(v))
                             for d, v in zip(DISTANCES, r)]).scale


def scale_mean(rng, motion, shrink):
    r = readings(rng, motion, shrink)
    return (np.mean(r[1]) - np.mean(r[0])) / (DISTANCES[1] - DISTANCES[0])


def scale_trim(rng, motion, shrink):
    bar = motion * DISTANCES[1] * (1 - shrink) + rng.normal(0, 0.02 / 3, 5)
    return np.median(bar) / DISTANCES[1]


def residual_um_per_100mm(estimator, seed=11):
    rng = np.random.default_rng(seed)
    errors = []
    for _ in range(PRINTERS):
        belt = 1 + rng.uniform(-0.003, 0.003)
        shrink = rng.uniform(0.003, 0.006)
        rd = NOMINAL_RD
        for _round in range(2):
            motion = belt * NOMINAL_RD / rd
            rd = rd * estimator(rng, motion, shrink)
        errors.append(abs(belt * NOMINAL_RD / rd - 1) * 1e5)
    return float(np.mean(errors)), float(np.quantile(errors, 0.95))


def test_residual_error_after_two_rounds(bench):
    base_mean, base_p95 = residual_um_per_100mm(scale_median)
    bench.figure("diff_ab median estimator: mean residual", base_mean, " um/100mm",
                 goal="< 25 (0.025 %)")
    bench.figure("diff_ab median estimator: 95th percentile", base_p95, " um/100mm")
    mean_mean, _ = residual_um_per_100mm(scale_mean)
    bench.ratio("diff_ab spreadsheet mean vs median: residual", mean_mean, base_mean,
                " um/100mm", goal=">= 1.0x")
    trim_mean, _ = residual_um_per_100mm(scale_trim)
    bench.ratio("diff_ab measure-and-trim vs median: residual", trim_mean, base_mean,
                " um/100mm", goal=">> 1x")


def _per_call(fn, repeat=2000):
    start = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - start) / repeat


def test_estimator_and_gcode_timings(bench):
    r = [np.array([10.01, 10.02, 10.0, 10.01, 10.03]),
         np.array([150.31, 150.3, 150.32, 150.29, 150.33])]
    sets = [diff_ab.ReadingSet(d, tuple(v)) for d, v in zip(DISTANCES, r)]
    bare = _per_call(lambda: (sorted(r[1])[2] - sorted(r[0])[2]) / 140.0)
    full = _per_call(lambda: diff_ab.fit_axis(sets))
    bench.ratio("diff_ab fit_axis vs bare formula: time per call", full * 1e6,
                bare * 1e6, " us")

    options = pylons.PylonOptions()
    start = time.perf_counter()
    text = pylons.render(options)
    render_s = time.perf_counter() - start
    start = time.perf_counter()
    lines = []
    placed = pylons.pylons(options)
    for layer in range(50):
        for p in placed:
            for path in pylons.layer_paths(options, p, layer):
                lines.append(f"G0 X{path.start[0]:.3f} Y{path.start[1]:.3f}")
                for (x, y), e in path.moves:
                    lines.append(f"G1 X{x:.3f} Y{y:.3f} E{e:.5f} F3600")
    plain = "\n".join(lines)
    plain_s = time.perf_counter() - start
    bench.ratio("diff_ab pylon G-code: jinja2 render vs plain f-strings", render_s,
                plain_s, " s")
    bench.figure("diff_ab pylon G-code size", len(text) / 1024, " KiB")
    assert len(plain) > 0
