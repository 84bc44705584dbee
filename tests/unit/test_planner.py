"""The flow planner: G-code to flow in print time, as Klipper runs it."""

from __future__ import annotations

import codecs
import io
import math
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flowloop.errors import FlowloopError
from flowloop.gcode import bulk_planner
from flowloop.gcode.reference_planner import (
    Barrier,
    Planner,
    PrinterLimits,
    Segment,
    limits_from_config,
    plan_file,
    plan_text,
)
from flowloop.host.klipper_config import parse_config

pytestmark = pytest.mark.unit

DATA = Path(__file__).resolve().parents[1] / "data" / "gcode"
AREA = math.pi * 0.875 ** 2          # 1.75 mm filament
LIMITS = PrinterLimits(max_velocity=300, max_accel=1000)


def segments(text: str, limits: PrinterLimits = LIMITS):
    return [e for e in plan_text(text, limits) if isinstance(e, Segment)]


# --- trapezoids, computed by hand --------------------------------------------------

def test_a_long_move_accelerates_cruises_and_stops():
    # 100 mm at 100 mm/s, 1000 mm/s^2: 5 mm (0.1 s) each way, 90 mm cruise (0.9 s)
    (s,) = segments("G1 X100 F6000")
    assert s.speed_mm_s == pytest.approx(100.0)
    assert s.accel_s == pytest.approx(0.1)
    assert s.decel_s == pytest.approx(0.1)
    assert s.duration_s == pytest.approx(1.1)
    assert s.distance_mm == pytest.approx(100.0)


def test_a_short_move_keeps_half_its_length_for_cruise():
    # minimum_cruise_ratio 0.5: peak v^2 = a * d * (1 - 0.5) = 2000 on 4 mm,
    # 1 mm up, 2 mm cruise, 1 mm down, each 1 mm / sqrt(2000) * 2 or / v
    (s,) = segments("G1 X4 F6000")
    v = math.sqrt(2000.0)
    assert s.speed_mm_s == pytest.approx(v)
    assert s.duration_s == pytest.approx(2 * (1 / (v / 2)) + 2 / v)


def test_without_minimum_cruise_ratio_a_short_move_is_a_triangle():
    limits = PrinterLimits(max_velocity=300, max_accel=1000, minimum_cruise_ratio=0)
    (s,) = segments("G1 X4 F6000", limits)
    assert s.speed_mm_s == pytest.approx(math.sqrt(1000 * 4))
    # 2 mm up and 2 mm down at 1000 mm/s^2: t = 2 * sqrt(2 * 2 / 1000)
    assert s.duration_s == pytest.approx(2 * math.sqrt(2 * 2 / 1000))


def test_a_square_corner_is_taken_at_square_corner_velocity():
    first, second = segments("G1 X100 F6000\nG1 X100 Y100")
    # decelerate 100 -> 5 mm/s: (100^2 - 5^2) / 2a = 4.9875 mm
    assert first.end_flow_mm3_s == 0.0
    assert first.decel_s == pytest.approx((100 - 5) / 1000)
    assert second.accel_s == pytest.approx((100 - 5) / 1000)
    assert first.start_s + first.duration_s == pytest.approx(second.start_s)


def test_a_straight_continuation_does_not_slow_down():
    first, second = segments("G1 X50 F6000\nG1 X100")
    assert first.decel_s == 0.0 and second.accel_s == 0.0
    assert first.duration_s + second.duration_s == pytest.approx(1.1)


def test_a_change_of_extrusion_rate_is_a_corner_for_the_extruder():
    # instantaneous_corner_velocity 1 mm/s over 0.1 mm of E per mm: 10 mm/s
    first, second = segments("M83\nG1 X50 F6000\nG1 X100 E5")
    assert first.decel_s == pytest.approx((100 - 10) / 1000)
    assert second.start_flow_mm3_s == pytest.approx(10 * 0.1 * AREA)


def test_max_velocity_caps_the_feed_rate():
    (s,) = segments("G1 X100 F60000", PrinterLimits(max_velocity=200, max_accel=1000))
    assert s.speed_mm_s == pytest.approx(200.0)


