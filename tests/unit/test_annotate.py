"""Autotemp annotations: where they go, what they say, and that the file
comes out whole, once."""

from __future__ import annotations

import codecs
import io
import itertools
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import List, NamedTuple

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flowloop import cli
from flowloop.errors import FlowloopError
from flowloop.gcode import ahead as ahead_module
from flowloop.gcode.annotate import (
    MARKER_REGEX,
    READAHEAD_S,
    AnnotateSettings,
    annotate_file,
    annotate_stream,
    is_annotated,
)
from flowloop.gcode.bulk_planner import plan_batches
from flowloop.gcode.melt import CELL_S, MELT_TIME_S
from flowloop.gcode.reference_planner import Barrier, Segment, plan_file
from tests.samples import WEAK_PROFILE

pytestmark = pytest.mark.unit

DEFAULT = AnnotateSettings()
DATA = Path(__file__).resolve().parents[1] / "data" / "gcode"
REAL = DATA / "block_layers_1_2.gcode"
COMMAND = re.compile(rb"^AUTOTEMP_FLOW FLOW=(\S+) LEAD=(\S+) DURATION=(\S+)\r?$",
                     re.MULTILINE)
# LEAD is rounded down and DURATION up to 0.01 s
ROUNDING_S = 0.011


class Announced(NamedTuple):
    at_s: float          # print time of the move after the command
    start_s: float
    end_s: float
    flow: float


def plan(data: bytes):
    return list(plan_file(io.BytesIO(data)))


def announcements(data: bytes) -> List[Announced]:
    """Every AUTOTEMP_FLOW of an annotated file, on the file's own timeline.

    A command's place is the line it stands before (commands stacked at one
    place share it): the start of the file after the marker (print time 0),
    the line after a barrier (the barrier's time) or a move (its start)."""
    events = plan(data)
    segs = [e for e in events if isinstance(e, Segment)]
    after_barrier = {e.offset: e.time_s for e in events if isinstance(e, Barrier)}
    after_marker = data.index(b"\n") + 1
    out, place, previous_end = [], None, None
    for m in COMMAND.finditer(data):
        if m.start() != previous_end:
            place = m.start()
        previous_end = data.index(b"\n", m.end()) + 1
        if place == after_marker:
            at = 0.0
        elif place in after_barrier:
            at = after_barrier[place]
        else:
            at = next(s.start_s for s in segs if s.offset > place)
        flow, lead, duration = (float(g) for g in m.groups())
        out.append(Announced(at, at + lead, at + lead + duration, flow))
    return out


def peak_between(segs, t0: float, t1: float) -> float:
    return max((s.peak_flow_between(t0, t1) for s in segs
                if s.start_s < t1 and s.start_s + s.duration_s > t0), default=0.0)


def flow_at(seg, t: float) -> float:
    """A move's flow at print time t (its trapezoid)."""
    u = t - seg.start_s
    if u < 0.0 or u > seg.duration_s:
        return 0.0
    if u < seg.accel_s:
        return seg.start_flow_mm3_s + (
            seg.flow_mm3_s - seg.start_flow_mm3_s) * u / seg.accel_s
    left = seg.duration_s - u
    if left < seg.decel_s:
        return seg.end_flow_mm3_s + (
            seg.flow_mm3_s - seg.end_flow_mm3_s) * left / seg.decel_s
    return seg.flow_mm3_s


