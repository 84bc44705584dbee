"""devtools.demo_flowrate_limiter.cut_as_on_a_printer: the benches feed batch
mode the pieces the limiter queues a long move in on a printer. The pieces
must end where the G-code's moves end, with the same filament, and none may
take longer than a piece."""

from __future__ import annotations

import math

import pytest

from devtools.demo_flowrate_limiter import GCODE, cut_as_on_a_printer
from flowloop.control.caps import CUT_FROM_S, PIECE_S


def _ends(lines, relative_e):
    """(x, y, e) after each G1 line, and each extruding G1's duration at its
    F (0 for travel and retraction)."""
    x = y = e = 0.0
    feed, out = 1500.0, []
    for line in lines:
        words = line.split(";", 1)[0].split()
        if not words or words[0] != "G1":
            if words[:1] == ["G92"]:
                e = 0.0
            continue
        a = {w[0]: float(w[1:]) for w in words[1:]}
        feed = a.get("F", feed)
        nx, ny = a.get("X", x), a.get("Y", y)
        ne = e + a["E"] if relative_e and "E" in a else a.get("E", e)
        out.append(((nx, ny, ne), math.hypot(nx - x, ny - y) / (feed / 60)
                    if ne > e else 0.0))
        x, y, e = nx, ny, ne
    return out


@pytest.mark.parametrize("relative_e", [False, True])
def test_a_long_line_is_cut_into_pieces_that_end_where_it_ends(relative_e):
    # 3 s at 40 mm/s, then a 0.5 s line and a retraction (kept whole)
    lines = ["G28", "M83" if relative_e else "M82", "G92 E0",
             "G1 X10 Y10 F6000",
             "G1 X130 Y10 E8.7 F2400" if relative_e else "G1 X130 Y10 E8.7 F2400",
             "G1 X150 Y10 E1.45" if relative_e else "G1 X150 Y10 E10.15",
             "G1 E-0.8 F2100" if relative_e else "G1 E9.35 F2100"]
    cut = cut_as_on_a_printer(lines)
    ends = _ends(cut, relative_e)
    # the travel, six pieces of 0.5 s, the short line, the retraction
    assert len(ends) == 1 + 6 + 1 + 1
    pieces = ends[1:7]
    assert all(d == pytest.approx(PIECE_S) for _, d in pieces)
    assert pieces[-1][0] == pytest.approx((130, 10, 8.7), abs=1e-4)
    assert ends[-2][0] == pytest.approx((150, 10, 10.15), abs=1e-4)
    assert ends[-1][0][2] == pytest.approx(9.35, abs=1e-4)


def test_the_bench_print_keeps_its_path_and_filament_and_no_piece_is_long():
    lines = GCODE.read_text().splitlines()
    whole, cut = _ends(lines, False), _ends(cut_as_on_a_printer(lines), False)
    assert len(cut) > len(whole)
    assert cut[-1][0] == pytest.approx(whole[-1][0], abs=1e-4)
    # every long extruding move was cut: none is left longer than klippy's
    # buffer, and the pieces are no longer than a piece (at their F)
    assert max(d for _, d in whole) > CUT_FROM_S
    assert max(d for _, d in cut) <= max(CUT_FROM_S, PIECE_S) + 1e-6


def test_an_arc_is_refused_not_passed_through_uncut():
    with pytest.raises(ValueError, match="G0/G1 in G90 only"):
        cut_as_on_a_printer(["G2 X10 Y10 I5 J0 E1"])


def test_the_speed_factor_counts_as_klippy_hands_the_speed_over():
    # M220 S200: the 3 s line runs 1.5 s, in three pieces
    lines = ["M83", "G1 X10 Y10 F6000", "M220 S200", "G1 X130 Y10 E8.7 F2400"]
    assert len(cut_as_on_a_printer(lines)) == 3 + 3