def test_z_moves_follow_max_z_velocity():
    limits = PrinterLimits(max_velocity=300, max_accel=1000, max_z_velocity=5)
    (s,) = segments("G1 Z10 F6000", limits)
    assert s.speed_mm_s == pytest.approx(5.0)


def test_flow_is_speed_times_extrusion_per_mm_times_filament_area():
    (s,) = segments("M83\nG1 X100 E10 F6000")
    assert s.flow_mm3_s == pytest.approx(100 * 0.1 * AREA)
    assert s.start_flow_mm3_s == 0.0 and s.end_flow_mm3_s == 0.0
    assert s.filament_mm == pytest.approx(10.0)


def test_peak_flow_between_follows_the_trapezoid():
    (s,) = segments("M83\nG1 X100 E10 F6000")
    peak = s.flow_mm3_s
    assert s.peak_flow_between(0.0, 0.05) == pytest.approx(peak / 2)
    assert s.peak_flow_between(0.5, 0.6) == pytest.approx(peak)
    assert s.peak_flow_between(1.05, 2.0) == pytest.approx(peak / 2)
    assert s.peak_flow_between(2.0, 3.0) == 0.0


# --- G-code state ------------------------------------------------------------------

def test_absolute_and_relative_extrusion_give_the_same_flow():
    absolute = segments("M82\nG92 E0\nG1 X10 E1 F1200\nG1 X20 E2.5\nG92 E0\nG1 X30 E1")
    relative = segments("M83\nG1 X10 E1 F1200\nG1 X20 E1.5\nG1 X30 E1")
    assert [s.filament_mm for s in absolute] == pytest.approx([1, 1.5, 1])
    assert [s.flow_mm3_s for s in absolute] == \
        pytest.approx([s.flow_mm3_s for s in relative])


def test_g92_sets_the_extruder_position_without_moving():
    (s,) = segments("G92 E100\nG1 X10 E101 F1200")
    assert s.filament_mm == pytest.approx(1.0)


def test_relative_coordinates_move_from_where_the_head_is():
    segs = segments("G91\nG1 X10 F6000\nG1 X10\nG90\nG1 X10")
    assert [s.distance_mm for s in segs] == pytest.approx([10, 10, 10])


def test_m221_scales_extrusion_and_m220_scales_speed():
    plain, = segments("M83\nG1 X100 E10 F3000")
    fast, = segments("M83\nM220 S200\nM221 S50\nG1 X100 E10 F3000")
    assert fast.filament_mm == pytest.approx(5.0)
    assert fast.speed_mm_s == pytest.approx(2 * plain.speed_mm_s)
    assert fast.flow_mm3_s == pytest.approx(plain.flow_mm3_s)


def test_m221_keeps_the_absolute_e_position():
    # Klipper rebases E so that the next absolute E continues from the last
    (s,) = segments("G1 E5 F600\nM221 S50\nG1 X10 E7 F600")[1:]
    assert s.filament_mm == pytest.approx(1.0)


def test_a_retraction_and_its_unretract_carry_no_flow():
    segs = segments("M83\nG1 X10 E1 F1200\nG1 E-2 F2400\nG1 X50 F6000\n"
                    "G1 E2 F2400\nG1 X60 E1 F1200")
    assert [s.filament_mm for s in segs] == pytest.approx([1, 0, 0, 0, 1])
    assert [s.flow_mm3_s > 0 for s in segs] == [True, False, False, False, True]


def test_firmware_retraction_uses_the_configured_length_and_speed():
    # (max_extrude_only_accel high enough for 1 mm to reach 20 mm/s)
    limits = PrinterLimits(max_velocity=300, max_accel=1000, retract_length=1.0,
                           retract_speed=20.0, unretract_extra_length=0.5,
                           max_extrude_only_accel=10000)
    segs = segments("M82\nG1 X10 E1 F1200\nG10\nG10\nG1 X50 F6000\nG11\n"
                    "G1 X60 E2 F1200", limits)
    extruded = [round(s.filament_mm, 6) for s in segs]
    # one retraction (a second G10 does nothing), the unretract refills 1 mm
    # and primes 0.5 mm, and the G-code E position is unchanged by both
    assert extruded == [1.0, 0.0, 0.0, 0.5, 1.0]
    retract = segs[1]
    assert retract.distance_mm == pytest.approx(1.0)
    assert retract.speed_mm_s == pytest.approx(20.0)


