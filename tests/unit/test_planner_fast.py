"""The bulk planner (bulk_planner) against the reference planner, which
test_planner_klipper checks against Klipper's own toolhead code: the same
events, bit for bit, from any file and at any chunk size."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flowloop.errors import FlowloopError
from flowloop.gcode import bulk_planner, reference_planner
from flowloop.gcode.reference_planner import PrinterLimits
from tests.samples import arc_fitted

pytestmark = pytest.mark.unit

DATA = Path(__file__).resolve().parents[1] / "data" / "gcode"
LIMITS = PrinterLimits(max_velocity=300, max_accel=3000, retract_length=1.0,
                       max_extrude_cross_section=50.0)


def reference(data: bytes, limits: PrinterLimits = LIMITS):
    return list(reference_planner.plan_file(io.BytesIO(data), limits))


def fast(data: bytes, limits: PrinterLimits = LIMITS, chunk_bytes=1 << 20):
    return list(bulk_planner.plan_file(io.BytesIO(data), limits, chunk_bytes))


def assert_same(data: bytes, limits: PrinterLimits = LIMITS, chunk_bytes=1 << 20):
    ours, theirs = fast(data, limits, chunk_bytes), reference(data, limits)
    assert len(ours) == len(theirs)
    for i, (a, b) in enumerate(zip(ours, theirs)):
        assert type(a) is type(b), f"event {i}"
        assert tuple(a) == tuple(b), f"event {i}"     # exactly, not approx


@pytest.mark.parametrize("name", ["block_layers_1_2.gcode", "box_bridge_layer.gcode"])
@pytest.mark.parametrize("chunk_bytes", [1 << 20, 4096, 97])
def test_a_real_file_gives_the_reference_plan_at_any_chunk_size(name, chunk_bytes):
    data = (DATA / name).read_bytes()
    assert_same(data, PrinterLimits(), chunk_bytes)


def with_firmware_retraction(data: bytes) -> bytes:
    """A G10 before and a G11 after every travel that follows an extrusion."""
    out, extruded = [], False
    for line in data.split(b"\n"):
        move = line.startswith(b"G1 ") and b"X" in line
        if move and b" E" not in line and extruded:
            out += [b"G10", line, b"G11 ; unretract"]
            extruded = False
            continue
        out.append(line)
        if move:
            extruded = b" E" in line
    return b"\n".join(out)


@pytest.mark.parametrize("chunk_bytes", [1 << 20, 500])
def test_firmware_retraction_gives_the_reference_plan(chunk_bytes):
    data = with_firmware_retraction((DATA / "block_layers_1_2.gcode").read_bytes()
                                    + (DATA / "box_bridge_layer.gcode").read_bytes())
    assert data.count(b"\nG10\n") >= 5
    limits = PrinterLimits(retract_length=0.8, retract_speed=35,
                           unretract_extra_length=0.05, unretract_speed=30)
    assert_same(data, limits, chunk_bytes)
    assert_same(b"M83\n" + data.replace(b"G92 E0", b"G92 E5"), limits, chunk_bytes)


def test_the_lines_it_reads_in_bulk_and_the_ones_it_hands_over():
    text = ("; header\n\nM82\nG90\nG1 Z0.2 F7800\nG1 X10 Y10 E1.5 F1800\n"
            "G0 F9000 X20 Y5\nG1 E-2 F2400\nG92 E0\nG1 E2\nM106 S255\n"
            "M73 P5 R10\nG1 X30 Y30 E1 ; a comment\nG1 X30.0 Y30 E1\n"
            "G1 X40 Y30 E+2.5 F.5e3\ng1 x50\nG1\tX60 E3\nG1 X70 E4 X71\n"
            "M83\nG1 X80 E0.5\nG91\nG1 X1 Y1 E0.1\nG90\nG10\nG1 X90 Y40\nG11\n"
            "G2 X100 Y50 I5 J5 E1\nM221 S90\nG1 X110 Y50 E1\nM220 S50\n"
            "G1 X120 Y50 E1\nG4 P100\nG1 X125\nM400\nG1 X130 E0.4\nM109 S200\n"
            "G1 X10 Y10 E1 F3000\r\nG1 X15 Y10 E0.2\r\n"
            "SET_VELOCITY_LIMIT ACCEL=1000\nG1 X20 Y20 E1\nG92 X0 Y0\n"
            "G1 X5 Y5 E0.5\nG28\nG1 X1 Y1 E1\n"
            # found by fuzzing: a G92 without axes sets them all; Klipper
            # reads "G10 0" as a command of its own (ignored)
            "G1 X7 Y7 E3\nG92 \nG1 X9 E1\nG92 ; all\nG1 X2 E2\n"
            "G10 0\nG1 X3\nG10 ; retract\nG1 X4\nG11\r\nG1 X5 E3\n")
    assert_same(text.encode())
    assert_same(text.encode(), chunk_bytes=13)


def test_bad_input_fails_with_the_reference_message():
    for text in ("G1 X10 F0", "G1 X10\nG1 X100000000000", "G1 X1.2.3",
                 "G92 E-", "M83\nG1 X1 E5 F600", "M83\nG1 E60 F600",
                 "G1 X1\n\x00\x01G1\n", "G1 X\xff\n"):
        data = text.encode("latin-1")
        with pytest.raises(FlowloopError) as ours:
            fast(data, PrinterLimits())
        with pytest.raises(FlowloopError) as theirs:
            reference(data, PrinterLimits())
        assert str(ours.value) == str(theirs.value)


def test_min_plus_is_the_sequential_recurrence():
    rng = np.random.default_rng(1)
    for _ in range(50):
        n = int(rng.integers(1, 300))
        a = rng.choice([0.0, 25.0, 1e4, 999999999.9], n) * rng.random(n)
        add = rng.random(n) * rng.choice([1.0, 3000.0, 1e6], n)
        x0 = float(rng.random() * 100)
        x, out = x0, []
        for ai, di in zip(a.tolist(), add.tolist()):
            x = min(ai, x + di)
            out.append(x)
        assert bulk_planner.min_plus(a, add, x0).tolist() == out


number = st.floats(min_value=-120, max_value=120, allow_nan=False).map(
    lambda v: f"{v:.3f}".rstrip("0").rstrip("."))
word = st.tuples(st.sampled_from("XYZEF"), number).map(
    lambda w: w[0] + (w[1].lstrip("-") if w[0] == "F" else w[1]))
line = st.one_of(
    st.lists(word, min_size=0, max_size=5).map(lambda ws: " ".join(["G1"] + ws)),
    st.lists(word, min_size=1, max_size=3).map(lambda ws: " ".join(["G0"] + ws)),
    st.sampled_from(["G92 E0", "G92 E1.5", "G92 X0 Y0", "M82", "M83", "G90",
                     "G91", "G10", "G11", "M106 S255", "; comment", "",
                     "M221 S95", "M220 S110", "G4 P50", "M400", "G1 E-1 F2400",
                     "G1 E1", "G1 Z0.4", "G1 F600", "G2 X10 Y10 I5 J0",
                     "M109 S210", "G1 X1 ; c", "SET_VELOCITY_LIMIT ACCEL=500"]))


# arcs (gcode_arcs): mostly an end and a centre in the plane, now and then
# none, an R (refused) or a helical Z; extruding or not, a feed or not
coordinate = st.floats(-60, 60).map(lambda v: f"{v:.3f}".rstrip("0").rstrip("."))
arc_line = st.tuples(
    st.sampled_from(["G2", "G3"]),
    st.sampled_from(["X{} Y{}", "X{} Y{}", "X{} Y{}", "X{}", "X{} Y{} Z{}", ""]),
    st.lists(coordinate, min_size=3, max_size=3),
    st.sampled_from(["I{} J{}", "I{} J{}", "I{} J{}", "I{}", "J{}", "", "R{}"]),
    st.lists(st.floats(-20, 20).map(lambda v: f"{v:.3f}"), min_size=2, max_size=2),
    st.one_of(st.none(), st.floats(0, 5).map(lambda v: f"{v:.4f}")),
    st.one_of(st.none(), st.integers(60, 9000))).map(
    lambda a: " ".join(w for w in (a[0], a[1].format(*a[2]), a[3].format(*a[4]),
                                   f"E{a[5]}" if a[5] is not None else "",
                                   f"F{a[6]}" if a[6] is not None else "") if w))
simple_move = st.lists(st.tuples(st.sampled_from("XYE"), coordinate),
                       min_size=1, max_size=3).map(
    lambda ws: "G1 " + " ".join(k + v for k, v in ws))
arc_file_line = st.one_of(
    arc_line, arc_line, arc_line, simple_move, simple_move,
    st.sampled_from(["G17", "G18", "G19", "M82", "M83", "M83", "G92 E0",
                     "G92 Z1", "M221 S90", "G10", "G11", "G1 F1200", "G91",
                     "G90", "; a comment", "M106 S128"]))


def same_plan_or_error(data: bytes, limits: PrinterLimits, chunk: int) -> None:
    """The reference's events bit for bit, or its error word for word."""
    try:
        expected = reference(data, limits)
    except FlowloopError as e:
        with pytest.raises(FlowloopError) as ours:
            fast(data, limits, chunk)
        assert str(ours.value) == str(e)
        return
    ours = fast(data, limits, chunk)
    assert [tuple(e) for e in ours] == [tuple(e) for e in expected]


