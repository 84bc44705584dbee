"""Every G-code command flowloop registers, with bad values for every
parameter it takes (issue 36), in one batch-mode klippy run per printer:
klippy never shuts down, and after a refusal the printer's state (every
rotation_distance, heater targets, what SAVE_CONFIG would write, the
toolhead, each section's settings, the active profiles) is as it was.

A deterministic table: each command with parameters that would pass (the
base), then one parameter at a time replaced by each bad value. The values
that may be valid somewhere (0, -1, +-1e308, 1e-320: a LEAD of 0 is) are
sent too, for the "never shuts down" half; every other value must be
refused. klippy runs through fuzz_harness.py, which keeps a batch going
past the first refusal and logs the state after each line.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from devtools.klippy_test import KlippyTestFailure, run_file, write_test

HERE = Path(__file__).resolve().parent
PROJECT = HERE.parent.parent

# Values that are a number nowhere (nan, infinities, other scripts' digits,
# '_' separators, text, very long text, unicode) and values that are valid
# for some parameters (a LEAD of 0, an ENABLE of 0).
REFUSED = ["nan", "NaN", "inf", "-inf", "1_000", "\uff11\uff12", "1e", "--1",
           "0x10", "abc", "x" * 1000, "\u00e9", "\U0001f4a5", "\u0661\u0662",
           "1.5.2"]
MAYBE_VALID = ["0", "-1", "1e308", "-1e308", "1e-320"]
VALUES = REFUSED + MAYBE_VALID
# Klipper splits a traditional command's (M104) parameters at letters,
# upper-cased ("Snan" is a parameter SNAN, "S1e-320" is S1 E-320): these
# stay an S (or T) value that is no number
TRADITIONAL_REFUSED = ["-inf", "\uff11\uff12", "\u00e9", "\u0661\u0662"]

# command -> (base parameters that would pass or fail later, parameters)
COMMANDS = {
    "QUERY_FLOW_SENSOR": ("", ["SENSOR"]),
    "CALIBRATE_FLOW_SENSOR": ("LENGTH=1 SPEEDS=5,10 MAX_SPREAD=0.2",
                              ["LENGTH", "SPEEDS", "MAX_SPREAD", "SENSOR"]),
    "CALIBRATE_EXTRUDER_ROTATION_DISTANCE": ("LENGTH=5 SPEED=10",
                                             ["LENGTH", "SPEED", "SENSOR"]),
    "SET_FLOW_SENSOR_SIMULATION": ("", ["FAULT", "SENSOR"]),
    "SET_FLOWRATE_LIMIT": ("", ["ENABLE", "MAX_FLOW", "MODE", "EXTRUDER"]),
    "QUERY_FLOWRATE_LIMIT": ("", ["EXTRUDER"]),
    "AUTOTEMP_FLOW": ("FLOW=5 LEAD=2 DURATION=1", ["FLOW", "LEAD", "DURATION"]),
    "SET_AUTOTEMP": ("", ["ENABLE", "WP", "EXTRUDER"]),
    "QUERY_AUTOTEMP": ("", ["EXTRUDER"]),
    "M104": ("S0", ["S", "T"]),
    "M109": ("S0", ["S", "T"]),
    # TEMPS above the heater's max_temp: refused after every number is read
    "MEASURE_MATERIAL_PROFILE": (
        "NAME=fuzz TEMPS=300,310 MIN_TEMP=180 MAX_TEMP=250",
        ["NAME", "EXTRUDER", "TEMPS", "POWERS", "START_FLOW", "STEP",
         "MAX_FLOW", "MIN_GRIP", "ACTIVATE", "MIN_TEMP", "MAX_TEMP"]),
    # no active profile: refused after every number is read
    "MEASURE_MATERIAL_PROFILE_PRINT": ("NAME=fuzz",
                                       ["NAME", "EXTRUDER", "MIN_GRIP",
                                        "ACTIVATE"]),
    "MEASURE_MATERIAL_PROFILE_LAYER": ("LAYER=1 FLOW=5", ["LAYER", "FLOW"]),
    "CANCEL_MATERIAL_PROFILE": ("", []),
    "DIFF_AB_CALIBRATE": ("A1=10.01 A2=150.3 B1=10.0 B2=149.8",
                          ["A1", "A2", "B1", "B2", "D1", "D2", "A3", "B3",
                           "D3", "FORCE"]),
    "WAIT_BED_EQUILIBRIUM": ("", ["TOLERANCE", "TIMEOUT"]),
}
DELTA_COMMANDS = {
    # not homed: a probe that starts is refused by Klipper's first move
    "ENDSTOP_CALIBRATE": ("METHOD=manual",
                          ["METHOD", "RADIUS", "SAMPLES", "TOLERANCE",
                           "HORIZONTAL_MOVE_Z", "PROBE_SPEED", "LIFT_SPEED",
                           "SAMPLE_RETRACT_DIST", "SAMPLES_TOLERANCE",
                           "SAMPLES_TOLERANCE_RETRIES"]),
}
# Text parameters: none of the values is a valid one for them
TEXT = {"SENSOR", "FAULT", "MODE", "EXTRUDER", "METHOD"}
# A profile name may be any short text: only the long one is bad
NAME_VALUES = ["x" * 1000, ""]


def registered_commands() -> set:
    """Every G-code command name klippy_extras registers."""
    names = set()
    for path in (PROJECT / "klippy_extras").rglob("*.py"):
        text = path.read_text()
        names |= set(re.findall(r"register_(?:mux_)?command\(\s*'([A-Z0-9_]+)'",
                                text))
        # flow_sensor registers from a table: ('QUERY_FLOW_SENSOR', self.cmd_...
        names |= set(re.findall(r"\('([A-Z0-9_]+)',\s*self\.cmd_", text))
    return names


def cases(commands: dict):
    """(line, must_refuse) for every command, parameter and value."""
    for command, (base, params) in commands.items():
        traditional = re.fullmatch(r"[A-Z]\d+", command) is not None
        if not params:
            yield f"{command} FUZZ=nan", False     # ignored: nothing read
        for param in params:
            values = NAME_VALUES if param == "NAME" else VALUES
            for value in values:
                kept = " ".join(p for p in base.split()
                                if (p[0] if traditional else p.split("=")[0])
                                != param)
                if traditional:
                    text = f"{command} {param}{value} {kept}"
                    must = value in TRADITIONAL_REFUSED
                else:
                    text = f"{command} {kept} {param}={value}"
                    must = param in TEXT or param == "NAME" \
                        or value not in MAYBE_VALID
                yield " ".join(text.split()), must


def fuzz(build, venv, workdir: Path, config: Path, commands: dict):
    """Run every case; return (cases, states by line number, log lines by
    line number) where line i's log is what came between states i-1 and i."""
    all_cases = list(cases(commands))
    lines = ["FUZZ_STATE N=0"]
    for i, (line, _) in enumerate(all_cases, start=1):
        lines += [line, f"FUZZ_STATE N={i}"]
    _, test = write_test(workdir, "fuzz", "\n".join(lines) + "\n",
                         config=config)
    try:
        log = run_file(test, Harnessed(build), venv, workdir)
    except KlippyTestFailure as e:
        # judged below on what the log says (a shutdown ends klippy in error)
        log = (workdir / "run0.log").read_text(errors="replace") \
            + f"\nFUZZ_RUN_FAILED {str(e).splitlines()[0]}\n"
    states, segments, current = {}, {}, []
    for text in log.splitlines():
        found = re.match(r"FUZZ_STATE (\d+) (.*)$", text)
        if found:
            states[int(found.group(1))] = json.loads(found.group(2))
            segments[int(found.group(1))] = current
            current = []
        else:
            current.append(text)
    return all_cases, states, segments, log