def test_set_retraction_changes_the_length():
    segs = segments("SET_RETRACTION RETRACT_LENGTH=3 RETRACT_SPEED=30\nG10\nG11")
    assert [s.distance_mm for s in segs] == pytest.approx([3.0, 3.0])


def test_an_arc_is_split_into_segments_of_the_arc_resolution():
    # a half circle of radius 10 (31.4 mm): 31 segments of about 1 mm
    segs = segments("M83\nG1 X0 Y0 F1200\nG2 X20 Y0 I10 J0 E3.1")
    arc = segs[1:] if segs[0].distance_mm == 0 else segs
    assert len(arc) == 31
    assert sum(s.distance_mm for s in arc) == pytest.approx(10 * math.pi, rel=1e-3)
    assert sum(s.filament_mm for s in arc) == pytest.approx(3.1)
    assert len({s.offset for s in arc}) == 1


def test_an_absolute_e_arc_extrudes_the_difference():
    segs = segments("G92 E10\nG3 X0 Y20 I0 J10 E12 F600")
    assert sum(s.filament_mm for s in segs) == pytest.approx(2.0)


def test_set_velocity_limit_and_m204_change_later_moves():
    limited, = segments("SET_VELOCITY_LIMIT VELOCITY=50\nG1 X100 F6000")
    assert limited.speed_mm_s == pytest.approx(50.0)
    slow, = segments("M204 S500\nG1 X100 F6000")
    assert slow.accel_s == pytest.approx(0.2)
    slow, = segments("SET_VELOCITY_LIMIT ACCEL=500\nG1 X100 F6000")
    assert slow.accel_s == pytest.approx(0.2)


def test_m204_takes_the_lower_of_p_and_t_and_square_corner_velocity_can_change():
    slow, = segments("M204 P800 T500\nG1 X100 F6000")
    assert slow.accel_s == pytest.approx(0.2)
    first, _ = segments("SET_VELOCITY_LIMIT SQUARE_CORNER_VELOCITY=10\n"
                        "G1 X100 F6000\nG1 X100 Y100")
    assert first.decel_s == pytest.approx((100 - 10) / 1000)


def test_an_arc_in_the_xz_plane_moves_z():
    segs = segments("G1 X0 Z0 F600\nG18\nG2 X20 Z0 I10 K0",
                    PrinterLimits(max_velocity=300, max_accel=1000, max_z_velocity=50))
    arc = [s for s in segs if s.offset > 0]
    assert len(arc) == 31
    assert sum(s.distance_mm for s in arc) == pytest.approx(10 * math.pi, rel=1e-3)


def test_m400_drains_the_queue_and_restarts_a_quarter_second_later():
    a, b = segments("G1 X10 F6000\nM400\nG1 X20")
    assert a.decel_s > 0
    assert b.start_s == pytest.approx(a.start_s + a.duration_s + 0.25)


def test_comments_and_unknown_commands_are_ignored():
    segs = segments("; G1 X1000\nG1 X10 F6000 ; G1 X500\nM106 S255\nFOO_BAR X=1\n"
                    "g1 x20\nN10 G1 X30*55\nG1X40Y0")
    assert [s.distance_mm for s in segs] == pytest.approx([10, 10, 10, 10])


def test_numbers_are_read_as_klipper_splits_them():
    # klippy/gcode.py splits on letters: "X10E0.5" is X10 E0.5, and "E1e1"
    # is E1 then E1 (the last one counts), never 1e1 = 10
    segs = segments("M83\nG1 X10E0.5 F600\nG1 X20 E1e1")
    assert [s.filament_mm for s in segs] == pytest.approx([0.5, 1.0])


