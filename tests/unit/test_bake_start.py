"""The bake starts the print at the temperature its plan starts from, with the
start G-code slicers write for Klipper (flowloop.gcode.start)."""

from __future__ import annotations

import io
import re
from pathlib import Path

import pytest

from flowloop.cli import main
from flowloop.gcode.bake import bake_file
from flowloop.gcode.start import find_start_heat, start_fix
from flowloop.material.profile import profile_from_dict
from tests.unit.test_autotemp_bake import BLOCK, WEAK

PROFILE = profile_from_dict(WEAK)
BODY = BLOCK.read_text().split("M82 ; use absolute distances for extrusion\n", 1)[1]
# The usual Klipper start G-code of each slicer (as written into the file)
STARTS = {
    # PrusaSlicer's Klipper printer profiles: the automatic M190/M109 off,
    # the start macro heats and waits
    "prusaslicer": "M190 S0\nM109 S0 ; uncomment to remove set&wait temp gcode\n"
                   "PRINT_START EXTRUDER=200 BED=60\n",
    # OrcaSlicer's Voron profile
    "orcaslicer": "PRINT_START BED=60 HOTEND=200 CHAMBER=0\n",
    # Cura with Klipper's documented START_PRINT macro
    "cura": "START_PRINT BED_TEMP=60 EXTRUDER_TEMP=200\n",
    # a plain file: the slicer's own heat-and-wait
    "plain": "M104 S200\nG28\nG1 Z5 F5000\nM109 S200\n",
}


def _file(tmp_path: Path, start: str) -> Path:
    path = tmp_path / "in.gcode"
    path.write_text("; test\n" + start + "G90\nM82\n" + BODY)
    return path


def _first_extrusion_line(lines):
    e = 0.0
    for i, line in enumerate(lines):
        m = re.match(r"^G1 .*E([-0-9.]+)", line)
        if m and float(m[1]) > e + 1e-9 and " X" in line:
            return i
        if m:
            e = float(m[1])
        if line.startswith("G92 E0"):
            e = 0.0
    raise AssertionError("no extrusion")


def _wait_before_first_extrusion(text: str):
    """The temperature of the last M109 Klipper runs before the first
    extruding move (None: it never waits)."""
    lines = text.splitlines()
    waits = [int(m[1]) for line in lines[:_first_extrusion_line(lines)]
             for m in [re.match(r"^M109 S(\d+)", line)] if m]
    return waits[-1] if waits else None


@pytest.mark.parametrize("slicer", sorted(STARTS))
def test_the_print_starts_where_the_plan_starts(tmp_path, slicer):
    src = _file(tmp_path, STARTS[slicer])
    out = tmp_path / "out.gcode"
    result, timeline = bake_file(src, out, PROFILE, 0.5)
    text = out.read_text()
    start = result.start
    # the infill of the first layer needs 226 C: the plan starts there
    assert start.start_c >= 226
    if slicer == "plain":
        assert start.action == "raise"
        assert not re.search(r"^M109 S200", text, re.M)
    else:
        assert start.action == "add"
        assert "added M109 S227 after it" in start.message
    # the heater waits at the plan's start before the first extrusion
    assert _wait_before_first_extrusion(text) == start.start_c
    # the modelled nozzle starts there
    assert timeline.nozzle_c[0] >= 225.0
    assert result.under_capacity_s == 0.0


def test_a_hotter_wait_is_kept_and_the_model_starts_from_it(tmp_path):
    src = _file(tmp_path, "G28\nM109 S235\n")
    out = tmp_path / "out.gcode"
    result, timeline = bake_file(src, out, PROFILE, 0.5)
    assert result.start.action == "keep"
    assert "M109 S235" in out.read_text()
    assert abs(timeline.nozzle_c[0] - 235.0) < 1.0


def test_a_macro_given_enough_is_kept_and_says_what_it_assumed(tmp_path):
    src = _file(tmp_path, "PRINT_START EXTRUDER=230 BED=60\n")
    result, _ = bake_file(src, tmp_path / "out.gcode", PROFILE, 0.5)
    assert result.start.action == "keep"
    assert "assuming your macro waits at it" in result.start.message


