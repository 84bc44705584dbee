"""Every feature per tool: a two-extruder printer (config/toolchanger.cfg,
the docs' example) prints a real PrusaSlicer two-tool file
(tests/data/gcode/two_tool_box.gcode: perimeters on T0, infill on T1, the
slicer's standby temperatures for the idle tool) with a profile per tool.
Judged on the steps Klipper sends (each extruder's own step pin) and on the
heaters' targets as the print goes."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import pytest

from devtools import stack
from devtools.klippy_test import run_file, write_test
from flowloop.material.profile import profile_from_dict, profile_line
from tests.klippy.flowrate_limiter_steps import parsedump, stepper_steps, windowed_flow
from tests.klippy.test_flowrate_limiter import AREA, CLOCK_HZ, MM_PER_STEP
from tests.samples import make

HERE = Path(__file__).resolve().parent
GCODE = HERE.parent / "data" / "gcode" / "two_tool_box.gcode"
CONFIG = HERE / "toolchanger.cfg"
STEP_PINS = {"extruder": "PA4", "extruder1": "PC1"}
WINDOW_S = 0.1
CHUNK_LINES = 20


def _profile(name, flow_mm3_s, temp_c, min_c, max_c):
    return make(air=(0.05, temp_c, flow_mm3_s + 1.0), real=(0.05, temp_c, flow_mm3_s),
                bounds=(min_c, max_c - 5.0, max_c), name=name,
                identity={"nozzle_diameter_mm": 0.4})


# T0 melts little (PLA on a small hotend), T1 more (the file's infill tool):
# the file asks each for more than its profile allows.
PROFILES = {"extruder": _profile("t0-pla", 2.0, 200.0, 190.0, 215.0),
            "extruder1": _profile("t1-petg", 5.0, 230.0, 220.0, 245.0)}
WP = 0.0   # the real-print line


def _cap(extruder: str) -> float:
    """The most a tool's profile allows: its line at its max_temp_c."""
    profile = profile_from_dict(PROFILES[extruder])
    return profile_line(profile, WP).flow_mm3_s(profile.bounds.max_temp_c)


@pytest.fixture(scope="module")
def printed(klipper_build, klippy_venv):
    """The file printed in chunks: one record per chunk (the tool that
    prints, each autotemp's status, each heater's target, the chunk's
    lines), each limiter's final status, the MCU output decoded."""
    workdir = stack.short_tempdir("fl-tools-")
    klippy = stack.Klippy(klipper_build, klippy_venv, CONFIG, workdir,
                          {"mcu": "atmega2560"})
    records, limiters = [], {}
    try:
        api = klippy.ready_api()
        try:
            for extruder, profile in PROFILES.items():
                api.call("flowloop/set_active_profile", extruder=extruder,
                         profile=profile, working_point=WP)
            # what the file's M109 would do on a printer (batch mode does not
            # wait): both hotends hot before the first layer
            api.gcode("\n".join(
                ["G28", "SET_HEATER_TEMPERATURE HEATER=extruder TARGET=215",
                 "SET_HEATER_TEMPERATURE HEATER=extruder1 TARGET=240"]
                + [f"G1 X{10 if i % 2 else 160} F6000" for i in range(60)]
                + ["M400"]))
            lines = GCODE.read_text().splitlines()
            for i in range(0, len(lines), CHUNK_LINES):
                chunk = lines[i:i + CHUNK_LINES]
                api.gcode("\n".join(chunk + ["M400"]))
                now = api.status_now("toolhead", "autotemp", "autotemp extruder1",
                                     "extruder", "extruder1")
                records.append({"tool": now["toolhead"]["extruder"],
                                "autotemp": {"extruder": now["autotemp"],
                                             "extruder1": now["autotemp extruder1"]},
                                "target": {"extruder": now["extruder"]["target"],
                                           "extruder1": now["extruder1"]["target"]},
                                "lines": chunk})
            limiters = {name: api.query(section) for name, section in (
                ("extruder", "flowrate_limiter"),
                ("extruder1", "flowrate_limiter extruder1"))}
        finally:
            api.close()
    finally:
        klippy.stop()
    log = (workdir / "klippy.log").read_text()
    dump = parsedump(klipper_build, klippy_venv,
                     klipper_build.dictionary("atmega2560"), workdir / "mcu-output")
    shutil.rmtree(workdir, ignore_errors=True)
    return records, limiters, dump, log


