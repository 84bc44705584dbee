"""Slicer filament settings from a profile (flowloop.material.slicer) and
`flowloop profile export --format prusaslicer,orcaslicer`.

PrusaSlicer's .ini is checked by PrusaSlicer itself (Debian's prusa-slicer
slices a cube with it); OrcaSlicer's .json against keys of real OrcaSlicer
filament files (tests/data/slicer/README.md says which)."""

from __future__ import annotations

import json
import math
import re
import shutil
import subprocess
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flowloop import __version__
from flowloop.cli import main
from flowloop.errors import FlowloopError
from flowloop.material import profile as P
from flowloop.material import slicer
from tests.samples import make

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data" / "slicer"
DOC = ROOT / "docs" / "material_profiles.md"
PRUSA = shutil.which("prusa-slicer")


def herz(**kw) -> P.Profile:
    return P.profile_from_dict(make(**kw))


def run(capsys, *argv):
    code = main(["profile", *map(str, argv)])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture
def herz_file(tmp_path) -> Path:
    path = tmp_path / "herz-pla-red_80.json"
    path.write_bytes(P.encode_profile(herz()))
    return path


# --- the numbers ------------------------------------------------------------------

def test_the_numbers_of_the_worked_example():
    p = herz()
    n = slicer.slicer_numbers(p)          # recommended 210 degC, WP 0.5
    assert (n.temp_c, n.first_layer_temp_c) == (210, 210)
    assert n.max_volumetric_speed_mm3_s == 11.65   # 11.658: rounded down
    n = slicer.slicer_numbers(p, 230, 235)
    assert n.max_volumetric_speed_mm3_s == 14.57   # 14.578
    assert (n.temp_c, n.first_layer_temp_c, n.min_temp_c, n.max_temp_c) == \
        (230, 235, 190, 260)
    assert n.filament_diameter_mm == 1.75
    assert slicer.slicer_numbers(p, 230, working_point=0).max_volumetric_speed_mm3_s \
        == 13.05   # the real-print line: 0.146 * 230 - 20.5244 = 13.0556
    assert slicer.slicer_numbers(p, 230, working_point=1).max_volumetric_speed_mm3_s \
        == 16.10   # into air: 16.1007


def test_the_notes_name_the_profile_the_working_point_and_flowloop():
    n = slicer.slicer_numbers(herz(), 230, working_point=0.25)
    assert f"flowloop {__version__}" in n.notes
    assert '"herz-pla-red_80"' in n.notes and '"UM2-1"' in n.notes
    assert "working point 0.25" in n.notes and "at 230 degC" in n.notes


def test_a_name_with_letters_beyond_ascii_reads_as_written():
    n = slicer.slicer_numbers(herz(name="pla grün", identity={"printer": "Prüfer"}))
    assert '"pla grün"' in n.notes and '"Prüfer"' in n.notes
    assert '# profile "pla grün"' in slicer.prusaslicer_ini(n)
    assert "\\u00fc" not in slicer.prusaslicer_ini(n) + slicer.orcaslicer_json(n)


@pytest.mark.parametrize("temp", [189, 261, 189.9999, 500, -5])
def test_a_temperature_outside_the_bounds_is_refused(temp):
    with pytest.raises(FlowloopError, match=r"outside the profile's bounds 190\.\.260"):
        slicer.slicer_numbers(herz(), temp)
    with pytest.raises(FlowloopError, match="outside"):
        slicer.slicer_numbers(herz(), 210, temp)


@pytest.mark.parametrize("temp", [math.nan, math.inf, "215", True])
def test_a_temperature_that_is_not_a_number_is_refused(temp):
    with pytest.raises(FlowloopError):
        slicer.check_temp(herz(), temp)


