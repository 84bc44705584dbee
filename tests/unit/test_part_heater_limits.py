"""Every other target flowloop writes stays within the printer's own
[extruder] min_temp..max_temp where it knows them (issue 35.5, the pattern):
the test parts refuse a temperature the printer would refuse (the user
asked for it: lowering it would print another part), a start macro given
more than max_temp is lowered as the bake lowers the file's own M109, and
MEASURE_MATERIAL_PROFILE never sets its heater below the heater's min_temp."""

from __future__ import annotations

import json

import pytest

from flowloop.cli import main
from flowloop.control.heater_range import HeaterRange
from flowloop.control.tools import check_heater_target
from flowloop.errors import FlowloopError
from flowloop.material import procedure as proc
from tests.unit.test_bake_heater_limits import (
    BLOCK,
    EXTRUDER_250,
    HOT,
    TARGET,
    printer_cfg,
)

pytestmark = pytest.mark.unit

EXTRUDER_170_250 = EXTRUDER_250.replace("min_temp: 0", "min_temp: 170")


def run(capsys, *argv: str):
    code = main(list(argv))
    said = capsys.readouterr()
    return code, said.out, said.err


# --- the test parts ------------------------------------------------------------

def test_a_measurement_part_at_260_on_a_printer_with_max_temp_250_is_refused(
        tmp_path, capsys):
    cfg = printer_cfg(tmp_path, EXTRUDER_250)
    out = tmp_path / "part.gcode"
    code, said, err = run(capsys, "measure-part", "-o", str(out), "--temp", "260",
                          "--printer-cfg", str(cfg))
    assert code != 0 and not out.exists()
    assert err.strip() == (
        f"flowloop measure-part: error: --temp 260 C is above the printer's"
        f" max_temp 250 C ({cfg} [extruder]): Klipper would refuse it")


def test_a_measurement_part_within_the_range_is_written_at_its_temperature(
        tmp_path, capsys):
    cfg = printer_cfg(tmp_path, EXTRUDER_250)
    out = tmp_path / "part.gcode"
    code, said, err = run(capsys, "measure-part", "-o", str(out), "--height", "3",
                          "--temp", "250", "--printer-cfg", str(cfg))
    assert code == 0, err
    assert err == ""
    assert [float(t) for t in TARGET.findall(out.read_text())] == [250, 250, 0]


def test_pylons_below_the_printer_s_min_temp_are_refused(tmp_path, capsys):
    cfg = printer_cfg(tmp_path, EXTRUDER_170_250)
    out = tmp_path / "pylons.gcode"
    code, said, err = run(capsys, "ab-pylons", "-o", str(out), "--hotend-temp",
                          "160", "--printer-cfg", str(cfg))
    assert code != 0 and not out.exists()
    assert err.strip() == (
        f"flowloop ab-pylons: error: --hotend-temp 160 C is below the printer's"
        f" min_temp 170 C ({cfg} [extruder]): Klipper would refuse it")


def test_pylons_whose_written_whole_degree_is_above_max_temp_are_refused(
        tmp_path, capsys):
    cfg = printer_cfg(tmp_path, EXTRUDER_250.replace("max_temp: 250",
                                                     "max_temp: 249.8"))
    code, said, err = run(capsys, "ab-pylons", "-o", str(tmp_path / "p.gcode"),
                          "--hotend-temp", "249.6", "--printer-cfg", str(cfg))
    assert code != 0
    assert "--hotend-temp 249.6 C (written as 250) is above the printer's" \
           " max_temp 249.8 C" in err


def test_pylons_at_260_with_max_temp_250_are_refused_and_within_it_written(
        tmp_path, capsys):
    cfg = printer_cfg(tmp_path, EXTRUDER_250)
    code, said, err = run(capsys, "ab-pylons", "-o", "-", "--hotend-temp", "260",
                          "--printer-cfg", str(cfg))
    assert code != 0 and said == ""
    assert "--hotend-temp 260 C is above the printer's max_temp 250 C" in err
    code, said, err = run(capsys, "ab-pylons", "-o", "-", "--hotend-temp", "245",
                          "--printer-cfg", str(cfg))
    assert code == 0, err
    assert [float(t) for t in TARGET.findall(said)] == [245, 245, 0]


