"""The flowloop command: --help everywhere, one-line errors."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from flowloop import __version__, cli


def subcommands():
    parser = cli.build_parser()
    action = next(a for a in parser._actions
                  if isinstance(a, argparse._SubParsersAction))
    return sorted(action.choices)


@pytest.mark.parametrize("name", subcommands())
def test_every_subcommand_has_help(name, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main([name, "--help"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith("usage: flowloop " + name)


def test_the_command_table_names_the_module_of_every_command():
    registered = {}
    for module in cli.COMMAND_MODULES:
        parser = cli.ArgumentParser(prog="flowloop")
        sub = parser.add_subparsers()
        __import__(module, fromlist=["register"]).register(sub)
        registered.update(dict.fromkeys(sub.choices, module))
    assert registered == cli.COMMANDS


def test_a_command_imports_only_its_own_module():
    # Moonraker starts `flowloop annotate` per upload: the other commands'
    # imports (jinja2, the sensor drivers, ...) are start-up it need not pay
    code = ("import sys\nfrom flowloop import cli\n"
            "try:\n    cli.main(['annotate', '--help'])\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in sys.modules if m.startswith('flowloop.cli.')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True,
                         text=True, check=True).stdout.strip().splitlines()[-1]
    imported = set(json.loads(out.replace("'", '"')))
    assert imported & set(cli.COMMAND_MODULES) == {"flowloop.cli.annotate"}


def test_the_console_script_is_installed_and_reports_its_version():
    exe = str(Path(sys.executable).parent / "flowloop")
    out = subprocess.run([exe, "--version"], capture_output=True, text=True)
    assert out.stdout.strip() == f"flowloop {__version__}"


def test_info_names_an_unreachable_moonraker_in_one_line(capsys):
    assert cli.main(["info", "--moonraker", "http://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("flowloop info: error: http://127.0.0.1:9: cannot reach")
    assert "\n" not in err


# --- negative numbers are typed as they read --------------------------------------

DELTA_CFG = Path(__file__).parents[1] / "klippy" / "endstop_calibrate.cfg"
PROBES = ("0,0,0.1", "-86.6,-50,0.3", "86.6,-50,-0.2", "0,100,0.0")


def value_options():
    """(command words, option) for every option of every command that takes a value."""
    def walk(parser, words):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    yield from walk(sub, words + [name])
            elif action.option_strings and action.nargs != 0 and action.choices is None:
                yield words, action.option_strings[-1]
    return list(walk(cli.build_parser(), []))


def test_no_option_mistakes_a_signed_list_for_an_option(capsys):
    # Whatever else is wrong with the command line, the value is the option's.
    options = value_options()
    assert (["delta-endstops"], "--probe") in options
    offenders = []
    for words, option in options:
        with pytest.raises(SystemExit):
            cli.build_parser().parse_args(words + [option, "-86.6,-5e1,0.3", "-h"])
        if "expected one argument" in capsys.readouterr().err:
            offenders.append(" ".join(words + [option]))
    assert offenders == []


def test_a_probe_near_tower_a_is_typed_as_it_reads(capsys):
    def run(args):
        code = cli.main(["delta-endstops", "--printer-cfg", str(DELTA_CFG), *args])
        out, err = capsys.readouterr()
        assert code == 0, err
        return out

    natural = run([w for p in PROBES for w in ("--probe", p)] + ["--z-offset", "-0.1"])
    with_equals = run([f"--probe={p}" for p in PROBES] + ["--z-offset=-0.1"])
    assert natural == with_equals
    assert "[stepper_a] position_endstop:" in natural


def test_a_negative_reading_gets_the_calibrations_own_one_line_error(capsys):
    code = cli.main(["ab-calibrate", "--rotation-distance-a", "40",
                     "--rotation-distance-b", "40", "--a1", "-13.9,13.95",
                     "--a2", "153.9", "--b1", "13.9", "--b2", "153.9"])
    err = capsys.readouterr().err
    assert code == 2
    assert err == "flowloop ab-calibrate: error: A1: reading -13.9 must be positive\n"


def test_pylons_take_a_centre_written_with_an_exponent(tmp_path, capsys):
    out = tmp_path / "p.gcode"
    assert cli.main(["ab-pylons", "-o", str(out), "--bed-x", "300", "--bed-y", "300",
                     "--centre-x", "1.5e2", "--centre-y", "-1e1"]) == 2
    # The value reached the pylon check (a centre at y = -10 does not fit).
    assert "does not fit" in capsys.readouterr().err


# --- an output never overwrites an input ------------------------------------------

DATA = Path(__file__).resolve().parents[1] / "data" / "gcode"
PROFILE_JSON = json.dumps({
    "identity": {"name": "weak", "nozzle_diameter_mm": 0.4},
    "lines": {"into_air": {"slope_mm3_s_per_c": 0.1, "temp_c": 200.0,
                           "flow_mm3_s": 4.5},
              "real_print": {"slope_mm3_s_per_c": 0.1, "temp_c": 200.0,
                             "flow_mm3_s": 3.5}},
    "bounds": {"min_temp_c": 190.0, "recommended_temp_c": 200.0, "max_temp_c": 240.0},
    "provenance": {"method": "manual"}})


@pytest.fixture
def slicer_files(tmp_path, monkeypatch):
    """f.gcode (a slicer's file) and p.json (a profile), in the current folder."""
    monkeypatch.chdir(tmp_path)
    gcode = tmp_path / "f.gcode"
    gcode.write_bytes((DATA / "block_layers_1_2.gcode").read_bytes())
    (tmp_path / "p.json").write_text(PROFILE_JSON)
    return gcode


def other_spelling(path: Path, how: str) -> str:
    if how == "dot":
        return f"./{path.name}"
    if how == "symlink":
        link = path.with_name("link.gcode")
        link.symlink_to(path.name)
        return str(link)
    if how == "hardlink":
        link = path.with_name("hard.gcode")
        os.link(path, link)
        return str(link)
    return str(path.resolve())


@pytest.mark.parametrize("how", ["dot", "symlink", "hardlink", "absolute"])
def test_baking_onto_the_slicers_own_file_is_refused_and_leaves_it_alone(
        slicer_files, capsys, how):
    before = slicer_files.read_bytes()
    out = other_spelling(slicer_files, how)
    assert cli.main(["annotate", "f.gcode", "-o", out, "--bake", "p.json"]) == 2
    err = capsys.readouterr().err
    assert err == (f"flowloop annotate: error: -o {Path(out)} would overwrite"
                   f" IN.gcode f.gcode: write elsewhere\n")
    assert slicer_files.read_bytes() == before
    # and baking elsewhere still works: the slicer's file is there
    assert cli.main(["annotate", "f.gcode", "-o", "baked.gcode", "--bake",
                     "p.json"]) == 0


@pytest.mark.parametrize("args, named", [
    (["-o", "p.json", "--bake", "p.json"], "-o p.json would overwrite --bake p.json"),
    (["-o", "b.gcode", "--bake", "p.json", "--plot", "f.gcode"],
     "--plot f.gcode would overwrite IN.gcode f.gcode"),
    (["-o", "b.gcode", "--bake", "p.json", "--plot", "b.gcode"],
     "--plot b.gcode would overwrite -o b.gcode"),
    (["-o", "printer.cfg", "--printer-cfg", "printer.cfg"],
     "-o printer.cfg would overwrite --printer-cfg printer.cfg"),
])
def test_no_output_of_annotate_overwrites_one_of_its_inputs(slicer_files, capsys,
                                                            args, named):
    (slicer_files.parent / "printer.cfg").write_text("[printer]\nmax_velocity: 300\n")
    before = {p.name: p.read_bytes() for p in slicer_files.parent.iterdir()}
    assert cli.main(["annotate", "f.gcode", *args]) == 2
    assert named in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in slicer_files.parent.iterdir()} == before