def test_slicers_store_whole_degrees():
    with pytest.raises(FlowloopError, match="not a whole degree"):
        slicer.slicer_numbers(herz(), 215.5)
    # bounds that are not whole: the whole degrees within them
    p = herz(bounds=(190.4, 209.6, 259.7))
    n = slicer.slicer_numbers(p)
    assert (n.min_temp_c, n.temp_c, n.max_temp_c) == (191, 210, 259)
    p = herz(bounds=(190.2, 190.4, 190.6))
    with pytest.raises(FlowloopError, match="no whole degree"):
        slicer.slicer_numbers(p)


@pytest.mark.parametrize("wp", [-0.1, 1.01, math.nan])
def test_a_working_point_outside_0_1_is_refused(wp):
    with pytest.raises(FlowloopError, match="working point"):
        slicer.slicer_numbers(herz(), 210, working_point=wp)


def test_a_temperature_where_the_hotend_melts_nothing_is_refused():
    # the real-print line reaches 0 at 140.6 degC: a slicer would read 0 as
    # "no limit" (PrusaSlicer) or refuse it (OrcaSlicer)
    p = herz(bounds=(120.0, 210.0, 260.0))
    with pytest.raises(FlowloopError, match="melts no flow"):
        slicer.slicer_numbers(p, 130, working_point=0)
    assert slicer.slicer_numbers(p, 150, working_point=0).max_volumetric_speed_mm3_s \
        == 1.37


@settings(max_examples=200, deadline=None)
@given(lo=st.floats(100, 300), span=st.floats(0.05, 150), rec=st.floats(0, 1),
       temp=st.integers(50, 500), first=st.integers(50, 500), wp=st.floats(0, 1),
       slope=st.floats(0.01, 1.0))
def test_temperatures_stay_in_bounds_and_the_flow_is_never_above_the_line(
        lo, span, rec, temp, first, wp, slope):
    hi = lo + span
    p = herz(bounds=(lo, lo + rec * span, hi), air=(slope, 200.0, 10.0),
             real=(slope, 210.0, 9.0))
    for t, f in ((temp, first), (None, None)):
        try:
            n = slicer.slicer_numbers(p, t, f, wp)
        except FlowloopError as e:
            # refused only for one of these reasons
            reasons = []
            if math.ceil(lo) > math.floor(hi):
                reasons.append("no whole degree")
            if t is not None and not (lo <= t <= hi and lo <= f <= hi):
                reasons.append("outside the profile's bounds")
            if not reasons:
                chosen = t if t is not None else slicer.default_temp(p)
                assert P.profile_line(p, wp).flow_mm3_s(chosen) < 0.01 + 1e-9
                reasons.append("melts no flow")
            assert any(reason in str(e) for reason in reasons), (str(e), reasons)
            continue
        for value in (n.temp_c, n.first_layer_temp_c, n.min_temp_c, n.max_temp_c):
            assert lo <= value <= hi and value == int(value)
        line = P.profile_line(p, wp).flow_mm3_s(n.temp_c)
        # rounded down (what float noise makes 7.8999999999999995 is 7.9)
        assert line - 0.01 - 1e-9 <= n.max_volumetric_speed_mm3_s <= line + 1e-9
        assert n.max_volumetric_speed_mm3_s >= 0.01


# --- PrusaSlicer ------------------------------------------------------------------

def test_the_ini_is_key_equals_value_lines():
    text = slicer.prusaslicer_ini(slicer.slicer_numbers(herz(), 230, 235))
    settings_ = dict(line.split(" = ", 1) for line in text.splitlines()
                     if not line.startswith("#"))
    assert settings_ == {
        "filament_diameter": "1.75", "filament_max_volumetric_speed": "14.57",
        "filament_notes": settings_["filament_notes"],
        "first_layer_temperature": "235", "temperature": "230"}
    assert settings_["filament_notes"].startswith('"flowloop ')


@pytest.mark.parametrize("text, quoted", [
    ('a "b" c', r'"a \"b\" c"'), ("back\\slash", r'"back\\slash"'),
    ("two\nlines", r'"two\nlines"')])
def test_strings_are_quoted_as_prusaslicer_writes_them(text, quoted):
    assert slicer.c_string(text) == quoted