@settings(max_examples=150, deadline=None)
@given(st.lists(arc_file_line, min_size=1, max_size=40), st.integers(1, 400))
def test_a_file_of_arcs_gives_the_reference_plan_at_any_chunk_size(lines, chunk):
    limits = PrinterLimits(max_velocity=300, max_accel=3000, retract_length=1.0,
                           max_extrude_cross_section=1e6,
                           max_extrude_only_distance=1e4)
    data = ("G90\n" + "\n".join(lines) + "\n").encode()
    same_plan_or_error(data, limits, chunk)


@pytest.mark.parametrize("absolute_e", [False, True])
@pytest.mark.parametrize("chunk_bytes", [1 << 20, 4096, 97])
def test_an_arc_fitted_file_gives_the_reference_plan(absolute_e, chunk_bytes):
    assert_same(arc_fitted(6, absolute_e), chunk_bytes=chunk_bytes)


def test_arcs_are_read_in_bulk():
    """Relative E, and absolute E reset each layer (G92 E0): every arc of
    the file is expanded in bulk, none goes through the reference line by
    line; with firmware retraction in the run they do."""
    through_reference = []

    class Counting(bulk_planner.BulkPlanner):
        def _scalar_line(self, data, starts, ends, i, offset, first_line):
            through_reference.append(bytes(data[starts[i]:ends[i]]))
            super()._scalar_line(data, starts, ends, i, offset, first_line)

    for absolute_e, retraction in ((False, False), (True, False), (False, True)):
        through_reference.clear()
        data = arc_fitted(6, absolute_e)
        if retraction:
            data = data.replace(b"F9000\n", b"F9000\nG10\nG11\n")
        planner = Counting(LIMITS)
        events = planner.chunk(data, 0) + planner.finish()
        arcs = [line for line in through_reference if line[:2] in (b"G2", b"G3")]
        assert len(arcs) == (6 * 3 * 4 if retraction else 0)
        planned = [r for e in events if isinstance(e, bulk_planner.Segments)
                   for r in e.records()]
        assert planned == [e for e in reference(data, LIMITS)
                           if isinstance(e, reference_planner.Segment)]


@settings(max_examples=150, deadline=None)
@given(st.lists(line, min_size=1, max_size=60), st.integers(1, 400),
       st.sampled_from([0.0, 0.5, 0.9]))
def test_any_file_gives_the_reference_plan_at_any_chunk_size(lines, chunk, mcr):
    limits = PrinterLimits(max_velocity=300, max_accel=3000, minimum_cruise_ratio=mcr,
                           retract_length=1.0, max_extrude_cross_section=1e6,
                           max_extrude_only_distance=1e4)
    data = ("G90\n" + "\n".join(lines) + "\n").encode()
    same_plan_or_error(data, limits, chunk)