def melt_peak_between(events, t0: float, t1: float, step: float = 0.0005) -> float:
    """The highest mean flow over MELT_TIME_S centred anywhere in [t0, t1],
    integrated here on a fine grid (not melt.py's way); no flow is counted
    across a barrier."""
    segs = [e for e in events if isinstance(e, Segment)]
    cuts = [e.time_s for e in events if isinstance(e, Barrier)]
    h = MELT_TIME_S / 2
    times = [t0 - h + i * step for i in range(int((t1 - t0 + 2 * h) / step) + 2)]
    near = [s for s in segs if s.start_s < t1 + h and s.start_s + s.duration_s > t0 - h]
    # the moves follow one another (each ends no earlier than the one
    # before), so the ones a time falls in are found walking both in order
    ends = [s.start_s + s.duration_s for s in near]
    assert ends == sorted(ends)
    flows, first = [], 0
    for t in times:
        while first < len(near) and ends[first] < t:
            first += 1          # over before t: flow_at would give 0
        flow, k = 0.0, first
        while k < len(near) and near[k].start_s <= t:
            flow = max(flow, flow_at(near[k], t))
            k += 1
        flows.append(flow)
    # sum(flows[i:i + n]) as a difference of running sums (one pass, not
    # one sum per centre)
    total = [0.0, *itertools.accumulate(flows)]
    best = 0.0
    n = int(round(2 * h / step))
    for i in range(len(times) - n):
        centre = times[i] + h
        if not t0 <= centre <= t1:
            continue
        if any(times[i] < c < times[i + n] for c in cuts):
            continue      # the mean across a wait is not the melt's
        best = max(best, (total[i + n] - total[i]) * step / (2 * h))
    return best


def annotated(data: bytes, settings=DEFAULT) -> bytes:
    out = io.BytesIO()
    annotate_stream(plan(data), io.BytesIO(data), out, settings)
    return out.getvalue()


def assert_announcements_cover_the_flow(original: bytes, result: bytes,
                                        settings=DEFAULT) -> None:
    """The one check of what annotations promise: windows tile the print from
    the first flow on, each FLOW is its window's peak of the flow to melt
    (the mean over MELT_TIME_S: at least it, to the cell's sampling, and never
    above the moves' own peak; rounded up to 0.1), and each comes at least
    lead - read-ahead early unless a barrier (or the file's start) was
    closer."""
    events = plan(original)
    segs = [e for e in events if isinstance(e, Segment)]
    barriers = [e.time_s for e in events if isinstance(e, Barrier)]
    # the annotations change nothing in the motion
    assert [(s.start_s, s.duration_s, s.flow_mm3_s) for s in plan(result)
            if isinstance(s, Segment)] == [(s.start_s, s.duration_s, s.flow_mm3_s)
                                           for s in segs]
    windows = announcements(result)
    flowing = [s for s in segs if s.filament_mm > 0]
    if not flowing:
        assert windows == []
        return
    assert windows[0].start_s <= flowing[0].start_s + 1e-9
    assert windows[-1].end_s >= segs[-1].start_s + segs[-1].duration_s - 1e-6
    for a, b in zip(windows, windows[1:]):
        if not any(a.end_s - ROUNDING_S <= t <= b.start_s + ROUNDING_S
                   for t in barriers):
            assert b.start_s == pytest.approx(a.end_s, abs=2 * ROUNDING_S)
    for w in windows:
        assert w.end_s - w.start_s > 0
        inner = melt_peak_between(events, w.start_s + ROUNDING_S,
                                  w.end_s - ROUNDING_S)
        outer = peak_between(segs, w.start_s - ROUNDING_S - MELT_TIME_S / 2,
                             w.end_s + ROUNDING_S + MELT_TIME_S / 2)
        # between two cell ends the mean moves by at most CELL_S / MELT_TIME_S
        assert inner <= w.flow + outer * CELL_S / MELT_TIME_S + 1e-9
        assert w.flow <= outer + 0.1 + 1e-9
        lead = w.start_s - w.at_s
        first_possible = max([t for t in barriers if t <= w.start_s], default=0.0)
        if w.start_s - settings.placement_s >= first_possible:
            assert lead >= settings.placement_s - ROUNDING_S


# --- the file and its marker --------------------------------------------------------

@pytest.mark.parametrize("name", ["block_layers_1_2.gcode", "box_bridge_layer.gcode"])
def test_a_real_file_gets_windows_that_cover_its_flow(name):
    data = (DATA / name).read_bytes()
    result = annotated(data)
    assert len(COMMAND.findall(result)) > 5
    assert_announcements_cover_the_flow(data, result)


