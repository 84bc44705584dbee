"""Differential A/B calibration: estimator, error budget, pylon G-code, CLI."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flowloop import cli
from flowloop.calibrate import diff_ab, pylons
from flowloop.errors import FlowloopError

W = 4.0   # nominal pylon width of the default part


def printed_readings(distances, scale, printed_width, width=W):
    """Outside-to-outside distances of a print: centres moved by `scale`,
    every pylon shrunk about its own centre to `printed_width`."""
    s = pylons.along_row_positions(distances, width)
    return [scale * (s[k] - s[0]) + printed_width for k in range(1, len(s))]


def sets(distances, readings):
    return [diff_ab.ReadingSet(d, tuple(np.atleast_1d(r).tolist()))
            for d, r in zip(distances, readings)]


# --- exact recovery ---

@settings(max_examples=200, deadline=None)
@given(scale=st.floats(0.98, 1.02), printed_width=st.floats(3.0, 4.5),
       d1=st.floats(9.0, 30.0), d2=st.floats(60.0, 200.0))
def test_noiseless_print_gives_the_scale_whatever_the_shrinkage(
        scale, printed_width, d1, d2):
    readings = printed_readings((d1, d2), scale, printed_width)
    fit = diff_ab.fit_axis(sets((d1, d2), readings))
    assert fit.scale == pytest.approx(scale, rel=1e-12)
    assert fit.printed_width_mm(W) == pytest.approx(printed_width, abs=1e-9)


def test_noiseless_calibration_scales_each_stepper_by_its_own_axis():
    ra = printed_readings((10, 150), 1.00221, 3.9)
    rb = printed_readings((10, 150), 0.99843, 3.8)
    cal = diff_ab.calibrate("corexy", 40.0, 40.0, sets((10, 150), ra),
                            sets((10, 150), rb))
    assert cal.a.stepper == "stepper_x" and cal.b.stepper == "stepper_y"
    assert cal.a.new_rotation_distance == pytest.approx(40.0 * 1.00221, rel=1e-12)
    assert cal.b.new_rotation_distance == pytest.approx(40.0 * 0.99843, rel=1e-12)
    assert not cal.converged


def test_least_squares_over_four_pylons_recovers_scale_width_and_flags_a_misread():
    distances = (10.0, 60.0, 110.0, 150.0)
    readings = printed_readings(distances, 0.9985, 3.85)
    fit = diff_ab.fit_axis(sets(distances, readings))
    assert fit.scale == pytest.approx(0.9985, rel=1e-12)
    assert fit.printed_width_mm(W) == pytest.approx(3.85, abs=1e-9)
    assert max(abs(r) for r in fit.residuals_mm) < 1e-9
    readings[1] += 0.1
    fit = diff_ab.fit_axis(sets(distances, readings))
    worst = int(np.argmax(np.abs(fit.residuals_mm)))
    assert worst == 1


def test_two_distances_give_the_papers_difference_formula():
    fit = diff_ab.fit_axis(sets((10, 150), (10.07, 150.28)))
    assert fit.scale == pytest.approx((150.28 - 10.07) / 140)
    # worst case of (eps1 + eps2) / (D2 - D1), one reading each
    b = diff_ab.ErrorBudget()
    eps = b.bed_expansion_mm + b.filament_mm + b.stepper_resolution_mm + 0.02
    assert fit.precision == pytest.approx(2 * eps / 140)


# --- error budget ---

def test_default_budget_matches_the_paper_for_five_readings():
    # five readings spread as the paper assumes: 3 sigma = 20 um
    sigma = 0.020 / 3
    offsets = np.array([-1.0, -0.5, 0.0, 0.5, 1.0])
    offsets = offsets * sigma / (1.4826 * np.median(np.abs(offsets)))
    budget = diff_ab.ErrorBudget()
    rs = diff_ab.ReadingSet(150.0, tuple(150.0 + offsets))
    assert budget.reading_sigma_mm(rs) == pytest.approx(sigma)
    assert budget.eps_max_mm(rs) == pytest.approx(0.017, abs=0.0006)
    fit = diff_ab.fit_axis([diff_ab.ReadingSet(10.0, tuple(10.0 + offsets)), rs])
    assert fit.precision < 2.5e-4                       # better than 0.025 %
    assert fit.uncertainty_pct == pytest.approx(0.038, abs=0.001)
    assert fit.uncertainty_um_per_100mm == pytest.approx(38, abs=1)


def test_stated_uncertainty_covers_a_monte_carlo_of_the_noise_model():
    rng = np.random.default_rng(7)
    budget = diff_ab.ErrorBudget()
    distances, true_scale, trials = (10.0, 150.0), 1.0012, 4000
    sigma = budget.reading_error_mm / 3
    ratios = []
    for _ in range(trials):
        true = printed_readings(distances, true_scale, 3.9)
        trueness = rng.uniform(-1, 1) * budget.trueness
        reading_sets = []
        for d, value in zip(distances, true):
            bounded = (rng.uniform(-1, 1) * budget.bed_expansion_mm
                       + rng.uniform(-1, 1) * budget.filament_mm
                       + rng.uniform(-1, 1) * budget.stepper_resolution_mm)
            noisy = (value + bounded + rng.normal(0, sigma, 5)) * (1 + trueness)
            reading_sets.append(diff_ab.ReadingSet(d, tuple(noisy)))
        fit = diff_ab.fit_axis(reading_sets, budget)
        ratios.append(abs(fit.scale - true_scale) / fit.uncertainty)
    ratios = np.array(ratios)
    # a worst-case (3 sigma) statement: almost never exceeded...
    assert np.mean(ratios > 1.0) < 0.005
    # ...yet not vacuous: the tail of the errors reaches a fair part of it
    assert np.quantile(ratios, 0.999) > 0.3


def test_more_readings_and_longer_rows_lower_the_uncertainty():
    def u(d2, n):
        rng = np.random.default_rng(1)
        noise = rng.normal(0, 0.005, (2, n))
        fit = diff_ab.fit_axis([diff_ab.ReadingSet(10.0, tuple(10 + noise[0])),
                                diff_ab.ReadingSet(d2, tuple(d2 + noise[1]))])
        return fit.precision
    assert u(150, 5) < u(60, 5)
    assert u(150, 9) < u(150, 3)


# --- robustness ---

def test_one_slipped_reading_does_not_move_the_scale():
    true = printed_readings((10, 150), 1.0015, 3.9)
    rng = np.random.default_rng(3)
    a1 = true[0] + rng.normal(0, 0.004, 5)
    a2 = true[1] + rng.normal(0, 0.004, 5)
    a2[2] += 0.35                 # the jaws slipped once
    fit = diff_ab.fit_axis(sets((10, 150), (a1, a2)))
    mean_scale = (np.mean(a2) - np.mean(a1)) / 140
    assert abs(fit.scale - 1.0015) < fit.precision
    assert abs(mean_scale - 1.0015) > fit.uncertainty   # a mean would be fooled
    assert fit.slipped == ((150.0, (float(a2[2]),)),)
    cal = diff_ab.calibrate("corexy", 40, 40, sets((10, 150), (a1, a2)),
                            sets((10, 150), true))
    assert any("check the readings of 150 mm" in ln for ln in cal.report_lines())


def test_a_bad_b_row_fails_the_whole_calibration():
    good = sets((10, 150), printed_readings((10, 150), 1.001, 3.9))
    with pytest.raises(FlowloopError, match="^B: readings must grow"):
        diff_ab.calibrate("corexy", 40, 40, good, sets((10, 150), (10.0, 9.5)))
    with pytest.raises(FlowloopError, match="^B: scale 1.03.* add FORCE=1"):
        diff_ab.calibrate("corexy", 40, 40, good, sets((10, 150), (10.0, 154.5)))
    forced = diff_ab.calibrate("corexy", 40, 40, good, sets((10, 150), (10.0, 154.5)),
                               force=True)
    assert forced.b.fit.scale == pytest.approx(144.5 / 140)


@pytest.mark.parametrize("kinematics", ["delta", "corexz", "hybrid_corexy", ""])
def test_other_kinematics_are_refused(kinematics):
    good = sets((10, 150), (10.0, 150.0))
    with pytest.raises(FlowloopError, match="needs corexy or cartesian"):
        diff_ab.calibrate(kinematics, 40, 40, good, good)


@pytest.mark.parametrize("limit", [0.0, -0.01, 0.21, 1.0, float("nan")])
def test_a_refusal_threshold_beyond_the_ceiling_is_refused(limit):
    # [diff_ab_calibrate] max_scale_change reads its maxval from the ceiling
    good = sets((10, 150), (10.0, 150.0))
    with pytest.raises(FlowloopError, match="max_scale_change"):
        diff_ab.calibrate("corexy", 40, 40, good, good, max_scale_change=limit)
    assert diff_ab.calibrate("corexy", 40, 40, good, good,
                             max_scale_change=diff_ab.MAX_SCALE_CHANGE_CEILING)


@pytest.mark.parametrize("rd", [0, -40, float("nan"), float("inf"), "x"])
def test_non_positive_rotation_distance_is_refused(rd):
    good = sets((10, 150), (10.0, 150.0))
    with pytest.raises(FlowloopError, match="rotation_distance A"):
        diff_ab.calibrate("cartesian", rd, 40, good, good)


def test_convergence_rule():
    assert diff_ab.is_converged(1.0002, 0.0)            # below 0.025 %
    assert not diff_ab.is_converged(1.0003, 0.0001)
    assert diff_ab.is_converged(1.0003, 0.0004)         # below the uncertainty
    assert diff_ab.is_converged(0.99975 + 1e-9, 0.0)


def test_history_is_plain_json_data_numbered_by_iteration():
    first = diff_ab.calibrate("corexy", 40, 40,
                              sets((10, 150), printed_readings((10, 150), 1.002, 3.9)),
                              sets((10, 150), printed_readings((10, 150), 0.998, 3.9)))
    second = diff_ab.calibrate("corexy", first.a.new_rotation_distance,
                               first.b.new_rotation_distance,
                               sets((10, 150), printed_readings((10, 150), 1.0, 3.9)),
                               sets((10, 150), printed_readings((10, 150), 1.0, 3.9)))
    history = diff_ab.append_history(diff_ab.append_history([], first), second)
    assert json.loads(json.dumps(history)) == history
    assert [e["iteration"] for e in history] == [1, 2]
    assert [e["converged"] for e in history] == [False, True]
    assert history[0]["a"]["rotation_distance"] == pytest.approx(40 * 1.002)


def test_a_trimmed_history_keeps_counting_iterations():
    cal = diff_ab.calibrate("corexy", 40, 40, sets((10, 150), (10.0, 150.0)),
                            sets((10, 150), (10.0, 150.0)))
    history = []
    for _ in range(13):
        history = diff_ab.append_history(history, cal, keep=10)
    assert [e["iteration"] for e in history] == list(range(4, 14))


@pytest.mark.parametrize("data", [{}, [1], [{"iteration": 1}],
                                  [{"iteration": "1", "converged": False,
                                    "a": {}, "b": {}}]])
def test_a_history_file_that_is_not_ours_is_one_line(tmp_path, capsys, data):
    history = tmp_path / "ab.json"
    history.write_text(json.dumps(data))
    assert cli.main(ARGS + ["--history", str(history)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(history) in err, err
    assert json.loads(history.read_text()) == data     # left as it was


# --- where rotation_distance lives ---

# --- the pylon G-code, parsed back ---

def extrusions_by_layer(gcode):
    """{z: [[(x0, y0), (x1, y1)] per extruding move]} from absolute-XY G-code."""
    x = y = z = None
    layers = {}
    for line in gcode.splitlines():
        code = line.split(";", 1)[0].split()
        if not code or code[0] not in ("G0", "G1"):
            continue
        words = {w[0]: float(w[1:]) for w in code[1:]}
        nx, ny, nz = words.get("X", x), words.get("Y", y), words.get("Z", z)
        if words.get("E", 0.0) > 0 and "X" in words:
            layers.setdefault(round(nz, 4), []).append(((x, y), (nx, ny)))
        x, y, z = nx, ny, nz
    return layers


def clusters(segments, link_mm=1.0):
    """Group extruding moves into pylons: moves whose ends lie within link_mm
    of each other belong together (loops are 0.5 mm apart, pylons >= 2 mm)."""
    parent = list(range(len(segments)))

    def root(i):
        while parent[i] != i:
            i = parent[i]
        return i

    for i, a in enumerate(segments):
        for j in range(i):
            if min(math.dist(p, q) for p in a for q in segments[j]) < link_mm:
                parent[root(i)] = root(j)
    groups = {}
    for i, seg in enumerate(segments):
        groups.setdefault(root(i), []).append(seg)
    return list(groups.values())


@pytest.mark.parametrize("kinematics,distances", [
    ("corexy", (10.0, 150.0)), ("cartesian", (10.0, 150.0)),
    ("corexy", (12.0, 70.0, 140.0))])
def test_pylon_centres_sit_where_d1_d2_say_on_the_right_diagonal(kinematics, distances):
    o = pylons.PylonOptions(kinematics=kinematics, distances_mm=distances,
                            bed_size_x_mm=300, bed_size_y_mm=300, centre_x_mm=140,
                            centre_y_mm=160)
    gcode = pylons.render(o)
    layers = extrusions_by_layer(gcode)
    assert len(layers) == round(o.pylon_height_mm / o.layer_height_mm)
    z = sorted(layers)[7]
    groups = clusters(layers[z])
    assert len(groups) == 2 * (len(distances) + 1)
    r = math.sqrt(0.5)
    rows = {"corexy": {"a": (r, r), "b": (r, -r)},
            "cartesian": {"a": (1, 0), "b": (0, 1)}}[kinematics]
    cx, cy = 140, 160
    for axis, (ux, uy) in rows.items():
        vx, vy = -uy, ux
        row = []
        for g in groups:
            pts = [p for seg in g for p in seg]
            along = [(px - cx) * ux + (py - cy) * uy for px, py in pts]
            across = [(px - cx) * vx + (py - cy) * vy for px, py in pts]
            centre_across = (max(across) + min(across)) / 2
            if abs(centre_across) < 1e-3:      # on this row's line
                row.append((min(along) - o.line_width_mm / 2,
                            max(along) + o.line_width_mm / 2))
        assert len(row) == len(distances) + 1, axis
        row.sort()
        for (lo, hi) in row:
            assert hi - lo == pytest.approx(o.pylon_width_mm, abs=2e-3)
        for k, d in enumerate(distances, start=1):
            assert row[k][1] - row[0][0] == pytest.approx(d, abs=2e-3)


def test_pylons_are_printed_outer_loop_first_with_seams_off_the_measured_faces():
    o = pylons.PylonOptions()
    for layer in (0, 1):
        for p in pylons.pylons(o):
            paths = pylons.layer_paths(o, p, layer)
            extents = []
            for path in paths:
                pts = [path.start] + [pt for pt, _ in path.moves]
                along = [(x - p.centre[0]) * p.along[0] + (y - p.centre[1]) * p.along[1]
                         for x, y in pts]
                extents.append(max(along) - min(along))
                # the seam (start) is mid-way on a side face, not on a measured face
                assert abs(along[0]) < 1e-9
            assert extents == sorted(extents, reverse=True)
            assert extents[0] == pytest.approx(o.pylon_width_mm - o.line_width_mm)


def test_pylons_are_solid():
    o = pylons.PylonOptions(pylon_width_mm=4.3)
    loops, centre = pylons.pylon_loops(o)
    lw = o.line_width_mm
    filled = 2 * len(loops) * lw + (centre or 0.0)
    assert filled == pytest.approx(o.pylon_width_mm)


@pytest.mark.parametrize("kwargs,message", [
    ({"distances_mm": (7.0, 150.0)}, "gap"),
    ({"distances_mm": (150.0, 10.0)}, "increase"),
    ({"bed_size_x_mm": 100.0}, "does not fit"),
    ({"hotend_temp_c": 400.0}, "from 150 to 320 C"),
    ({"kinematics": "delta"}, "corexy or cartesian"),
    ({"distances_mm": (10.0, 80.0, 84.0, 150.0)}, "too close"),
])
def test_impossible_parts_are_refused(kwargs, message):
    with pytest.raises(FlowloopError, match=message):
        pylons.render(pylons.PylonOptions(**kwargs))


def test_gcode_keeps_the_bed_hot_and_never_exceeds_the_asked_speeds():
    # a print speed below the default first-layer speed (20 mm/s)
    o = pylons.PylonOptions(print_speed_mm_s=15, travel_speed_mm_s=120,
                            wait_bed_equilibrium=True, start_gcode="G28\\nBED_MESH")
    gcode = pylons.render(o)
    feeds = [float(m) for m in re.findall(r"^G[01] .*F(\d+(?:\.\d+)?)", gcode, re.M)]
    assert max(feeds) <= 120 * 60
    extruding = [float(m) for m in re.findall(r"^G1 X.* E[\d.]+ F(\d+)", gcode, re.M)]
    assert extruding and max(extruding) <= 15 * 60
    assert "M140 S0" not in gcode and "M190 S0" not in gcode
    assert gcode.index("M190 S60") < gcode.index("WAIT_BED_EQUILIBRIUM") \
        < gcode.index("M109 S215")
    assert "\nBED_MESH\n" in gcode
    assert "DIFF_AB_CALIBRATE D1=10 D2=150 A1=" in gcode


# --- the CLI ---

ARGS = ["ab-calibrate", "--rotation-distance-a", "40", "--rotation-distance-b", "39.8",
        "--a1", "10.01,10.02,10.0,10.01,10.03",
        "--a2", "150.31,150.33,150.32,150.30,150.9",
        "--b1", "10.0 10.01 10.0", "--b2", "149.80,149.82,149.81"]


def test_cli_json_has_the_documented_shape(capsys):
    assert cli.main(ARGS + ["--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"a", "b", "converged"}
    for axis in ("a", "b"):
        assert set(out[axis]) == {"scale", "rotation_distance", "uncertainty_pct"}
    assert out["a"]["scale"] == pytest.approx((150.32 - 10.01) / 140)
    assert out["b"]["rotation_distance"] == pytest.approx(39.8 * (149.81 - 10.0) / 140)
    assert out["converged"] is False


def test_cli_human_report_and_history(capsys, tmp_path):
    history = tmp_path / "ab.json"
    assert cli.main(ARGS + ["--history", str(history)]) == 0
    assert cli.main(ARGS + ["--history", str(history)]) == 0
    out = capsys.readouterr().out
    assert "[stepper_x] rotation_distance: 40.0" in out
    assert "#2:" in out
    assert [e["iteration"] for e in json.loads(history.read_text())] == [1, 2]


@pytest.mark.parametrize("change,message", [
    (["--a1", "10,nan"], "A1: 'nan' is not a finite number"),
    (["--b2", "9"], "B: readings must grow"),
    (["--rotation-distance-a", "-1"], "--rotation-distance-a must be a positive"),
    (["--a2", "154"], "A: scale .* add --force"),
    (["--d2", "10"], "D2 .* must be greater than D1"),
    (["--a3", "80"], "A3 needs D3=<nominal distance>"),
    (["--d4", "80"], "D4 is given but neither A4 nor B4 readings"),
    (["--a9", "1", "--d9", "1"], "D9 .* must be greater than D2"),
    (["--caliper-accuracy", "nan"], "--caliper-accuracy must be a finite number"),
    (["--caliper-range", "-1e-3"], "--caliper-range must be a finite number >= 0"),
])
def test_cli_bad_input_exits_with_one_line(capsys, change, message):
    args = list(ARGS)
    for flag, value in zip(change[::2], change[1::2]):
        if flag in args:
            args[args.index(flag) + 1] = value
        else:
            args += [flag, value]
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and re.search(message, err), err


def test_cli_force_accepts_a_large_scale(capsys):
    args = list(ARGS)
    args[args.index("--a2") + 1] = "154"
    assert cli.main(args + ["--force", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["a"]["scale"] > 1.02


@pytest.mark.parametrize("option, value, message", [
    ("--speed", "inf", "--speed must be a number above 0 and at most 1000 mm/s,"
                       " got inf"),
    ("--accel", "-1e3", "--accel must be a number above 0 and at most 100000"
                        " mm/s^2, got -1000"),
    ("--centre-x", "nan", "--centre-x must be a finite number, got nan"),
    ("--d2", "nan", "D2 must be a number in (0, 1000], got nan"),
])
def test_pylon_errors_name_the_flag_that_was_typed(tmp_path, capsys, option, value,
                                                   message):
    out = tmp_path / "p.gcode"
    assert cli.main(["ab-pylons", "-o", str(out), option, value]) == 2
    assert capsys.readouterr().err == f"flowloop ab-pylons: error: {message}\n"
    assert not out.exists()


def test_cli_writes_pylon_gcode(tmp_path, capsys):
    out = tmp_path / "p.gcode"
    assert cli.main(["ab-pylons", "-o", str(out), "--kinematics", "cartesian",
                     "--d2", "80", "--d3", "150", "--bed-temp", "70"]) == 0
    text = out.read_text()
    assert "kinematics: cartesian" in text and "M190 S70" in text
    assert "D1=10 D2=80 D3=150" in text
    assert cli.main(["ab-pylons", "-o", str(out), "--bed-x", "90"]) == 2
    assert "does not fit" in capsys.readouterr().err


# --- bed equilibrium ---

def simulated_bed(detector, minutes, tau_min=6.0, heat_up_s=90):
    """A bed at 60 C whose holding power decays from 60 % to 30 % with time
    constant tau (the frame warming up), with PWM noise. Returns the time
    (s) the detector first says 'equilibrium', or None."""
    rng = np.random.default_rng(5)
    for t in range(0, int(minutes * 60)):
        temp = 60.0 if t >= heat_up_s else 20.0 + 40.0 * t / heat_up_s
        power = 0.30 + 0.30 * math.exp(-t / (tau_min * 60)) + rng.normal(0, 0.01)
        if detector.add(float(t), power, temp, 60.0) == "equilibrium":
            return t
    return None


def test_bed_equilibrium_waits_until_the_power_stops_falling():
    detector = diff_ab.BedEquilibrium(tolerance_pct_per_min=0.5, window_s=120)
    t = simulated_bed(detector, minutes=60)
    # the slope 30 %/tau * exp(-t/tau) falls below 0.5 %/min at t = tau*ln(10)
    expected = 6.0 * 60 * math.log(0.30 * 100 / 6.0 / 0.5)
    assert t is not None and abs(t - expected) < 120
    assert detector.slope_pct_per_min() > -0.5


def test_bed_equilibrium_states():
    detector = diff_ab.BedEquilibrium(window_s=10)
    assert detector.add(0.0, 0.0, 20.0, 0.0) == "off"
    assert detector.add(1.0, 1.0, 40.0, 60.0) == "heating"
    assert detector.add(2.0, 0.5, 59.0, 60.0) == "settling"
    for t in range(3, 14):
        state = detector.add(float(t), 0.5 - 0.01 * t, 60.0, 60.0)
    assert state == "falling"                      # -60 %/min
    assert detector.add(14.0, 0.3, 55.0, 60.0) == "heating"   # left the band
    with pytest.raises(FlowloopError, match="TOLERANCE"):
        diff_ab.BedEquilibrium(tolerance_pct_per_min=0)


def test_pylon_gcode_keeps_the_printers_acceleration_unless_asked():
    """Klipper accepts an ACCEL above max_accel: only the user may raise it."""
    assert "SET_VELOCITY_LIMIT" not in pylons.render(pylons.PylonOptions())
    gcode = pylons.render(pylons.PylonOptions(accel_mm_s2=1500))
    assert "SET_VELOCITY_LIMIT ACCEL=1500" in gcode
    with pytest.raises(FlowloopError, match="accel_mm_s2"):
        pylons.render(pylons.PylonOptions(accel_mm_s2=-1))
