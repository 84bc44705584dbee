"""A baked file asks nothing of the heater the printer refuses: every target
within the printer's own [extruder] min_temp..max_temp, read from
--printer-cfg as klippy reads it, and the summary says when that bound the
plan and what to slice with then."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from flowloop.cli import main
from flowloop.control.heater_range import HeaterRange
from flowloop.errors import FlowloopError
from flowloop.gcode.heater import cap_line
from flowloop.host.klipper_config import heater_range, parse_config

pytestmark = pytest.mark.unit

DATA = Path(__file__).resolve().parents[1] / "data" / "gcode"
BLOCK = DATA / "block_layers_1_2.gcode"
# At working point 0.5 it melts 2.0 mm^3/s at 200 C and 0.08 more per degree:
# the block's infill (6.6 mm^3/s) needs 257.5 C, which the profile allows.
HOT = {"identity": {"name": "hot", "nozzle_diameter_mm": 0.4},
       "lines": {"into_air": {"slope_mm3_s_per_c": 0.08, "temp_c": 200.0,
                              "flow_mm3_s": 2.5},
                 "real_print": {"slope_mm3_s_per_c": 0.08, "temp_c": 200.0,
                                "flow_mm3_s": 1.5}},
       "bounds": {"min_temp_c": 190.0, "recommended_temp_c": 220.0,
                  "max_temp_c": 260.0},
       "provenance": {"method": "manual"}}
# Every heater target a line sets: M104/M109 S or R (commented lines set none).
TARGET = re.compile(r"^\s*M10[49]\b[^;\n]*?\s[SR](\d+(?:\.\d*)?)", re.M)


def printer_cfg(tmp_path: Path, extruder: str) -> Path:
    """printer.cfg including extruder.cfg (CRLF, as a Windows editor saves
    it), which holds [extruder]."""
    (tmp_path / "extruder.cfg").write_bytes(extruder.replace("\n", "\r\n").encode())
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[include extruder.cfg]\n\n[printer]\nkinematics: cartesian\n"
                   "max_velocity: 300\nmax_accel: 3000\n")
    return cfg


EXTRUDER_250 = ("[extruder]\nnozzle_diameter: 0.4\nfilament_diameter: 1.75\n"
                "min_temp: 0\nmax_temp: 250\n")


def bake(tmp_path: Path, capsys, *extra: str, src: Path = BLOCK):
    profile = tmp_path / "hot.json"
    profile.write_text(json.dumps(HOT))
    out = tmp_path / "baked.gcode"
    code = main(["annotate", str(src), "-o", str(out), "--bake", str(profile),
                 *extra])
    said = capsys.readouterr()
    return code, out, said.out, said.err


def test_a_profile_allowing_260_with_max_temp_250_writes_no_target_above_250(
        tmp_path, capsys):
    # the slicer's own start asks 265 and 260 of the heater too
    src = tmp_path / "hot.gcode"
    text = BLOCK.read_text()
    assert "M109 S200" in text
    src.write_text("M104 S265 ; preheat\n" + text.replace("M109 S200", "M109 S260"))
    code, out, said, err = bake(tmp_path, capsys, "--printer-cfg",
                                str(printer_cfg(tmp_path, EXTRUDER_250)), src=src)
    assert code == 0, err
    baked = out.read_text()
    targets = [float(t) for t in TARGET.findall(baked)]
    assert len(targets) > 5 and max(targets) == 250
    assert "M109 S250 ; flowloop bake: was M109 S260, outside max_temp 250" in baked
    assert "M104 S250 ; flowloop bake: was M104 S265, outside max_temp 250" in baked
    assert "start: the file's M109 S250 (line 18) heats to at least the plan's" \
        in said
    # the printer's limit bound the plan, and the summary says what to do:
    # 2.0 + 0.08 * 50 = 6.00 mm^3/s at 250 C
    cfg = tmp_path / "printer.cfg"
    assert f"targets capped at the printer's max_temp 250 C ({cfg} [extruder])," \
        f" below the profile's 260 C" in said
    assert re.search(r"\d+ windows need more than the printer's max_temp 250 C: .*"
                     r"slice with a max volumetric speed of 6\.00 mm\^3/s, or let"
                     r" \[flowrate_limiter\] hold the flow", said), said
    assert "2 of the file's own M104/M109 outside 0..250 C" in said


def test_the_same_bake_without_the_printer_s_limit_goes_to_the_profile_s_260(
        tmp_path, capsys):
    code, out, said, err = bake(tmp_path, capsys)
    assert code == 0, err
    targets = [float(t) for t in TARGET.findall(out.read_text())]
    assert 250 < max(targets) <= 260
    assert "targets not checked against the printer's min_temp/max_temp: give" \
        " --printer-cfg" in said


def test_an_extruder_without_max_temp_is_refused_as_klippy_refuses_it(
        tmp_path, capsys):
    cfg = printer_cfg(tmp_path, "[extruder]\nmin_temp: 0\n")
    code, out, said, err = bake(tmp_path, capsys, "--printer-cfg", str(cfg))
    assert code != 0 and not out.exists()
    assert err.strip() == ("flowloop annotate: error: Option 'max_temp' in"
                           " section 'extruder' must be specified")


def test_a_printer_cfg_without_extruder_says_the_targets_are_not_checked(
        tmp_path, capsys):
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[printer]\nkinematics: none\nmax_velocity: 300\n"
                   "max_accel: 3000\n")
    code, out, said, err = bake(tmp_path, capsys, "--printer-cfg", str(cfg))
    assert code == 0, err
    assert f"{cfg} has no [extruder]: targets not checked against its" \
        " min_temp/max_temp" in said


def test_a_heater_range_gives_whole_degrees_klipper_accepts():
    heater = HeaterRange(170.0, 249.5, "printer.cfg [extruder]")
    assert heater.whole(249.2) == 249       # 250 would be refused
    assert heater.whole(231.01) == 232      # rounded up below the top
    assert heater.whole(150.0) == 170
    assert heater.accepts(0) and not heater.accepts(100) and not heater.accepts(250)
    with pytest.raises(FlowloopError, match="max_temp 170 must be above min_temp 170"):
        HeaterRange(170.0, 170.0, "printer.cfg [extruder]")


@pytest.mark.parametrize("line, expected", [
    (b"M104 S265\n",
     b"M104 S250 ; flowloop bake: was M104 S265, outside max_temp 250\n"),
    (b"M109 R260 T0\r\n",
     b"M109 R250 T0 ; flowloop bake: was M109 R260 T0, outside max_temp 250\r\n"),
    (b"M104 S100\n",
     b"M104 S170 ; flowloop bake: was M104 S100, outside min_temp 170\n"),
    (b"M104 S0\n", b"M104 S0\n"),                  # off: always accepted
    (b"M104 T1 S300\n", b"M104 T1 S300\n"),        # another heater's
    (b"M1040 S300\n", b"M1040 S300\n"),
    (b"; M104 S300\n", b"; M104 S300\n"),
    (b"M104 S240 ; print\n", b"M104 S240 ; print\n"),
    (b"M104 S255 ; print\n",
     b"M104 S250 ; flowloop bake: was M104 S255, outside max_temp 250\n"),
])
def test_the_file_s_own_targets_are_brought_within_the_range(line, expected):
    heater = HeaterRange(170.0, 250.0, "printer.cfg [extruder]")
    newline = b"\r\n" if line.endswith(b"\r\n") else b"\n"
    assert cap_line(line, heater, newline)[0] == expected


def test_the_range_comes_from_extruder_as_klippy_reads_it():
    config = parse_config("[extruder]\nmin_temp: 5\nmax_temp: 285 # hot\n")
    assert heater_range(config, "p.cfg") == HeaterRange(5.0, 285.0, "p.cfg [extruder]")
    assert heater_range(parse_config("[printer]\n"), "p.cfg") is None
    with pytest.raises(FlowloopError, match="'max_temp' in section 'extruder'"
                                            " must be above 300"):
        heater_range(parse_config("[extruder]\nmin_temp: 300\nmax_temp: 250\n"),
                     "p.cfg")