def test_a_flow_step_is_announced_lead_ahead():
    # 40 s slow, then 20 s at four times the flow: the fast part is announced
    # lead - read-ahead before it starts, in the middle of the slow part
    slow = [f"G1 X{10 * (i % 2) + 10:.0f} Y{i:.0f} E0.05 F600" for i in range(1, 41)]
    fast = [f"G1 X{100 * (i % 2) + 10:.0f} Y{40 + i * 0.1:.1f} E3 F6000"
            for i in range(1, 21)]
    data = "\n".join(["M83", "G1 X10 Y0 F6000"] + slow + fast).encode() + b"\n"
    settings = AnnotateSettings(lead_s=15.0)     # shorter than the slow part
    result = annotated(data, settings)
    assert_announcements_cover_the_flow(data, result, settings)
    segs = [e for e in plan(data) if isinstance(e, Segment)]
    fast_start = next(s.start_s for s in segs if s.flow_mm3_s > 5)
    step = next(w for w in announcements(result) if w.flow > 5)
    assert step.start_s <= fast_start
    assert step.start_s - step.at_s >= settings.placement_s - ROUNDING_S
    assert step.at_s > 10.0        # in the slow part, not at the file's start


def test_nothing_is_announced_across_a_barrier():
    lines = ["M83"] + [f"G1 X{10 * (i % 2)} Y{i} E0.1 F600" for i in range(30)]
    data = "\n".join(lines[:20] + ["M109 S220"] + lines[20:]).encode() + b"\n"
    result = annotated(data)
    barrier_at = result.index(b"M109 S220")
    after = [m.start() for m in COMMAND.finditer(result)]
    windows = announcements(result)
    barrier_s = next(e.time_s for e in plan(data) if isinstance(e, Barrier))
    for offset, w in zip(after, windows):
        if w.start_s > barrier_s + 1e-9:
            assert offset > barrier_at
    assert_announcements_cover_the_flow(data, result)


def test_a_dwell_after_a_barrier_announces_no_empty_window():
    moves = [f"G1 X{10 * (i % 2)} Y{i} E0.3 F1200" for i in range(20)]
    data = "\n".join(["M83"] + moves[:10] + ["M109 S210", "G4 P3000"]
                     + moves[10:]).encode() + b"\n"
    result = annotated(data)
    assert b"DURATION=0.00" not in result
    assert_announcements_cover_the_flow(data, result)


