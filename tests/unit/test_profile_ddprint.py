"""ddPrint material files: import of the whole public repository, export,
round trips."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from flowloop.errors import FlowloopError
from flowloop.material import ddprint
from flowloop.material import profile as P
from tests.samples import MAT, make


def flatten_numbers(data, prefix=""):
    """{"properties_80.Ktemp": 0.146, ...}: every number of a ddPrint dict."""
    out = {}
    for key, value in data.items():
        if isinstance(value, dict):
            out.update(flatten_numbers(value, f"{prefix}{key}."))
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            out[f"{prefix}{key}"] = value
    return out


UM2 = sorted((MAT / "UM2-1").glob("*.json"))
EVERY_FILE = sorted(MAT.rglob("*.json"))
INTO_AIR_LOWER = "the real-print line lies above the into-air line"


def test_the_four_um2_profiles_are_there():
    assert [p.name for p in UM2] == ["herz-pla-red.json", "herz_petg_white.json",
                                     "kaisertech_pla_white.json",
                                     "noname_pla_blue.json"]


# Every material file of ddPrint's public repository (tests/data): the
# profiles it gives, the problems that must be named, and which profiles get
# the plausibility warning (real-print line above the into-air line).
EXPECTED = {
    "Anycubic_i3m-1/kaisertech_pla_white.json": (["kaisertech_pla_white_40"], []),
    "JP-1/3d-print-filament_nylon_natural_N17528181109H5.json": (
        ["3d-print-filament_nylon_natural_N17528181109H5_80"], []),
    "JP-1/biofila_platec.json": (["biofila_platec_80"], []),
    "JP-1/das-filament_pla_grau.json": (["das-filament_pla_grau_80"], []),
    "JP-1/esun_petg_solid-white_6-922572-264090.json": (
        ["esun_petg_solid-white_6-922572-264090_80"], []),
    "JP-1/herz_petg-black-5800070.json": (["herz_petg-black-5800070_80"], []),
    "JP-1/kaiser-pla-grey.json": (["kaiser-pla-grey_80"], []),
    "JP-1/taulman_nylon-230-black_688295584315.json": (
        ["taulman_nylon-230-black_688295584315_80"], []),
    "JP-1/zaper-petg-silver-1807201H3D0182.json": (
        ["zaper-petg-silver-1807201H3D0182_80"], []),
    "UM2-1/herz-pla-red.json": (["herz-pla-red_80"], []),
    "UM2-1/herz_petg_white.json": (["herz_petg_white_40"], []),
    "UM2-1/kaisertech_pla_white.json": (["kaisertech_pla_white_80"], []),
    "UM2-1/noname_pla_blue.json": (["noname_pla_blue_80"], []),
    "pla.json": (["pla_40", "pla_80"], []),
    "petg.json": (["petg_40", "petg_80"], []),
    # ddPrint's placeholders ("XXX copied from petg"): one line, no real print
    "nylon.json": (["nylon_80"], ["properties_40: no real-print point"]),
    "tpu_tpe.json": (["tpu_tpe_80"], ["properties_40: no real-print point"]),
}
WARNED = {"biofila_platec_80", "kaiser-pla-grey_80",
          "taulman_nylon-230-black_688295584315_80", "petg_40"}


def imported_profiles():
    return ddprint.import_paths(EVERY_FILE)[0]


@pytest.mark.parametrize("rel", sorted(EXPECTED))
def test_every_file_of_the_repository_imports_or_names_its_problem(rel):
    names, problems = EXPECTED[rel]
    result = ddprint.import_file(MAT / rel)
    assert [p.identity.name for p in result.profiles] == names
    assert len(result.problems) == len(problems)
    for got, want in zip(result.problems, problems):
        assert want in got and Path(rel).name in got


def test_a_file_without_measured_lines_is_refused_with_the_reason():
    with pytest.raises(FlowloopError, match=r"abs.json: no properties_NN"):
        ddprint.import_file(MAT / "abs.json")


def test_all_files_of_the_repository_are_covered():
    found = {str(p.relative_to(MAT)) for p in EVERY_FILE}
    assert found == set(EXPECTED) | {"abs.json"}
    assert len(found) == 18


def test_a_real_print_line_above_into_air_is_imported_and_warned_not_refused():
    profiles = imported_profiles()
    assert len(profiles) == 19
    warned = {p.identity.name for p in profiles if P.line_warnings(p)}
    assert warned == WARNED
    for p in profiles:
        for warning in P.line_warnings(p):
            assert INTO_AIR_LOWER in warning
            for wp in (0.0, 0.5):  # held at the into-air line, the lower one
                assert P.flow_at(p, 230.0, wp) == pytest.approx(
                    p.lines.into_air.line().flow_mm3_s(230.0))


def test_a_file_is_matched_to_a_generic_base_a_word_begins_with():
    assert ddprint.find_generic_base(MAT / "JP-1/biofila_platec.json") == \
        MAT / "pla.json"
    assert ddprint.find_generic_base(MAT / "JP-1/kaiser-pla-grey.json") == \
        MAT / "pla.json"


def test_herz_pla_red_maps_to_the_schema_with_its_generic_base():
    (p,) = ddprint.import_file(MAT / "UM2-1/herz-pla-red.json").profiles
    assert p.identity.printer == "UM2-1" and p.identity.nozzle_diameter_mm == 0.8
    assert p.identity.filament_type == "PLA" and p.identity.filament_diameter_mm == 1.75
    assert p.lines.into_air == P.FlowLine(slope_mm3_s_per_c=0.146, temp_c=171.6312,
                                          flow_mm3_s=7.5789)
    assert p.lines.real_print == P.FlowLine(slope_mm3_s_per_c=0.146, temp_c=210.0,
                                            flow_mm3_s=10.1356)
    assert p.lines.into_air_power == P.PowerLine(slope_mm3_s_per_pwm=0.1472,
                                                 pwm=90.0, flow_mm3_s=7.5789)
    assert p.lines.real_print_power.pwm == 132.4
    assert (p.bounds.min_temp_c, p.bounds.recommended_temp_c,
            p.bounds.max_temp_c) == (190, 210, 260)  # from pla.json
    assert p.ddprint.nozzle == {"version": 5, "slippage": 0.1}
    assert p.ddprint.top["bedTemp"] == 65
    assert p.provenance.method == "ddprint_import"
    assert "UM2-1/herz-pla-red.json + pla.json" == p.provenance.source


def numbers_of_one_nozzle(path, nozzle_key):
    """Every number a ddPrint file (merged over its generic base) holds for
    one nozzle: the top-level ones and that nozzle's."""
    data = ddprint.read_file(path)
    if ddprint.is_specific(data):
        merged = ddprint.read_file(ddprint.find_generic_base(path))
        merged.update(data)
        data = merged
    return {k: v for k, v in flatten_numbers(data).items()
            if not k.startswith("properties_") or k.startswith(nozzle_key + ".")}