def test_annotating_in_place_is_still_asked_for_with_the_same_path(slicer_files):
    assert cli.main(["annotate", "f.gcode", "-o", "./f.gcode"]) == 0
    assert b"AUTOTEMP_FLOW" in slicer_files.read_bytes()


# --- errors that say what is wrong ---------------------------------------------------

@pytest.mark.parametrize("typo", [["--leed", "30"], ["--leed=30"]])
def test_an_unknown_option_names_its_subcommand_and_the_option_meant(typo, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["annotate", *typo, "f.gcode"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: flowloop annotate ")
    assert err.endswith("flowloop annotate: error: unknown option --leed"
                        " (did you mean --lead?)\n")


def test_an_unknown_option_of_an_action_names_the_action(capsys):
    with pytest.raises(SystemExit):
        cli.main(["profile", "show", "p.json", "--jsn"])
    assert capsys.readouterr().err.endswith(
        "flowloop profile show: error: unknown option --jsn (did you mean --json?)\n")


def test_a_bad_heater_power_names_that_option_alone(slicer_files, capsys):
    assert cli.main(["annotate", "f.gcode", "-o", "b.gcode", "--bake", "p.json",
                     "--heater-power", "-5"]) == 2
    assert capsys.readouterr().err == (
        "flowloop annotate: error: --heater-power must be above 0, not -5.0\n")


def test_an_empty_gcode_file_is_annotated_with_a_warning(tmp_path, capsys):
    empty = tmp_path / "empty.gcode"
    empty.write_bytes(b"")
    assert cli.main(["annotate", str(empty)]) == 0
    err = capsys.readouterr().err
    assert err == (f"flowloop annotate: warning: {empty}: no move extrudes: nothing"
                   f" to announce\n")


def test_a_decimal_comma_reading_is_refused_not_read_as_two(capsys):
    code = cli.main(["ab-calibrate", "--rotation-distance-a", "40",
                     "--rotation-distance-b", "40", "--a1", "9,9",
                     "--a2", "153.9", "--b1", "13.9", "--b2", "153.9"])
    err = capsys.readouterr().err
    assert code == 2
    assert err == ("flowloop ab-calibrate: error: A1: '9,9' has a decimal comma:"
                   " write 9.9, or separate readings with spaces (or dots:"
                   " 9.0,9.0)\n")


def test_a_baked_empty_file_gets_the_same_warning(slicer_files, capsys):
    slicer_files.write_bytes(b"")
    assert cli.main(["annotate", "f.gcode", "-o", "b.gcode", "--bake", "p.json"]) == 0
    assert capsys.readouterr().err == ("flowloop annotate: warning: f.gcode: no move"
                                       " extrudes: nothing to announce\n")


def test_a_z_offset_with_a_decimal_comma_says_so(capsys):
    assert cli.main(["delta-endstops", "--printer-cfg", str(DELTA_CFG),
                     *[w for p in PROBES for w in ("--probe", p)],
                     "--z-offset", "0,1"]) == 2
    assert "--z-offset: '0,1' has a decimal comma: write 0.1" in capsys.readouterr().err


def test_an_empty_history_file_is_a_history_of_no_rounds(tmp_path, capsys):
    history = tmp_path / "h.json"
    history.write_text("")
    assert cli.main(["ab-calibrate", "--rotation-distance-a", "40",
                     "--rotation-distance-b", "40", "--a1", "9.93", "--a2", "149.9",
                     "--b1", "9.95", "--b2", "149.9", "--history", str(history)]) == 0
    assert len(json.loads(history.read_text())) == 1


def test_annotate_as_a_program_skips_what_it_does_not_need_and_ends_cleanly(tmp_path):
    # as Moonraker runs it per upload: start-up without msgspec (profiles),
    # klipper_config (--printer-cfg) or the other commands; the program's
    # own exit (os._exit after flushing) leaves the file written and says so
    source = Path(__file__).resolve().parents[1] / "data" / "gcode"
    gcode = tmp_path / "part.gcode"
    gcode.write_bytes((source / "block_layers_1_2.gcode").read_bytes())
    done = subprocess.run([sys.executable, "-X", "importtime", "-m", "flowloop",
                           "annotate", str(gcode)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    imported = {line.rsplit("|", 1)[-1].strip() for line in done.stderr.splitlines()
                if line.startswith("import time:")}
    assert "flowloop.gcode.annotate" in imported
    assert not imported & {"msgspec", "flowloop.material.profile",
                           "flowloop.host.klipper_config"}
    assert done.stdout.strip()            # its summary line
    from flowloop.gcode.annotate import is_annotated
    assert is_annotated(gcode.read_bytes()[:65536])
    # a refused file: one line, exit 2, nothing written
    missing = tmp_path / "none.gcode"
    refused = subprocess.run([sys.executable, "-m", "flowloop", "annotate",
                              str(missing)], capture_output=True, text=True)
    assert refused.returncode == 2
    assert len(refused.stderr.strip().splitlines()) == 1 and not missing.exists()