def test_a_dwell_adds_its_time_and_a_wait_is_a_barrier():
    events = plan_text("G1 X10 F6000\nG4 P500\nG1 X20\nM109 S200\nG1 X30", LIMITS)
    a, b, barrier, c = events
    assert b.start_s == pytest.approx(a.start_s + a.duration_s + 0.5)
    assert isinstance(barrier, Barrier) and barrier.command == "M109"
    assert barrier.time_s == pytest.approx(b.start_s + b.duration_s)
    assert c.start_s == pytest.approx(barrier.time_s)


def test_segments_carry_the_offset_of_their_line():
    text = "G1 X10 F6000\n; comment\nG1 X10 Y10\n"
    a, b = segments(text)
    assert (a.offset, b.offset) == (0, text.index("G1 X10 Y10"))


# --- bad input: one line ------------------------------------------------------------

@pytest.mark.parametrize("text, message", [
    ("G1 X10 F0", "line 1: invalid speed: 'G1 X10 F0'"),
    ("G1 X10\nG1 X100000000000", "line 2: absurd value X100000000000"),
    ("G1 X1.2.3", "line 1: unable to parse X"),
    ("G92 E-", "line 1: unable to parse E"),
    ("G2 X10 Y0 R5", "does not support R moves"),
    ("G91\nG2 X10 Y0 I5", "relative move mode"),
    ("G20", "inches"),
    ("M83\nG1 X1 E5 F600", "line 2: move exceeds maximum extrusion (12.026 mm^2 vs"
                          " 0.640 mm^2, max_extrude_cross_section): 'G1 X1 E5 F600'"),
    ("M83\nG1 E60 F600", "max_extrude_only_distance): 'G1 E60 F600'"),
    ("M220 S0", "S must be above 0"),
])
def test_bad_input_is_one_line_naming_the_line(text, message):
    with pytest.raises(FlowloopError) as exc:
        plan_text(text, LIMITS)
    assert message in str(exc.value)
    assert "\n" not in str(exc.value)


def test_binary_data_is_refused():
    import io
    with pytest.raises(FlowloopError, match="line 2: binary data"):
        list(plan_file(io.BytesIO(b"G1 X1\n\x00\x01\x02G1\n")))
    with pytest.raises(FlowloopError, match="line 1: not G-code text"):
        list(plan_file(io.BytesIO(b"G1 X\xff\n")))


def test_limits_refuse_nonsense():
    with pytest.raises(FlowloopError, match="max_accel must be above 0"):
        PrinterLimits(max_accel=0)
    with pytest.raises(FlowloopError, match="minimum_cruise_ratio must be below 1"):
        PrinterLimits(minimum_cruise_ratio=1.0)


def test_limits_come_from_printer_cfg_with_klipper_defaults():
    config = parse_config("[printer]\nkinematics: cartesian\nmax_velocity: 250\n"
                          "max_accel: 4000\n[extruder]\nnozzle_diameter: 0.6\n"
                          "[firmware_retraction]\nretract_length: 0.8\n")
    limits = limits_from_config(config)
    assert (limits.max_velocity, limits.max_accel) == (250, 4000)
    assert limits.retract_length == 0.8
    assert limits.derived("max_extrude_cross_section") == pytest.approx(4 * 0.36)
    assert limits.derived("max_z_velocity") == 250
    bad = parse_config("[printer]\nmax_velocity: 250\nmax_accel: -1\n")
    with pytest.raises(FlowloopError, match="Option 'max_accel' in section 'printer'"):
        limits_from_config(bad)


# --- a real slicer file --------------------------------------------------------------

def slicer_e_total(path: Path) -> float:
    """Filament the file extrudes, counted the simple way (absolute E, G92 E)."""
    total = last = 0.0
    for line in path.read_text().splitlines():
        code = line.split(";")[0].split()
        if code[:1] == ["G92"]:
            last = float(code[1][1:])
        elif code[:1] == ["G1"]:
            for word in code[1:]:
                if word[0] == "E":
                    e = float(word[1:])
                    total += e - last
                    last = e
    return total