def _cube_stl(path: Path, size: float = 20.0) -> None:
    v = [(x, y, z) for x in (0, size) for y in (0, size) for z in (0, size)]
    faces = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1),
             (2, 3, 7), (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)]
    out = ["solid cube"]
    for face in faces:
        out += ["facet normal 0 0 0", " outer loop"]
        out += [f"  vertex {v[i][0]} {v[i][1]} {v[i][2]}" for i in face]
        out += [" endloop", "endfacet"]
    path.write_text("\n".join(out + ["endsolid cube"]) + "\n")


def _slice(tmp_path: Path, *inis: Path) -> str:
    stl, gcode = tmp_path / "cube.stl", tmp_path / (inis[-1].stem + ".gcode")
    if not stl.exists():
        _cube_stl(stl)
    loads = [arg for ini in inis for arg in ("--load", str(ini))]
    done = subprocess.run([PRUSA, *loads, "--export-gcode", "-o", str(gcode),
                           str(stl)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    return gcode.read_text()


def _max_flow(gcode: str, diameter: float) -> float:
    """The most volumetric flow (mm^3/s) of the G-code's extruding moves."""
    area = math.pi * diameter ** 2 / 4
    x = y = e = 0.0
    feed = 0.0
    relative_e = False
    most = 0.0
    for line in gcode.splitlines():
        line = line.split(";", 1)[0].strip()
        if not line:
            continue
        word, *params = line.split()
        values = {p[0]: float(p[1:]) for p in params if p[0] in "XYEF"}
        if word == "M83":
            relative_e = True
        elif word == "M82":
            relative_e = False
        elif word == "G92" and "E" in values:
            e = values["E"]
        elif word in ("G0", "G1"):
            feed = values.get("F", feed)
            nx, ny = values.get("X", x), values.get("Y", y)
            de = 0.0
            if "E" in values:
                de = values["E"] if relative_e else values["E"] - e
                e = e + de if relative_e else values["E"]
            dist = math.hypot(nx - x, ny - y)
            if de > 0 and dist > 1.0 and feed > 0:
                most = max(most, de * area / (dist / (feed / 60)))
            x, y = nx, ny
    return most


@pytest.mark.skipif(PRUSA is None, reason="prusa-slicer is not installed (Debian: "
                                           "apt-get install prusa-slicer)")
def test_prusaslicer_loads_the_ini_and_slices_with_its_numbers(tmp_path):
    # a name with quotes: the note must come back as it was written
    p = herz(name='herz "red" PLA', bounds=(180.0, 210.0, 260.0))
    numbers = slicer.slicer_numbers(p, 190, 200, working_point=0)
    assert numbers.max_volumetric_speed_mm3_s == 7.21
    ini = tmp_path / "herz.ini"
    ini.write_text(slicer.prusaslicer_ini(numbers))
    gcode = _slice(tmp_path, ini)
    # its config comments: what PrusaSlicer read, as it writes it back
    config = dict(m.groups() for m in re.finditer(r"^; (\w+) = (.*)$", gcode, re.M))
    assert config["temperature"] == "190"
    assert config["first_layer_temperature"] == "200"
    assert config["filament_max_volumetric_speed"] == "7.21"
    assert config["filament_diameter"] == "1.75"
    assert config["filament_notes"] == slicer.c_string(numbers.notes)
    # and it printed with them: the first layer at 200, the rest at 190
    temps = re.findall(r"^M10[49] S(\d+)", gcode, re.M)
    assert temps[:2] == ["200", "200"] and "190" in temps
    # the limit holds: no move extrudes faster than 7.21 mm^3/s; without it
    # (0: no limit) the same cube does
    assert _max_flow(gcode, 1.75) <= 7.21 * 1.02
    unlimited = tmp_path / "unlimited.ini"
    unlimited.write_text(ini.read_text().replace(
        "filament_max_volumetric_speed = 7.21", "filament_max_volumetric_speed = 0"))
    assert _max_flow(_slice(tmp_path, unlimited), 1.75) > 7.21 * 1.2


@pytest.mark.skipif(PRUSA is None, reason="prusa-slicer is not installed (Debian: "
                                           "apt-get install prusa-slicer)")
def test_the_ini_loaded_last_overrides_a_farms_own_settings(tmp_path):
    # a farm's printer and print settings first, flowloop's filament last
    farm = tmp_path / "farm.ini"
    farm.write_text("layer_height = 0.2\ntemperature = 250\n"
                    "first_layer_temperature = 255\n"
                    "filament_max_volumetric_speed = 20\n")
    ini = tmp_path / "herz.ini"
    ini.write_text(slicer.prusaslicer_ini(slicer.slicer_numbers(herz(), 230, 235)))
    gcode = _slice(tmp_path, farm, ini)
    config = dict(m.groups() for m in re.finditer(r"^; (\w+) = (.*)$", gcode, re.M))
    assert config["layer_height"] == "0.2"            # the farm's
    assert (config["temperature"], config["first_layer_temperature"],
            config["filament_max_volumetric_speed"]) == ("230", "235", "14.57")


# --- OrcaSlicer -------------------------------------------------------------------

def _orca_reference():
    """{key: the JSON type of its value} over the real OrcaSlicer excerpts."""
    excerpts = json.loads((DATA / "orcaslicer_filament_excerpt.json").read_text())
    kinds = {}
    for source, preset in excerpts.items():
        for key, value in preset.items():
            kind = ("list of str" if isinstance(value, list)
                    and all(isinstance(v, str) for v in value)
                    else type(value).__name__)
            assert kinds.setdefault(key, kind) == kind, (source, key)
    # OrcaSlicer's PrintConfig.cpp: filament_notes is coStrings
    kinds["filament_notes"] = "list of str"
    return excerpts, kinds


def test_the_orcaslicer_preset_has_the_keys_and_types_of_real_ones():
    excerpts, kinds = _orca_reference()
    preset = json.loads(slicer.orcaslicer_json(
        slicer.slicer_numbers(herz(), 230, 235), inherits="Generic PLA"))
    for key, value in preset.items():
        assert key in kinds, f"{key}: in no real OrcaSlicer filament file"
        kind = ("list of str" if isinstance(value, list)
                and all(isinstance(v, str) for v in value) else type(value).__name__)
        assert kind == kinds[key], key
        if kind == "list of str":
            assert len(value) == 1, key   # one extruder's value
    assert preset["type"] == "filament" and preset["from"] == "User"
    assert preset["inherits"] == "Generic PLA"
    assert preset["name"] == "herz-pla-red_80"
    assert preset["filament_settings_id"] == ["herz-pla-red_80"]
    assert preset["nozzle_temperature"] == ["230"]
    assert preset["nozzle_temperature_initial_layer"] == ["235"]
    assert preset["nozzle_temperature_range_low"] == ["190"]
    assert preset["nozzle_temperature_range_high"] == ["260"]
    assert preset["filament_max_volumetric_speed"] == ["14.57"]
    assert preset["filament_diameter"] == ["1.75"]
    # the numbers read as the real files' do: temperatures whole (coInts),
    # the rest decimal numbers
    for key in ("nozzle_temperature", "nozzle_temperature_initial_layer",
                "nozzle_temperature_range_low", "nozzle_temperature_range_high"):
        for real in (p[key] for p in excerpts.values() if key in p):
            assert real[0].isdigit()
        assert preset[key][0].isdigit()
    for key in ("filament_max_volumetric_speed", "filament_diameter"):
        assert float(preset[key][0]) > 0
    # a user preset as OrcaSlicer exports one has these; its import
    # (PresetBundle::import_json_presets) skips a file without a version that
    # parses, and takes filament_settings_id for "a filament preset"
    user = excerpts["resources/profiles/Custom/filament/XFILAMENTS PLA.json"]
    assert {"from", "inherits", "name", "filament_settings_id", "version"} \
        <= set(preset)
    assert user["from"] == preset["from"]
    shape = r"\d+\.\d+\.\d+\.\d+"
    assert re.fullmatch(shape, user["version"]) and re.fullmatch(shape,
                                                                 preset["version"])


def test_orcaslicer_refuses_more_than_its_most():
    n = slicer.slicer_numbers(herz(), 230)._replace(max_volumetric_speed_mm3_s=250.0)
    with pytest.raises(FlowloopError, match="OrcaSlicer's most"):
        slicer.orcaslicer_preset(n)


@pytest.mark.parametrize("name, fmt", [("PrusaSlicer", "prusaslicer"),
                                       ("superslicer", "prusaslicer"),
                                       (" OrcaSlicer ", "orcaslicer")])
def test_format_names(name, fmt):
    assert slicer.check_format(name) == fmt


def test_an_unknown_format_is_refused():
    with pytest.raises(FlowloopError, match="unknown slicer format 'cura'"):
        slicer.export_text(herz(), "cura")


# --- the command ------------------------------------------------------------------

def test_export_writes_each_format_to_the_output_dir(herz_file, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    code, text, err = run(capsys, "export", herz_file, "--format",
                          "prusaslicer,orcaslicer,ddprint", "--temp", "230",
                          "--first-layer-temp", "235", "--output-dir", out)
    assert code == 0, err
    names = sorted(p.name for p in out.iterdir())
    assert names == ["herz-pla-red_80.ddprint.json", "herz-pla-red_80.ini",
                     "herz-pla-red_80.orcaslicer.json"]
    assert text.count("wrote ") == 3
    p = P.decode_profile(herz_file.read_bytes())
    assert (out / "herz-pla-red_80.ini").read_text() == \
        slicer.export_text(p, "prusaslicer", 230, 235)
    assert (out / "herz-pla-red_80.orcaslicer.json").read_text() == \
        slicer.export_text(p, "orcaslicer", 230, 235)


def test_one_slicer_format_goes_to_stdout_or_to_o(herz_file, tmp_path, capsys):
    code, text, _ = run(capsys, "export", herz_file, "-f", "orcaslicer", "--wp", "1",
                        "--inherits", "Generic PLA")
    assert code == 0
    preset = json.loads(text)
    assert preset["filament_max_volumetric_speed"] == ["13.18"]  # 210 degC, into air
    assert preset["inherits"] == "Generic PLA"
    out = tmp_path / "f.ini"
    code, _, _ = run(capsys, "export", herz_file, "-f", "superslicer", "-o", out)
    assert code == 0 and "filament_max_volumetric_speed = 11.65" in out.read_text()


@pytest.mark.parametrize("argv, message", [
    (["-f", "cura", "-o", "OUT"], "--format: unknown format 'cura'"),
    (["-f", "prusaslicer", "--temp", "300", "-o", "OUT"],
     "--temp: 300 degC is outside the profile's bounds 190..260 degC"),
    (["-f", "prusaslicer", "--first-layer-temp", "185", "-o", "OUT"],
     "--first-layer-temp: 185 degC is outside"),
    (["-f", "prusaslicer", "--temp", "215.5", "-o", "OUT"], "--temp: 215.5 degC is "
                                                             "not a whole degree"),
    (["-f", "prusaslicer", "--temp", "hot", "-o", "OUT"], "--temp: not a number"),
    (["-f", "orcaslicer", "--wp", "1.5", "-o", "OUT"], "--wp: got '1.5'"),
    (["-f", "orcaslicer", "--wp", "-0.1", "-o", "OUT"], "--wp: got '-0.1'"),
    (["--temp", "230", "-o", "OUT"], "--temp: only for a slicer format"),
    (["-f", "prusaslicer", "--inherits", "x", "-o", "OUT"],
     "--inherits: only for --format orcaslicer"),
    (["-f", "prusaslicer,orcaslicer", "-o", "OUT"], "give --output-dir"),
    (["-f", "prusaslicer,orcaslicer"], "give --output-dir"),
    (["-f", "prusaslicer", "-o", "OUT", "-d", "."], "-o and --output-dir: give one"),
])
def test_bad_input_is_one_line_and_writes_nothing(argv, message, herz_file, tmp_path,
                                                  capsys):
    out = tmp_path / "out"
    out.mkdir()
    before = sorted(tmp_path.rglob("*"))
    argv = [str(out / "f") if a == "OUT" else a for a in argv]
    code, text, err = run(capsys, "export", herz_file, *argv)
    assert code == 2 and text == ""
    assert err.count("\n") == 1 and message in err, err
    assert sorted(tmp_path.rglob("*")) == before


@pytest.mark.parametrize("fmt", ["ddprint", "prusaslicer", "orcaslicer"])
def test_an_existing_file_is_overwritten_only_with_force(fmt, herz_file, tmp_path,
                                                         capsys):
    out = tmp_path / "mine.txt"
    out.write_text("the user's own file\n")
    code, text, err = run(capsys, "export", herz_file, "-f", fmt, "-o", out)
    assert code == 2 and err.count("\n") == 1
    assert f"-o: {out} exists: not overwritten (--force overwrites it)" in err
    assert out.read_text() == "the user's own file\n"
    code, _, err = run(capsys, "export", herz_file, "-f", fmt, "-o", out, "--force")
    assert code == 0, err
    assert out.read_text() != "the user's own file\n"


def test_nothing_is_written_when_one_of_several_outputs_exists(herz_file, tmp_path,
                                                               capsys):
    (tmp_path / "herz-pla-red_80.orcaslicer.json").write_text("{}")
    code, _, err = run(capsys, "export", herz_file, "-f", "prusaslicer,orcaslicer",
                       "-d", tmp_path)
    assert code == 2 and "orcaslicer.json exists" in err
    assert not (tmp_path / "herz-pla-red_80.ini").exists()


def test_force_never_overwrites_the_profile_itself(herz_file, capsys):
    before = herz_file.read_bytes()
    code, _, err = run(capsys, "export", herz_file, "-f", "orcaslicer", "-o",
                       herz_file, "--force")
    assert code == 2 and "would overwrite FILE" in err
    assert herz_file.read_bytes() == before


# --- the docs' worked example -----------------------------------------------------

def _doc_section() -> str:
    text = DOC.read_text()
    section = text.split("## Exports to slicers", 1)[1]
    return section.split("\n## ", 1)[0]


def _block_after(section: str, command: str) -> list:
    lines = section.splitlines()
    i = lines.index(f"$ {command}")
    out = []
    for line in lines[i + 1:]:
        if line.startswith(("$ ", "```")):
            break
        out.append(line)
    return out


def test_the_docs_worked_example_is_what_runs(herz_file, tmp_path, capsys,
                                              monkeypatch):
    section = _doc_section()
    command = next(line[2:] for line in section.splitlines()
                   if line.startswith("$ flowloop profile export"))
    monkeypatch.chdir(herz_file.parent)
    code, text, err = run(capsys, *command.split()[2:])
    assert code == 0, err
    assert text.splitlines() == _block_after(section, command)

    def versionless(lines):
        return [re.sub(r"flowloop \d+\.\d+\S*?(?=[: ])", "flowloop VERSION", line)
                for line in lines]
    for name in ("herz-pla-red_80.ini", "herz-pla-red_80.orcaslicer.json"):
        written = (herz_file.parent / name).read_text().splitlines()
        assert versionless(_block_after(section, f"cat {name}")) == \
            versionless(written), name
    # the figures in the prose
    for figure in ("0.146 * 230 - 19.0018 = 14.578", "14.57 mm³/s", "11.65 mm³/s"):
        assert figure in section, figure
    assert slicer.slicer_numbers(herz()).max_volumetric_speed_mm3_s == 11.65
