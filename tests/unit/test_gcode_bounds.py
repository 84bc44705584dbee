"""Every temperature, speed and size a generated part writes into G-code is
bounded, from one table (flowloop.gcode.bounds), for the CLI and the core alike."""

from __future__ import annotations

import dataclasses

import pytest

from flowloop import cli
from flowloop.calibrate.pylons import PylonOptions
from flowloop.cli.diff_ab import PYLON_OPTIONS
from flowloop.cli.measure import OPTIONS as PART_OPTIONS
from flowloop.errors import FlowloopError
from flowloop.gcode import bounds
from flowloop.gcode.measure_part import PartOptions

# Options that are neither a temperature, a speed nor a size (a ratio, a flow
# held at the max speed, where the rows cross: checked against the bed).
NOT_WRITTEN_AS_IS = {"rise", "start-flow", "max-flow", "extrusion-multiplier",
                     "centre-x", "centre-y"}


def written_options():
    for command, table in (("measure-part", PART_OPTIONS),
                           ("ab-pylons", PYLON_OPTIONS)):
        for flag, _, _ in table:
            if flag not in NOT_WRITTEN_AS_IS:
                yield command, flag


@pytest.mark.parametrize("command, flag", list(written_options()))
def test_an_absurd_value_of_every_written_option_is_refused_naming_it(
        tmp_path, capsys, command, flag):
    out = tmp_path / "part.gcode"
    assert cli.main([command, "-o", str(out), f"--{flag}", "1e7"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"flowloop {command}: error: --{flag} ")
    assert err.count("\n") == 1
    assert not out.exists()


def test_measure_part_refuses_a_hotend_of_1000_c_as_the_pylons_do(tmp_path, capsys):
    out = tmp_path / "part.gcode"
    assert cli.main(["measure-part", "-o", str(out), "--temp", "1000"]) == 2
    assert capsys.readouterr().err == (
        "flowloop measure-part: error: --temp must be a number from 150 to 320 C,"
        " got 1000\n")
    assert cli.main(["measure-part", "-o", str(out), "--bed-temp", "500"]) == 2
    assert capsys.readouterr().err == (
        "flowloop measure-part: error: --bed-temp must be a number from 0 to 130 C,"
        " got 500\n")
    assert cli.main(["ab-pylons", "-o", str(out), "--hotend-temp", "1000"]) == 2
    assert capsys.readouterr().err == (
        "flowloop ab-pylons: error: --hotend-temp must be a number from 150 to"
        " 320 C, got 1000\n")
    assert not out.exists()


@pytest.mark.parametrize("make", [
    lambda **kw: PartOptions(**{"hotend_temp_c": 210.0, "bed_temp_c": 60.0, **kw}),
    lambda **kw: PylonOptions(**{"hotend_temp_c": 210.0, "bed_temp_c": 60.0, **kw}),
])
def test_both_generators_take_their_temperatures_from_the_one_table(make):
    hotend, bed = bounds.HOTEND_TEMP_C, bounds.BED_TEMP_C
    make(hotend_temp_c=hotend.low, bed_temp_c=bed.low)
    make(hotend_temp_c=hotend.high, bed_temp_c=bed.high)
    with pytest.raises(FlowloopError, match="^hotend_temp_c must be"):
        make(hotend_temp_c=hotend.high + 1)
    with pytest.raises(FlowloopError, match="^bed_temp_c must be"):
        make(bed_temp_c=bed.high + 1)


def test_the_core_refuses_a_speed_no_printer_moves_at():
    # The klippy side builds the same option objects: it refuses too.
    with pytest.raises(FlowloopError, match="^travel_speed_mm_s must be"):
        PartOptions(travel_speed_mm_s=5000.0)
    with pytest.raises(FlowloopError, match="^retract_speed_mm_s must be"):
        PylonOptions(retract_speed_mm_s=5000.0)


def test_a_bound_names_the_value_and_its_range():
    with pytest.raises(FlowloopError) as e:
        bounds.SPEED_MM_S.check("--speed", 0.0)
    assert str(e.value) == ("--speed must be a number above 0 and at most 1000"
                            " mm/s, got 0")
    assert bounds.SPEED_MM_S.check("--speed", 1000) == 1000.0


@pytest.mark.parametrize("options", [PartOptions, PylonOptions])
def test_every_number_a_generator_writes_has_its_bound_in_the_one_table(options):
    # a new option is bounded by bounds.OPTIONS or named here as not written
    not_written = {"rise", "start_flow_mm3_s", "max_flow_mm3_s",
                   "extrusion_multiplier", "centre_x_mm", "centre_y_mm",
                   "distances_mm"}
    numbers = {f.name for f in dataclasses.fields(options)
               if "float" in str(f.type)}
    assert numbers - not_written <= set(bounds.OPTIONS)
    assert numbers - not_written