def _flow(dump, extruder):
    return windowed_flow(*stepper_steps(dump, STEP_PINS[extruder]), CLOCK_HZ,
                         MM_PER_STEP, AREA, WINDOW_S)


def test_the_file_is_a_two_tool_print_with_no_unknown_command(printed):
    records, _, _, log = printed
    assert "Unknown command" not in log
    tools = [r["tool"] for r in records]
    changes = [b for a, b in zip(tools, tools[1:]) if a != b]
    # perimeters on T0, infill on T1, six layers: T0 -> T1 -> T0 ...
    assert changes == ["extruder1", "extruder"] * 3


def test_each_tools_moves_are_capped_by_its_own_profile(printed):
    _, limiters, dump, _ = printed
    for extruder in ("extruder", "extruder1"):
        flow = _flow(dump, extruder)
        allowed = _cap(extruder) * WINDOW_S / (AREA * MM_PER_STEP)
        assert flow["max_steps"] <= math.ceil(allowed) + 1, extruder
        assert limiters[extruder]["profile"] == PROFILES[extruder]["identity"]["name"]
        assert limiters[extruder]["slowed_moves"] > 0
    # T1 ran well above T0's cap: its moves were not capped by T0's profile
    assert _flow(dump, "extruder1")["max_flow"] > _cap("extruder") + 1.0


def test_autotemp_heats_the_printing_tool_from_its_own_profile(printed):
    records, _, _, _ = printed
    for extruder in ("extruder", "extruder1"):
        bounds = PROFILES[extruder]["bounds"]
        planned = [r for r in records if r["tool"] == extruder
                   and r["autotemp"][extruder]["target"] is not None]
        assert len(planned) >= 5, extruder
        for r in planned:
            assert r["autotemp"][extruder]["profile"] == \
                PROFILES[extruder]["identity"]["name"]
            assert bounds["min_temp_c"] <= r["target"][extruder] \
                <= bounds["max_temp_c"]


def test_the_idle_tool_keeps_the_slicers_standby(printed):
    records, _, _, _ = printed
    # the file's standby: M104 S175 T0 before T1, M104 S200 T1 before T0
    standby = {"extruder": 175.0, "extruder1": 200.0}
    for previous, r in zip(records, records[1:]):
        for extruder, temp_c in standby.items():
            idle_all_chunk = previous["tool"] != extruder and r["tool"] != extruder
            if idle_all_chunk and not any(f"T{extruder[-1:] or 0}" in x
                                          for x in r["lines"]):
                assert r["target"][extruder] == temp_c, (extruder, r["lines"])
                assert r["autotemp"][extruder]["target"] is None


def test_the_slicers_m104_for_the_printing_tool_is_overridden_and_kept(printed):
    _, _, _, log = printed
    # M104 S175 T0 comes while T0 still prints: kept for the hand-back
    assert "autotemp: M104 S175 overridden" in log
    assert "autotemp extruder1: M104 S200 overridden" in log


# --- bad input ---------------------------------------------------------------

TWO_TOOLS = f"[include {HERE}/flow_sensor_printer.cfg]\n" \
            f"[include {HERE.parent.parent}/config/toolchanger.cfg]\n"


@pytest.mark.parametrize("extra, message", [
    ("[flowrate_limiter extruder2]\n",
     "Section [flowrate_limiter extruder2], option extruder: 'extruder2' is not"
     " an extruder"),
    ("[autotemp extruder2]\n",
     "Section [autotemp extruder2], option extruder: 'extruder2' is not an"
     " extruder"),
    ("[flowrate_limiter]\nextruder: extruder1\n",
     "Section [flowrate_limiter extruder1], option extruder: extruder1 already"
     " has [flowrate_limiter] (one [flowrate_limiter] section per extruder)"),
    ("[autotemp extruder1]\nextruder: extruder\n",
     "Option 'extruder' is not valid in section 'autotemp extruder1'"),
])
def test_a_section_for_no_such_tool_is_one_config_error_naming_it(
        klipper_build, klippy_venv, short_tmp, extra, message):
    _, test = write_test(short_tmp, "bad", cfg=TWO_TOOLS + extra, should_fail=True)
    log = run_file(test, klipper_build, klippy_venv, short_tmp)
    assert message in log
    assert log.count("Config error") == 1