def test_a_file_that_never_waits_gets_a_wait_before_its_first_extrusion(tmp_path):
    src = _file(tmp_path, "G28\n")
    out = tmp_path / "out.gcode"
    result, _ = bake_file(src, out, PROFILE, 0.5)
    assert result.start.action == "add"
    assert "no M109 or start macro" in result.start.message
    assert _wait_before_first_extrusion(out.read_text()) == result.start.start_c


def test_the_cli_says_what_it_did_in_one_line(tmp_path, capsys):
    src = _file(tmp_path, STARTS["prusaslicer"])
    profile = tmp_path / "weak.json"
    profile.write_text(__import__("json").dumps(WEAK))
    assert main(["annotate", str(src), "-o", str(tmp_path / "o.gcode"),
                 "--bake", str(profile)]) == 0
    out = capsys.readouterr().out.splitlines()
    start = [x for x in out if x.strip().startswith("start:")]
    assert start == ["  start: PRINT_START (line 4) is given EXTRUDER=200, below"
                     " the plan's 227 C: added M109 S227 after it; to heat once,"
                     " give it EXTRUDER=227"]


# --- the rule alone -------------------------------------------------------

def _heat(text: str, first: int = None):
    data = text.encode()
    return find_start_heat(io.BytesIO(data), len(data) if first is None else first)


def test_the_last_wait_before_the_first_extrusion_counts():
    heat = _heat("PRINT_START EXTRUDER=200\nM109 S210\nG1 X1\n")
    assert (heat.kind, heat.temp_c, heat.line_no) == ("m109", 210.0, 2)
    heat = _heat("M109 S210\nPRINT_START EXTRUDER=200\n")
    assert (heat.kind, heat.temp_c, heat.param) == ("macro", 200.0, "EXTRUDER")


def test_another_tools_wait_and_plain_commands_are_not_the_start():
    assert _heat("M109 T1 S250\nSET_PRESSURE_ADVANCE ADVANCE=0.04\nG28\n"
                 ).kind == "none"
    assert _heat("M109 T0 S215\n").temp_c == 215.0
    assert _heat("M109 R190\n").temp_c == 190.0
    # a start macro without a temperature: unknown
    heat = _heat("START_PRINT\n")
    assert (heat.kind, heat.temp_c) == ("macro", None)
    assert start_fix(heat, 226.0).action == "add"
    assert "waits at a temperature the file does not say" in start_fix(
        heat, 226).message


def test_a_wait_after_the_first_extrusion_is_not_the_start():
    text = "G28\nG1 X1 E1\nM109 S250\n"
    assert _heat(text, text.index("G1 X1")).kind == "none"


def test_an_m109_without_a_temperature_is_unknown():
    fix = start_fix(_heat("M109\n"), 226.0)
    assert fix.action == "add" and fix.line.startswith("M109 S226")


def test_a_byte_order_mark_is_left_out_and_the_baked_file_is_not_baked_again(
        tmp_path):
    import codecs

    from flowloop.errors import FlowloopError
    src = _file(tmp_path, STARTS["plain"])
    bom = tmp_path / "bom.gcode"
    bom.write_bytes(codecs.BOM_UTF8 + src.read_bytes())
    out, again = tmp_path / "out.gcode", tmp_path / "again.gcode"
    result, _ = bake_file(bom, out, PROFILE, 0.5)
    baked = out.read_bytes()
    assert baked.startswith(b"; flowloop autotemp annotations v")
    # the start's M109 on a later line is still found and raised
    assert result.start.action == "raise"
    with pytest.raises(FlowloopError, match="annotated or baked already"):
        bake_file(out, again, PROFILE, 0.5)
    # and it is the same file as the one baked without the mark
    bake_file(src, again, PROFILE, 0.5)
    assert again.read_bytes() == baked


def test_a_start_wait_on_the_first_line_after_a_byte_order_mark_is_found():
    heat = _heat("\ufeffM109 S210\nG1 X1 E1\n")
    assert (heat.kind, heat.temp_c) == ("m109", 210.0)