@pytest.mark.parametrize("path", [f for f in EVERY_FILE if f.name != "abs.json"],
                         ids=lambda p: str(p.relative_to(MAT)))
def test_every_imported_profile_round_trips_with_every_number_kept(path):
    profiles = ddprint.import_file(path).profiles
    assert profiles
    for profile in profiles:
        key = ddprint.properties_key(profile.identity.nozzle_diameter_mm)
        want = numbers_of_one_nozzle(path, key)
        exported = ddprint.parse_text(ddprint.export_text(profile))
        got = flatten_numbers(exported)
        assert {k: got.get(k) for k in want} == want
        assert P.decode_profile(P.encode_profile(profile)) == profile
        # ...and the exported file imports to the same profile
        ident = profile.identity
        again = ddprint.to_profile(
            exported, ident.nozzle_diameter_mm, name=ident.name,
            printer=ident.printer, filament_name=ident.filament_name,
            filament_type=ident.filament_type, source=profile.provenance.source)
        assert again == profile


def test_comments_and_comment_strings_are_dropped():
    text = """{
      # a comment line
      "version": 5,
      "material_diameter": 1.75,
      "hotendBaseTemp": 190, "hotendGoodTemp": 210, "hotendMaxTemp": 260,
      "properties_40": {
        "# measure 1:",
        "Ktemp": 0.1, "P0temp": 205.0, "FR0pwm": 2.5,
          "# measure 2",
        "P0tempPrint": 215.0, "FR0pwmPrint": 2
      }
    }"""
    data = ddprint.parse_text(text)
    assert data["properties_40"] == {"Ktemp": 0.1, "P0temp": 205.0, "FR0pwm": 2.5,
                                     "P0tempPrint": 215.0, "FR0pwmPrint": 2}
    p = ddprint.to_profile(data, 0.4, name="x")
    assert p.lines.into_air_power is None  # no Kpwm: no power lines


def test_a_broken_file_names_the_line():
    with pytest.raises(FlowloopError, match=r"bad.json: not a ddPrint file: line 3"):
        ddprint.parse_text('{\n "a": 1,\n "b" 2\n}', "bad.json")


def test_a_printer_file_without_a_base_asks_for_one(tmp_path):
    lone = tmp_path / "printer" / "mystery.json"
    lone.parent.mkdir()
    lone.write_text('{"properties_40": {"Ktemp": 0.1}}')
    with pytest.raises(FlowloopError, match="--base FILE"):
        ddprint.import_file(lone)


