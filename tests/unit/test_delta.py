"""Delta kinematics and the ENDSTOP_CALIBRATE solver on synthetic printers."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flowloop.calibrate.delta import (
    DEFAULT_ANGLES_DEG,
    DeltaGeometry,
    check_flatness,
    geometry_from_config,
    median_of_samples,
    naive_endstop_update,
    probe_points,
    simulate_probe_z,
    solve_endstops,
)
from flowloop.errors import FlowloopError
from flowloop.host.klipper_config import parse_config

finite = dict(allow_nan=False, allow_infinity=False)


@st.composite
def printers(draw, angle_error_deg=0.0):
    radius = draw(st.floats(60.0, 200.0, **finite))
    arm = draw(st.floats(radius * 2.0, radius * 2.6, **finite))
    arms = tuple(arm + draw(st.floats(-1.0, 1.0, **finite)) for _ in range(3))
    height = draw(st.floats(150.0, 400.0, **finite))
    angles = tuple(a + draw(st.floats(-angle_error_deg, angle_error_deg, **finite))
                   for a in DEFAULT_ANGLES_DEG)
    return DeltaGeometry(radius, arms, (height, height, height), angles)


endstop_errors = st.tuples(*[st.floats(-5.0, 5.0, **finite)] * 3)


def probes_on(believed, true, points, bed_z=0.0):
    z = simulate_probe_z(believed, true, points, bed_z)
    return [(x, y, zz) for (x, y), zz in zip(points, z)]


def seven_points(geometry, fraction=0.7):
    return probe_points(geometry.angles_deg, geometry.radius * fraction)


def test_probe_points_are_the_centre_then_near_then_opposite_each_tower():
    points = probe_points((210.0, 329.8, 90.0), 100.0)
    assert points[0] == (0.0, 0.0)
    angles = [math.degrees(math.atan2(y, x)) % 360 for x, y in points[1:]]
    assert angles == pytest.approx([210.0, 329.8, 90.0, 30.0, 149.8, 270.0])
    assert [math.hypot(*p) for p in points[1:]] == pytest.approx([100.0] * 6)
    assert probe_points((210.0, 329.8, 90.0), 100.0, opposite=False) == points[:4]
    assert probe_points((210.0, 329.8, 90.0), 100.0, False, False) == points[1:4]


# --- kinematics --------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(printers(angle_error_deg=3.0), st.floats(0, 2 * math.pi), st.floats(0, 0.8),
       st.floats(-20.0, 100.0, **finite))
def test_forward_kinematics_inverts_inverse_kinematics(geometry, phi, frac, z):
    r = frac * geometry.radius
    xyz = (r * math.cos(phi), r * math.sin(phi), z)
    back = geometry.position(geometry.carriage_heights(xyz))
    assert np.allclose(back, xyz, atol=1e-9)
    assert np.allclose(geometry.position_from_travel(geometry.travel(xyz)), xyz,
                       atol=1e-9)


def test_homed_effector_is_at_the_centre_at_the_endstop_height():
    g = DeltaGeometry(140.0, (300.0, 300.0, 300.0), (310.0, 310.0, 310.0))
    assert np.allclose(g.position(g.abs_endstops), (0.0, 0.0, 310.0), atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(printers(angle_error_deg=2.0), st.floats(0, 2 * math.pi), st.floats(0, 0.8))
def test_height_derivative_matches_finite_differences_and_sums_to_one(geometry, phi,
                                                                      frac):
    r = frac * geometry.radius
    xyz = (r * math.cos(phi), r * math.sin(phi), 5.0)
    carriages = geometry.carriage_heights(xyz)
    h = 1e-6
    numeric = [(geometry.position(carriages + h * np.eye(3)[i])[2]
                - geometry.position(carriages - h * np.eye(3)[i])[2]) / (2 * h)
               for i in range(3)]
    analytic = geometry.dz_dcarriages(xyz)
    assert np.allclose(analytic, numeric, atol=1e-6)
    # Raising all carriages together raises the effector by the same amount.
    assert math.isclose(analytic.sum(), 1.0, abs_tol=1e-9)


def test_a_point_out_of_reach_is_refused():
    g = DeltaGeometry(100.0, (200.0, 200.0, 200.0), (300.0, 300.0, 300.0))
    with pytest.raises(FlowloopError, match="reach"):
        g.carriage_heights((400.0, 0.0, 0.0))


def test_arms_shorter_than_the_radius_are_refused():
    with pytest.raises(FlowloopError, match="stepper_b arm_length"):
        DeltaGeometry(150.0, (300.0, 140.0, 300.0), (300.0, 300.0, 300.0))


# --- the solver ----------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(printers(), endstop_errors, st.booleans())
def test_known_endstop_errors_are_recovered_to_well_under_a_micron(geometry, errors,
                                                                   four_points):
    true = geometry.with_endstops(np.add(geometry.position_endstops, errors))
    points = (probe_points(geometry.angles_deg, 0.7 * geometry.radius, opposite=False)
              if four_points else seven_points(geometry))
    result = solve_endstops(geometry, probes_on(geometry, true, points))
    assert np.allclose(result.position_endstop, true.position_endstops, atol=1e-6)
    assert result.residual_mm < 1e-6
    assert result.geometry_warning is None


def test_three_tower_points_without_the_centre_are_enough():
    g = DeltaGeometry(120.0, (250.0, 251.0, 249.5), (280.0, 280.0, 280.0))
    true = g.with_endstops((281.3, 278.9, 280.4))
    points = probe_points(g.angles_deg, 90.0, opposite=False, centre=False)
    result = solve_endstops(g, probes_on(g, true, points))
    assert np.allclose(result.position_endstop, true.position_endstops, atol=1e-9)


def test_a_probe_z_offset_is_the_height_each_probe_should_read():
    g = DeltaGeometry(140.0, (300.0, 300.0, 300.0), (300.0, 300.0, 300.0))
    true = g.with_endstops((298.8, 301.1, 300.2))
    points = seven_points(g)
    probes = probes_on(g, true, points, bed_z=1.25)
    result = solve_endstops(g, probes, bed_z=[1.25] * len(probes))
    assert np.allclose(result.position_endstop, true.position_endstops, atol=1e-9)
    assert max(abs(h) for h in result.heights_before_mm) > 0.5


def test_report_names_each_towers_probe_and_predicts_a_flat_bed():
    g = DeltaGeometry(140.0, (300.0, 300.0, 300.0), (300.0, 300.0, 300.0))
    true = g.with_endstops((301.5, 298.5, 300.0))
    points = probe_points(g.angles_deg, 100.0, opposite=False)
    result = solve_endstops(g, probes_on(g, true, points))
    assert result.tower_probe_index == (1, 2, 3)
    # Tower A really homes 1.5 mm higher than believed: near it the nozzle is
    # higher than it thinks, so it touches the bed at a negative believed z.
    assert result.heights_before_mm[1] < -0.5 < 0.5 < result.heights_before_mm[2]
    assert result.spread_before_mm > 1.5
    assert result.spread_after_mm < 1e-9
    assert np.allclose(result.corrections_mm, (1.5, -1.5, 0.0), atol=1e-9)
    out = result.to_json()
    assert set(out) == {"position_endstop", "residual_mm", "spread_before_mm",
                        "spread_after_mm"}
    assert list(out["position_endstop"]) == ["stepper_a", "stepper_b", "stepper_c"]


@settings(max_examples=30, deadline=None)
@given(printers(), endstop_errors, st.sampled_from([-1, 1]), st.floats(0.4, 3.0),
       st.sampled_from([0, 1, 2]))
def test_residual_warning_fires_when_a_tower_angle_is_off(geometry, errors, sign,
                                                         sideways_mm, tower):
    # A tower standing sideways_mm off its line (0.4 mm is 0.16 deg at r=140).
    angles = list(geometry.angles_deg)
    angles[tower] += sign * math.degrees(sideways_mm / geometry.radius)
    true = DeltaGeometry(geometry.radius, geometry.arm_lengths,
                         tuple(np.add(geometry.position_endstops, errors)),
                         tuple(angles))
    result = solve_endstops(geometry, probes_on(geometry, true, seven_points(geometry)))
    assert result.geometry_warning is not None
    assert "DELTA_CALIBRATE" in result.geometry_warning


@pytest.mark.parametrize("radius_error", [-0.4, 0.3])
def test_residual_warning_fires_when_the_radius_is_off_even_with_four_points(
        radius_error):
    g = DeltaGeometry(140.0, (300.0, 300.0, 300.0), (300.0, 300.0, 300.0))
    true = DeltaGeometry(140.0 + radius_error, g.arm_lengths, (300.7, 299.4, 300.1))
    points = probe_points(g.angles_deg, 100.0, opposite=False)
    result = solve_endstops(g, probes_on(g, true, points))
    assert result.geometry_warning is not None
    assert result.residual_mm > 0.01


def test_four_points_cannot_see_an_angle_error_so_the_docs_ask_for_seven():
    # Documented limit: near-tower and centre probes absorb a tower angle error
    # into the endstops; probes opposite the towers expose it.
    g = DeltaGeometry(140.0, (300.0, 300.0, 300.0), (300.0, 300.0, 300.0))
    true = DeltaGeometry(140.0, g.arm_lengths, (300.0, 300.0, 300.0),
                         (210.5, 330.0, 90.0))
    four_points = probe_points(g.angles_deg, 100, opposite=False)
    four = solve_endstops(g, probes_on(g, true, four_points))
    seven = solve_endstops(g, probes_on(g, true, seven_points(g, 100 / 140)))
    assert four.residual_mm < 0.005
    assert seven.residual_mm > 0.03


@pytest.mark.parametrize("probes, message", [
    ([(0, 0, 0.1), (50, 0, 0.2)], "at least 3"),
    ([(0, 0, 0.1), (50, 0, float("nan")), (0, 50, 0.0)], "not finite"),
    ([(0, 0, 0.1), (0, 0, 0.2), (0, 0, 0.3)], "tell the three towers apart"),
    ([(0, 0), (1, 1), (2, 2)], "x, y and z"),
])
def test_bad_probes_are_refused_in_one_line(probes, message):
    g = DeltaGeometry(140.0, (300.0, 300.0, 300.0), (300.0, 300.0, 300.0))
    with pytest.raises(FlowloopError, match=message) as info:
        solve_endstops(g, probes)
    assert "\n" not in str(info.value)


# --- what ENDSTOP_CALIBRATE decides ---------------------------------------------------


def test_each_point_is_the_median_of_its_samples_so_one_outlier_does_not_count():
    rows = [(0, 0, 0.10, 0), (0, 0, 0.90, 0), (0, 0, 0.12, 0),
            (50, 0, -0.2, 0), (50, 0, -0.21, 0), (50, 0, -3.0, 0)]
    assert median_of_samples(rows, 3).tolist() == [[0, 0, 0.12, 0], [50, 0, -0.21, 0]]
    with pytest.raises(FlowloopError, match="groups of 4"):
        median_of_samples(rows, 4)


@pytest.mark.parametrize("heights, ok", [
    ((0.004, -0.004, 0.0), True),
    ((0.03, 0.0, 0.0), False),  # not flat
    ((0.03, 0.03, 0.03), False),  # flat but the nozzle is 0.03 mm high everywhere
])
def test_verification_needs_a_flat_bed_at_the_right_height(heights, ok):
    assert check_flatness(heights, 0.01).within_tolerance is ok


# --- the documented comparison with the per-tower loop ----------------------------


def rounds_to_flat(update, believed, true, points, limit_mm=0.01, max_rounds=100):
    for rounds in range(1, max_rounds + 1):
        probes = probes_on(believed, true, points)
        believed = believed.with_endstops(update(believed, probes))
        after = simulate_probe_z(believed, true, points)
        if np.ptp(after) < limit_mm and np.max(np.abs(after)) < limit_mm:
            return rounds
    return max_rounds + 1


def test_the_solver_needs_one_round_where_the_per_tower_loop_needs_many():
    believed = DeltaGeometry(140.0, (300.0,) * 3, (300.0,) * 3)
    true = believed.with_endstops((301.5, 298.5, 300.8))
    points = probe_points(believed.angles_deg, 100.0, opposite=False)

    def solver(g, probes):
        return solve_endstops(g, probes).position_endstop

    def naive(g, probes):
        towers = [probes[i][2] for i in (1, 2, 3)]
        return naive_endstop_update(g.position_endstops, towers)

    assert rounds_to_flat(solver, believed, true, points) == 1
    naive_rounds = rounds_to_flat(naive, believed, true, points)
    # docs/endstop_calibrate.md quotes this count (4 rounds at 100/140 of the radius,
    # 7 at half the radius, where a point near a tower hangs more on the others).
    assert naive_rounds == 4
    inner = probe_points(believed.angles_deg, 70.0, opposite=False)
    assert rounds_to_flat(naive, believed, true, inner) == 7
    assert rounds_to_flat(solver, believed, true, inner) == 1


def test_naive_update_lowers_each_endstop_by_its_towers_height():
    assert naive_endstop_update((300.0, 301.0, 299.0), (0.2, -0.1, 0.0)) == (
        pytest.approx(299.8), pytest.approx(301.1), pytest.approx(299.0))


# --- geometry from printer.cfg ------------------------------------------------------


DELTA_CFG = """
[printer]
kinematics: delta
delta_radius: 140