def test_a_longer_lead_places_annotations_earlier():
    data = REAL.read_bytes()
    short = announcements(annotated(data, AnnotateSettings(lead_s=5)))
    long = announcements(annotated(data, AnnotateSettings(lead_s=30)))
    median = sorted(w.start_s - w.at_s for w in short)[len(short) // 2]
    assert median >= 5 - READAHEAD_S - ROUNDING_S
    assert sorted(w.start_s - w.at_s for w in long)[len(long) // 2] > median + 15


def test_the_marker_is_found_as_moonraker_looks_for_it():
    result = annotated(REAL.read_bytes())
    head = result[:1024 * 1024].decode()
    match = re.search(MARKER_REGEX, head, re.MULTILINE)
    assert match is not None and match.group("version") == "v2"
    assert result.splitlines()[0].startswith(b"; flowloop autotemp annotations v2")
    assert result.splitlines()[-1].startswith(b"; flowloop autotemp summary:"
                                              b" peak_flow_mm3_s=")
    # the slicer's own header is still there for Moonraker's metadata
    assert b"; generated by PrusaSlicer" in result[:2000]


def test_a_file_without_extrusion_gets_only_marker_and_summary():
    result = annotated(b"G28\nG1 X10 F600\n")
    assert COMMAND.findall(result) == []
    assert result.count(b"\n") == 4


def test_crlf_files_keep_their_line_ends(tmp_path):
    path = tmp_path / "crlf.gcode"
    path.write_bytes(b"M83\r\n" + b"".join(
        f"G1 X{i % 2 * 10} Y{i} E0.2 F1200\r\n".encode() for i in range(40)))
    annotate_file(path)
    data = path.read_bytes()
    assert data.count(b"\n") == data.count(b"\r\n")


# --- idempotence and safe output ---------------------------------------------------

def test_annotating_twice_changes_nothing(tmp_path):
    path = tmp_path / "part.gcode"
    path.write_bytes(REAL.read_bytes())
    first = annotate_file(path)
    once = path.read_bytes()
    second = annotate_file(path)
    assert first.annotated and not second.annotated
    # the second run reports the file's own summary line
    assert (second.peak_flow_mm3_s, second.windows) == (
        first.peak_flow_mm3_s, first.windows)
    assert path.read_bytes() == once
    copy = tmp_path / "copy.gcode"
    assert not annotate_file(path, copy).annotated
    assert copy.read_bytes() == once


def test_in_place_and_output_file_give_the_same_bytes(tmp_path):
    inplace, src, out = tmp_path / "a.gcode", tmp_path / "b.gcode", tmp_path / "o.gcode"
    inplace.write_bytes(REAL.read_bytes())
    src.write_bytes(REAL.read_bytes())
    annotate_file(inplace)
    annotate_file(src, out)
    assert inplace.read_bytes() == out.read_bytes()
    assert src.read_bytes() == REAL.read_bytes()


def test_a_linked_file_is_annotated_where_the_link_points(tmp_path):
    target, link = tmp_path / "real.gcode", tmp_path / "link.gcode"
    target.write_bytes(REAL.read_bytes())
    link.symlink_to(target)
    annotate_file(link)
    assert link.is_symlink()
    assert target.read_bytes().startswith(b"; flowloop autotemp annotations v2")


def test_a_failure_leaves_input_and_output_as_they_were(tmp_path):
    src, out = tmp_path / "bad.gcode", tmp_path / "out.gcode"
    src.write_bytes(REAL.read_bytes() + b"G1 X10 F-5\n")
    out.write_bytes(b"earlier output\n")
    for dst in (out, None):
        with pytest.raises(FlowloopError, match=r"bad.gcode: line \d+: invalid speed"):
            annotate_file(src, dst)
    assert out.read_bytes() == b"earlier output\n"
    assert src.read_bytes().endswith(b"G1 X10 F-5\n")
    assert sorted(os.listdir(tmp_path)) == ["bad.gcode", "out.gcode"]


def test_settings_refuse_nonsense():
    with pytest.raises(FlowloopError, match="lead must be"):
        AnnotateSettings(lead_s=0.5)
    with pytest.raises(FlowloopError, match="window must be"):
        AnnotateSettings(lead_s=5, window_s=10)
    for melt_s in (0.1, 2.5, float("nan")):
        with pytest.raises(FlowloopError, match="melt window must be 0.25 to 2 s"):
            AnnotateSettings(melt_s=melt_s)


def test_the_melt_window_is_a_setting_and_the_marker_says_it(tmp_path, capsys):
    """--melt-window: the time the flow is averaged over (issue 40: the
    hotend's melt lag, docs/autotemp.md); a shorter one announces more of a
    burst, and the marker names it."""
    peaks = {}
    src = DATA / "curves_0.6mm_layers_1_8.gcode"    # short bursts of infill
    for melt in ("0.25", "0.5", "2"):
        out = tmp_path / f"m{melt}.gcode"
        assert cli.main(["annotate", str(src), "-o", str(out),
                         "--melt-window", melt]) == 0
        said = capsys.readouterr().out
        peaks[melt] = float(re.search(r"peak flow (\S+) mm", said).group(1))
        assert out.read_text().splitlines()[0].endswith(f", melt {melt} s")
    assert peaks == {"0.25": 25.9, "0.5": 21.2, "2": 19.9}
    assert cli.main(["annotate", str(REAL), "-o", str(tmp_path / "x.gcode"),
                     "--melt-window", "0.1"]) == 2
    assert capsys.readouterr().err == ("flowloop annotate: error: melt window must"
                                       " be 0.25 to 2 s, not 0.1\n")
    assert not (tmp_path / "x.gcode").exists()


def test_the_melt_window_is_the_printers_autotemp_setting(tmp_path, capsys):
    """[autotemp] melt_window in the printer.cfg the annotator is given
    (--printer-cfg; Moonraker's upload processor passes its
    annotate_printer_cfg) sets the window; --melt-window wins over it; on a
    toolchanger the shortest of the [autotemp NAME] sections' (a shorter
    window announces more of a burst)."""
    src = DATA / "curves_0.6mm_layers_1_8.gcode"    # short bursts of infill
    cfg = tmp_path / "printer.cfg"

    def annotated(text, *extra):
        cfg.write_text(text)
        out = tmp_path / "out.gcode"
        out.unlink(missing_ok=True)
        assert cli.main(["annotate", str(src), "-o", str(out), "--printer-cfg",
                         str(cfg), *extra]) == 0
        said = capsys.readouterr().out
        marker = out.read_text().splitlines()[0]
        return (float(re.search(r"peak flow (\S+) mm", said).group(1)),
                re.search(r"melt (\S+) s$", marker).group(1),
                re.search(r"melt window (\S+) s\)", said).group(1))
    assert annotated("[autotemp]\nmelt_window: 0.25\n") == (25.9, "0.25", "0.25")
    assert annotated("[autotemp]\ntime_constant: 4\n") == (21.2, "0.5", "0.5")
    assert annotated("[autotemp]\nmelt_window: 0.25\n",
                     "--melt-window", "0.5") == (21.2, "0.5", "0.5")
    assert annotated("[autotemp]\nmelt_window: 2\n[autotemp extruder1]\n"
                     "melt_window: 0.25\n[autotemp extruder2]\n") \
        == (25.9, "0.25", "0.25")


@pytest.mark.parametrize("value", ["0.1", "2.5", "nan", "inf", "half"])
def test_a_bad_melt_window_in_the_printer_cfg_names_the_option(tmp_path, capsys,
                                                               value):
    cfg = tmp_path / "printer.cfg"
    cfg.write_text(f"[autotemp extruder1]\nmelt_window: {value}\n")
    out = tmp_path / "out.gcode"
    assert cli.main(["annotate", str(REAL), "-o", str(out), "--printer-cfg",
                     str(cfg)]) == 2
    shown = repr(value) if value == "half" else value
    assert capsys.readouterr().err == (
        f"flowloop annotate: error: {cfg}: Section [autotemp extruder1], option"
        f" melt_window: must be 0.25 to 2 s, not {shown}\n")
    assert not out.exists()


# --- the command ------------------------------------------------------------------

def test_the_command_annotates_and_says_what_it_did(tmp_path, capsys):
    src, out = tmp_path / "in.gcode", tmp_path / "out.gcode"
    src.write_bytes(REAL.read_bytes())
    assert cli.main(["annotate", str(src), "-o", str(out), "--lead", "10"]) == 0
    said = capsys.readouterr().out
    assert re.match(r".*out.gcode: \d+ windows, peak flow \d+\.\d mm\^3/s, print time"
                    r" 0:0\d:\d\d \(lead 10 s, window 1 s, melt window 0.5 s\)\n$",
                    said)
    peak = re.search(r"peak flow (\S+) mm", said).group(1)
    assert cli.main(["annotate", str(out)]) == 0
    assert capsys.readouterr().out == (
        f"{out}: annotated already, peak flow {peak} mm^3/s, unchanged\n")


def test_the_command_reads_limits_from_printer_cfg(tmp_path, capsys):
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[printer]\nkinematics: cartesian\nmax_velocity: 20\n"
                   "max_accel: 500\n")
    src = tmp_path / "in.gcode"
    src.write_bytes(b"M83\nG1 X100 E5 F6000\n")
    assert cli.main(["annotate", str(src), "--printer-cfg", str(cfg)]) == 0
    # 100 mm at 20 mm/s: over 5 s, not the 0.4 s of the default limits
    assert "print time 0:00:05" in capsys.readouterr().out


@pytest.mark.parametrize("content, message", [
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00", "line 1: not G-code text"),
    (b"G28\nGCDE\x01\x00\x00\x00", "line 2: binary data"),
    (b"G1 X10 E99999999999 F600\n", "absurd value"),
    (b"G1 X10 F-100\n", "invalid speed"),
])
def test_bad_input_is_one_line_and_no_output(tmp_path, capsys, content, message):
    src, out = tmp_path / "in.gcode", tmp_path / "out.gcode"
    src.write_bytes(content)
    assert cli.main(["annotate", str(src), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"flowloop annotate: error: {src}: line ")
    assert message in err and err.count("\n") == 1
    assert not out.exists()
    assert src.read_bytes() == content


def test_the_command_help_gives_the_profiles_default_working_point():
    # flowloop.cli.annotate keeps its own copy (material.profile and msgspec
    # are not imported at every upload's start-up)
    from flowloop.cli import annotate as command
    from flowloop.material.profile import DEFAULT_WORKING_POINT
    assert command.DEFAULT_WORKING_POINT == DEFAULT_WORKING_POINT


def test_an_unreadable_file_is_one_line(tmp_path, capsys):
    assert cli.main(["annotate", str(tmp_path / "missing.gcode")]) == 2
    err = capsys.readouterr().err
    assert err == (f"flowloop annotate: error: {tmp_path / 'missing.gcode'}: "
                   "cannot read: No such file or directory\n")


# --- any file ---------------------------------------------------------------------

steps = st.lists(st.tuples(st.floats(min_value=0.5, max_value=60),      # mm
                           st.floats(min_value=0.0, max_value=0.2),      # E per mm
                           st.sampled_from([300, 1200, 3000, 9000]),     # F
                           st.sampled_from(["", "", "", "G4 P800", "M109 S210",
                                            "M109 S210\nG4 P1500",
                                            "G1 E-1 F2400", "G1 E1 F2400"])),
                 min_size=1, max_size=60)


def zigzag_file(moves) -> bytes:
    """A relative-E file of the `steps` strategy's moves, back and forth."""
    lines, x = ["M83"], 0.0
    for i, (length, e_per_mm, feed, extra) in enumerate(moves):
        x = x + length if i % 2 else x - length
        lines.append(f"G1 X{x:.3f} Y{i * 0.5:.1f} E{length * e_per_mm:.4f} F{feed}")
        if extra:
            lines.append(extra)
    return "\n".join(lines).encode() + b"\n"


@settings(max_examples=80, deadline=None)
@given(steps, st.sampled_from([(4.0, 0.5), (15.0, 1.0), (8.0, 3.0)]))
def test_announcements_cover_the_flow_of_any_file(moves, lead_window):
    data = zigzag_file(moves)
    settings_ = AnnotateSettings(*lead_window)
    result = annotated(data, settings_)
    assert_announcements_cover_the_flow(data, result, settings_)




def annotated_by(events, data: bytes, settings_: AnnotateSettings) -> bytes:
    out = io.BytesIO()
    annotate_stream(events, io.BytesIO(data), out, settings_)
    return out.getvalue()


@settings(max_examples=80, deadline=None)
@given(steps, st.sampled_from([(4.0, 0.5), (15.0, 1.0), (8.0, 3.0), (2.0, 0.1)]),
       st.integers(20, 2000))
def test_windows_taken_in_bulk_are_the_ones_taken_one_move_at_a_time(
        moves, lead_window, chunk_bytes):
    data = zigzag_file(moves)
    settings_ = AnnotateSettings(*lead_window)
    one_by_one = annotated_by(plan_file(io.BytesIO(data)), data, settings_)
    in_bulk = annotated_by(plan_batches(io.BytesIO(data), chunk_bytes=chunk_bytes),
                           data, settings_)
    assert in_bulk == one_by_one


@pytest.mark.parametrize("lead_window", [(60.0, 1.0), (10.0, 0.3), (2.0, 0.1)])
@pytest.mark.parametrize("name", ["block_layers_1_2.gcode", "box_bridge_layer.gcode"])
def test_a_real_file_annotated_in_bulk_is_annotated_as_one_move_at_a_time(
        name, lead_window):
    data = (DATA / name).read_bytes()
    settings_ = AnnotateSettings(*lead_window)
    one_by_one = annotated_by(plan_file(io.BytesIO(data)), data, settings_)
    for chunk_bytes in (1 << 20, 3000):
        in_bulk = annotated_by(plan_batches(io.BytesIO(data), chunk_bytes=chunk_bytes),
                               data, settings_)
        assert in_bulk == one_by_one


class Discard:
    def write(self, data: bytes) -> int:
        return len(data)


def peak_memory_annotating(data: bytes, plan) -> int:
    import tracemalloc
    lines, src = io.BytesIO(data), io.BytesIO(data)
    tracemalloc.start()
    try:
        annotate_stream(plan(lines), src, Discard())
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("plan", [
    plan_file, lambda f: plan_batches(f, chunk_bytes=4096)],
    ids=["line by line", "in chunks"])
@pytest.mark.parametrize("extruding", [False, True])
def test_memory_does_not_grow_with_the_file(extruding, plan):
    def file(lines: int) -> bytes:
        e = " E0.05" if extruding else ""
        return b"M83\n" + b"".join(f"G1 X{i % 2 * 10} Y{i % 7}{e} F3000\n".encode()
                                   for i in range(lines))
    small = peak_memory_annotating(file(2000), plan)
    large = peak_memory_annotating(file(20000), plan)
    assert large < 1.5 * small


def test_a_byte_order_mark_is_left_out_and_the_file_is_annotated_once(tmp_path):
    body = b"M83\n" + b"".join(f"G1 X{i % 2 * 10} Y{i} E0.2 F1200\n".encode()
                               for i in range(40))
    bom, plain = tmp_path / "bom.gcode", tmp_path / "plain.gcode"
    bom.write_bytes(codecs.BOM_UTF8 + body)
    plain.write_bytes(body)
    assert annotate_file(bom) == annotate_file(plain)
    # exactly what the file without it becomes: the marker first, so
    # annotating again (and Moonraker's ident) sees it
    assert bom.read_bytes() == plain.read_bytes()
    assert is_annotated(bom.read_bytes())
    before = bom.read_bytes()
    assert not annotate_file(bom).annotated
    assert bom.read_bytes() == before


@pytest.mark.parametrize("bake", [False, True])
def test_the_command_as_moonraker_runs_it_writes_what_a_thread_writes(
        tmp_path, monkeypatch, bake):
    """The command as Moonraker runs it (a process of its own with one
    thread: the planner runs in a child process, flowloop.gcode.ahead; here
    for a file of any size) writes the bytes the same command writes with
    the planner in a thread."""
    extra = []
    if bake:
        profile = tmp_path / "weak.json"
        profile.write_text(json.dumps(WEAK_PROFILE))
        extra = ["--bake", str(profile)]

    def args(out: Path) -> List[str]:
        return ["annotate", str(DATA / "curves_0.4mm_layers_1_10.gcode"),
                "-o", str(out), *extra]
    child = tmp_path / "child.gcode"
    script = ("import sys; from flowloop.gcode import bulk_planner;"
              " bulk_planner.PROCESS_FROM_BYTES = 0;"
              " from flowloop.cli import main; sys.argv[0] = 'flowloop';"
              " sys.exit(main())")
    run = subprocess.run([sys.executable, "-c", script, *args(child)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    monkeypatch.setattr(ahead_module, "can_fork", lambda: False)
    thread = tmp_path / "thread.gcode"
    assert cli.main(args(thread)) == 0
    assert child.read_bytes() == thread.read_bytes()
    said = re.compile(rb"^M104 S\d+", re.M) if bake else COMMAND
    assert said.search(child.read_bytes())