@pytest.mark.parametrize("name", ["block_layers_1_2.gcode", "box_bridge_layer.gcode"])
def test_a_real_file_extrudes_what_the_slicer_wrote(name):
    path = DATA / name
    planner = Planner()
    events = []
    with open(path, "rb") as f:
        offset = 0
        for number, raw in enumerate(f, 1):
            events += planner.line(raw, offset, number)
            offset += len(raw)
    events += planner.finish()
    segs = [e for e in events if isinstance(e, Segment)]
    extruded = sum(s.filament_mm for s in segs)
    assert extruded > 200
    # what is still retracted at the end is owed, not lost
    assert extruded - planner.retracted_mm == pytest.approx(slicer_e_total(path))
    for a, b in zip(segs, segs[1:]):
        assert b.start_s >= a.start_s + a.duration_s - 1e-9
    assert 0 < max(s.flow_mm3_s for s in segs) < 20


# --- invariants -----------------------------------------------------------------------

coordinate = st.floats(min_value=-100, max_value=100, allow_nan=False)
moves = st.lists(st.tuples(coordinate, coordinate,
                           st.floats(min_value=-0.5, max_value=0.5),   # E per move
                           st.sampled_from([600, 1800, 6000, 30000])),  # F
                 min_size=1, max_size=40)


def relative_file(move_list) -> str:
    lines = ["M83"]
    for x, y, e, f in move_list:
        lines.append(f"G1 X{x:.3f} Y{y:.3f} E{e:.4f} F{f}")
    return "\n".join(lines)


@settings(max_examples=60, deadline=None)
@given(moves)
def test_invariants_of_any_plan(move_list):
    limits = PrinterLimits(max_velocity=200, max_accel=2000,
                           max_extrude_cross_section=100.0,
                           max_extrude_only_velocity=1000.0)
    planner = Planner(limits)
    events = []
    feed_at = {}                     # line offset -> requested speed (mm/s)
    text = relative_file(move_list)
    offset = 0
    for number, line in enumerate(text.encode().splitlines(keepends=True), 1):
        feed_at[offset] = float(line.split(b"F")[-1]) / 60 if b"F" in line else None
        events += planner.line(line, offset, number)
        offset += len(line)
    events += planner.finish()
    segs = [e for e in events if isinstance(e, Segment)]
    # E is neither lost nor invented: extruded minus still retracted = commanded
    commanded = sum(round(e, 4) for _x, _y, e, _f in move_list)
    extruded = sum(s.filament_mm for s in segs)
    assert extruded - planner.retracted_mm == pytest.approx(commanded, abs=1e-6)
    t = 0.0
    for s in segs:
        assert s.start_s == pytest.approx(t, abs=1e-9)
        t = s.start_s + s.duration_s
        # never faster than the line asked, nor than max_velocity
        assert s.duration_s >= s.distance_mm / feed_at[s.offset] - 1e-9
        assert s.speed_mm_s <= feed_at[s.offset] + 1e-6
        assert s.accel_s >= 0 and s.decel_s >= 0 and s.duration_s > 0
        assert min(s.flow_mm3_s, s.start_flow_mm3_s, s.end_flow_mm3_s) >= 0
        assert s.flow_mm3_s >= max(s.start_flow_mm3_s, s.end_flow_mm3_s) - 1e-9
        if s.filament_mm > 0:
            assert s.flow_mm3_s > 0



@pytest.mark.parametrize("plan", [plan_file, bulk_planner.plan_file])
def test_a_byte_order_mark_before_the_first_line_is_planned_past(plan):
    text = b"G28\nM83\nG1 X10 E1 F600\nG1 X20 E1\n"
    plain = list(plan(io.BytesIO(text)))
    marked = list(plan(io.BytesIO(codecs.BOM_UTF8 + text)))
    # the same events, each line's place 3 bytes further into the file
    assert marked == [e._replace(offset=e.offset + 3) for e in plain]
    assert any(isinstance(e, Segment) for e in marked)