def test_a_printer_cfg_without_extruder_says_the_part_s_temperature_is_unchecked(
        tmp_path, capsys):
    cfg = tmp_path / "printer.cfg"
    cfg.write_text("[printer]\nkinematics: none\n")
    out = tmp_path / "part.gcode"
    code, said, err = run(capsys, "measure-part", "-o", str(out), "--height", "3",
                          "--printer-cfg", str(cfg))
    assert code == 0 and out.exists()
    assert err.strip() == (f"{cfg} has no [extruder]: --temp not checked against"
                           f" its min_temp/max_temp")


def test_an_extruder_without_max_temp_is_refused_for_a_part_as_klippy_refuses_it(
        tmp_path, capsys):
    cfg = printer_cfg(tmp_path, "[extruder]\nmin_temp: 0\n")
    code, said, err = run(capsys, "ab-pylons", "-o", str(tmp_path / "p.gcode"),
                          "--printer-cfg", str(cfg))
    assert code != 0
    assert err.strip() == ("flowloop ab-pylons: error: Option 'max_temp' in"
                           " section 'extruder' must be specified")


# --- the bake's start macro ---------------------------------------------------

def test_a_start_macro_given_260_with_max_temp_250_is_lowered_and_said(
        tmp_path, capsys):
    src = tmp_path / "macro.gcode"
    src.write_text(BLOCK.read_text().replace("M109 S200",
                                             "PRINT_START EXTRUDER=260 BED=60"))
    profile = tmp_path / "hot.json"
    profile.write_text(json.dumps(HOT))
    out = tmp_path / "baked.gcode"
    cfg = printer_cfg(tmp_path, EXTRUDER_250)
    code, said, err = run(capsys, "annotate", str(src), "-o", str(out), "--bake",
                          str(profile), "--printer-cfg", str(cfg))
    assert code == 0, err
    lines = out.read_text().splitlines()
    assert ("PRINT_START EXTRUDER=250 BED=60 ; flowloop bake: was PRINT_START"
            " EXTRUDER=260 BED=60, outside max_temp 250") in lines
    assert not any("EXTRUDER=260" in line.split(";")[0] for line in lines)
    assert (f"  start: PRINT_START's EXTRUDER=260 (line 17) is outside the"
            f" printer's max_temp 250 C ({cfg} [extruder]): lowered to"
            f" EXTRUDER=250\n  start: PRINT_START (line 17) is given"
            f" EXTRUDER=250, at least the plan's 250 C: kept") in said


def test_a_start_macro_within_the_range_is_left_as_written(tmp_path, capsys):
    src = tmp_path / "macro.gcode"
    src.write_text(BLOCK.read_text().replace("M109 S200", "PRINT_START EXTRUDER=245"))
    profile = tmp_path / "hot.json"
    profile.write_text(json.dumps(HOT))
    out = tmp_path / "baked.gcode"
    code, said, err = run(capsys, "annotate", str(src), "-o", str(out), "--bake",
                          str(profile), "--printer-cfg",
                          str(printer_cfg(tmp_path, EXTRUDER_250)))
    assert code == 0, err
    assert "\nPRINT_START EXTRUDER=245 ; set temperature and wait" in out.read_text()
    assert "lowered" not in said


# --- one rule for what a heater accepts ---------------------------------------

@pytest.mark.parametrize("temp_c", [0.0, 170.0, 250.0, 169.9, 250.1, -1.0,
                                    float("nan")])
def test_klippy_s_m104_check_and_the_files_use_the_same_rule(temp_c):
    accepted = HeaterRange(170.0, 250.0, "heater").accepts(temp_c)
    try:
        check_heater_target(temp_c, 170.0, 250.0)
        refused = False
    except FlowloopError:
        refused = True
    assert accepted is not refused


# --- MEASURE_MATERIAL_PROFILE's heater ------------------------------------------

def test_a_measurement_never_goes_below_the_heater_s_min_temp():
    # the run sets its heater to the bounds' minimum: Klipper refuses 150
    # on a heater with min_temp 170
    b = proc.bounds_for(None, 150.0, 240.0, 300.0, 170.0)
    assert (b.min_temp_c, b.max_temp_c) == (170.0, 240.0)
    with pytest.raises(FlowloopError, match="MIN_TEMP: 250 degC is not below"
                                            " the maximum 240 degC"):
        proc.bounds_for(None, 150.0, 240.0, 300.0, 250.0)