class Harnessed:
    def __init__(self, build):
        self.tree, self.dict_dir = build.tree, build.dict_dir
        self.klippy = HERE / "fuzz_harness.py"


SHUTDOWN = ("Internal error", "Transition to shutdown", "Printer is shutdown",
            "Unhandled exception", "FUZZ_RUN_FAILED")


def judge(all_cases, states, segments, log):
    problems = []
    if len(states) != len(all_cases) + 1:
        problems.append(f"only {len(states)} of {len(all_cases) + 1} states"
                        " logged: klippy stopped early")
    for line in log.splitlines():
        if any(word in line for word in SHUTDOWN):
            problems.append(f"klippy shut down or failed: {line[:200]}")
            break
    for i, (line, must_refuse) in enumerate(all_cases, start=1):
        if i not in states:
            break
        if states[i]["shutdown"]:
            problems.append(f"{line[:120]}: shut the printer down")
            break
        if not must_refuse:
            continue
        refused = [t for t in segments[i] if "FUZZ_REFUSED" in t]
        if not refused:
            problems.append(f"{line[:120]}: accepted")
        if states[i] != states[i - 1]:
            changed = sorted(k for k in states[i]
                             if states[i][k] != states[i - 1][k])
            problems.append(f"{line[:120]}: refused but changed {changed}:"
                            f" {json.dumps({k: states[i][k] for k in changed})[:300]}")
    return problems


def test_the_fuzz_table_covers_every_command_flowloop_registers():
    assert registered_commands() == set(COMMANDS) | set(DELTA_COMMANDS)


@pytest.mark.parametrize("config, commands", [
    ("fuzz_gcode.cfg", COMMANDS), ("endstop_calibrate.cfg", DELTA_COMMANDS)],
    ids=["cartesian", "delta"])
def test_bad_values_never_shut_klippy_down_and_a_refusal_changes_nothing(
        config, commands, klipper_build, klippy_venv, short_tmp):
    all_cases, states, segments, log = fuzz(klipper_build, klippy_venv,
                                            short_tmp, HERE / config, commands)
    problems = judge(all_cases, states, segments, log)
    assert not problems, f"{len(problems)} problems:\n" + "\n".join(problems[:25])