[stepper_a]
arm_length: 300
position_endstop: 305.5
[stepper_b]
angle: 331
[stepper_c]
arm_length: 301.25
"""


def test_geometry_is_read_with_klippers_defaults():
    g = geometry_from_config(parse_config(DELTA_CFG))
    assert g.radius == 140.0
    assert g.arm_lengths == (300.0, 300.0, 301.25)
    assert g.position_endstops == (305.5, 305.5, 305.5)
    assert g.angles_deg == (210.0, 331.0, 90.0)


@pytest.mark.parametrize("text, message", [
    ("[printer]\nkinematics: cartesian\n", "not a delta printer config"),
    (DELTA_CFG.replace("delta_radius: 140", ""), "'delta_radius' in section 'printer'"),
    (DELTA_CFG.replace("position_endstop: 305.5", ""),
     "'position_endstop' in section 'stepper_a'"),
    (DELTA_CFG.replace("[stepper_c]", "[stepper_d]"), r"no \[stepper_c\]"),
    (DELTA_CFG.replace("301.25", "abc"), "'arm_length' in section 'stepper_c'"),
    (DELTA_CFG.replace("301.25", "100"), "must be above 140"),
])
def test_a_config_klippy_would_refuse_is_refused_naming_the_option(text, message):
    with pytest.raises(FlowloopError, match=message):
        geometry_from_config(parse_config(text))


# --- flowloop delta-endstops ----------------------------------------------------------

KLIPPY_TESTS = Path(__file__).parents[1] / "klippy"


def cli(capsys, *argv):
    from flowloop.cli import main
    code = main(["delta-endstops", *argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_cli_json_uses_the_save_config_block_of_printer_cfg(capsys, tmp_path):
    # endstop_calibrate_saved.cfg: endstops 301.2, 298.8, 300.5 in the block.
    saved = parse_config((KLIPPY_TESTS / "endstop_calibrate_saved.cfg").read_text())
    believed = geometry_from_config(saved)
    assert believed.position_endstops == (301.2, 298.8, 300.5)
    true = believed.with_endstops((301.0, 299.1, 300.5))
    points = probe_points(believed.angles_deg, 100.0, opposite=False)
    args = []
    for x, y, z in probes_on(believed, true, points, bed_z=0.4):
        args.append(f"--probe={x:.9f},{y:.9f},{z:.9f}")
    code, out, err = cli(capsys, "--printer-cfg",
                         str(KLIPPY_TESTS / "endstop_calibrate_saved.cfg"),
                         "--z-offset", "0.4", "--json", *args)
    assert code == 0, err
    result = json.loads(out)
    assert set(result) == {"position_endstop", "residual_mm", "spread_before_mm",
                           "spread_after_mm"}
    assert result["position_endstop"] == pytest.approx(
        {"stepper_a": 301.0, "stepper_b": 299.1, "stepper_c": 300.5}, abs=1e-6)
    assert result["spread_before_mm"] > 0.2
    assert result["spread_after_mm"] < 1e-6


def test_cli_prints_a_per_tower_report(capsys):
    code, out, _ = cli(capsys, "--printer-cfg",
                       str(KLIPPY_TESTS / "endstop_calibrate.cfg"),
                       "--probe", "0,0,0.1", "--probe=-86.6,-50,0.3",
                       "--probe", "86.6,-50,-0.2", "--probe", "0,100,0.0")
    assert code == 0
    assert "[stepper_a] position_endstop: 299." in out
    assert "[stepper_b] position_endstop: 300." in out
    assert "predicted after" in out


@pytest.mark.parametrize("cfg, probes, message", [
    ("endstop_calibrate_cartesian.cfg", ["0,0,0"] * 3, "not a delta printer config"),
    ("endstop_calibrate.cfg", ["0,0,0", "10,0,0"], "at least 3 --probe"),
    ("endstop_calibrate.cfg", ["0,0,0", "10,0,inf", "0,10,0"],
     "--probe 10,0,inf: 'inf' is not a finite number"),
    ("endstop_calibrate.cfg", ["0,0", "10,0,0", "0,10,0"],
     "--probe 0,0: needs 3 coordinates, got 2"),
    ("absent.cfg", ["0,0,0"] * 3, "cannot read config file"),
])
def test_cli_errors_are_one_line_and_exit_non_zero(capsys, cfg, probes, message):
    args = ["--printer-cfg", str(KLIPPY_TESTS / cfg)]
    for p in probes:
        args.append(f"--probe={p}")
    code, out, err = cli(capsys, *args)
    assert code != 0
    assert message in err
    assert err.count("\n") == 1 and not out


def test_cli_names_a_missing_option(capsys, tmp_path):
    text = (KLIPPY_TESTS / "endstop_calibrate.cfg").read_text()
    cfg = tmp_path / "printer.cfg"
    # (without the test macros it includes from its own folder)
    cfg.write_text(text.replace("arm_length: 300.0\n", "")
                   .replace("[include asserts.cfg]\n", ""))
    code, _, err = cli(capsys, "--printer-cfg", str(cfg), "--probe=0,0,0",
                       "--probe=1,0,0", "--probe=0,1,0")
    assert code != 0
    assert "'arm_length' in section 'stepper_a' must be specified" in err