def test_nozzle_filter_and_missing_nozzle():
    assert [p.identity.name for p in
            ddprint.import_file(MAT / "pla.json", nozzle_mm=0.4).profiles] == ["pla_40"]
    with pytest.raises(FlowloopError, match=r"no profile for nozzle 0.6 mm \(has 0.4"):
        ddprint.import_file(MAT / "pla.json", nozzle_mm=0.6)


def test_an_explicit_base_and_printer_are_used():
    (p,) = ddprint.import_file(MAT / "UM2-1/herz_petg_white.json",
                               base=MAT / "petg.json", printer="my UM2").profiles
    assert p.identity.printer == "my UM2"
    assert p.bounds.min_temp_c == 210 and p.bounds.recommended_temp_c == 230


def test_export_of_a_flowloop_profile_without_ddprint_extras():
    p = P.profile_from_dict(make(name='odd "name"; ../x', air=(0.2, 200.0, 10.0),
                                 real=(0.2, 220.0, 9.0), bounds=(190.0, 210.0, 250.0),
                                 provenance={"method": "into_air"}))
    text = ddprint.export_text(p)
    data = ddprint.parse_text(text)
    assert data["properties_80"]["Ktemp"] == 0.2 and data["hotendMaxTemp"] == 250
    assert data["version"] == data["properties_80"]["version"] == 5
    assert json.dumps(p.identity.name) in text.splitlines()[1]
    assert ddprint.to_profile(data, 0.8, name="y").lines == p.lines


ddprint_numbers = st.floats(min_value=0.01, max_value=400, allow_nan=False)


@settings(max_examples=100, deadline=None)
@given(st.floats(min_value=0.01, max_value=0.5),
       st.floats(min_value=150, max_value=250),
       st.floats(min_value=0.5, max_value=30), st.floats(min_value=0, max_value=10),
       st.dictionaries(st.sampled_from(["bedTemp", "kAdvance", "keepBedtemp"]),
                       ddprint_numbers))
def test_export_then_import_keeps_every_number(ktemp, p0temp, fr0, gap, extras):
    data = {"version": 5, "material_diameter": 1.75, "hotendBaseTemp": 150,
            "hotendGoodTemp": 200, "hotendMaxTemp": 260, **extras,
            "properties_40": {"version": 5, "slippage": 0.1, "Ktemp": ktemp,
                              "P0temp": p0temp, "FR0pwm": fr0,
                              "P0tempPrint": p0temp + gap, "FR0pwmPrint": fr0}}
    p = ddprint.to_profile(data, 0.4, name="h")
    again = ddprint.parse_text(ddprint.export_text(p))
    assert flatten_numbers(again) == flatten_numbers(data)


@pytest.mark.parametrize("path", UM2, ids=lambda p: p.stem)
def test_export_then_import_is_the_same_profile_and_owner(path, tmp_path):
    # docs/material_profiles.md: an exported profile imports back to itself
    profile = ddprint.import_file(path).profiles[0]
    assert profile.identity.printer == "UM2-1"
    assert profile.identity.filament_type in ("PLA", "PETG")
    exported = tmp_path / "exported-under-another-name.json"
    exported.write_text(ddprint.export_text(profile))
    (again,) = ddprint.import_file(exported).profiles
    assert again.identity == profile.identity
    assert again.lines == profile.lines and again.bounds == profile.bounds
    # --printer still decides when given
    (other,) = ddprint.import_file(exported, printer="farm-7").profiles
    assert other.identity.printer == "farm-7"


def test_a_spoolman_link_and_vendor_survive_export(tmp_path):
    profile = ddprint.import_file(UM2[0]).profiles[0]
    ident = P.Identity(name="linked", printer="voron-2", nozzle_diameter_mm=0.4,
                       filament_vendor="Prusament", filament_type="PLA",
                       spoolman_filament_id=12)
    exported = tmp_path / "x.json"
    exported.write_text(ddprint.export_text(
        P.Profile(**{**{f: getattr(profile, f) for f in profile.__struct_fields__},
                     "identity": ident})))
    (again,) = ddprint.import_file(exported).profiles
    assert again.identity == ident


@pytest.mark.parametrize("line, why", [
    ("# flowloop identity: {bad", "is not JSON"),
    ("# flowloop identity: [1]", "is not an object"),
    ('# flowloop identity: {"printer": 7}', "'printer' is not valid"),
    ('# flowloop identity: {"spoolman_filament_id": true}',
     "'spoolman_filament_id' is not valid"),
])
def test_a_broken_identity_comment_is_one_line(line, why):
    with pytest.raises(FlowloopError, match=why):
        ddprint.read_identity("# x\n" + line + "\n{}", "f.json")
