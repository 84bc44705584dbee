"""`flowloop profile show|plot|validate|import|export`."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from flowloop.cli import main
from flowloop.cli.profile import safe_file_stem
from flowloop.material import ddprint
from flowloop.material import profile as P
from tests.samples import MAT, make


def run(capsys, *argv):
    code = main(["profile", *map(str, argv)])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture
def imported(tmp_path, capsys):
    code, out, err = run(capsys, "import", MAT / "UM2-1/herz-pla-red.json",
                         "-o", tmp_path)
    assert code == 0, err
    return tmp_path / "herz-pla-red_80.json"


def test_import_writes_one_profile_per_file_and_nozzle(tmp_path, capsys):
    files = sorted((MAT / "UM2-1").glob("*.json")) + [MAT / "pla.json"]
    code, out, err = run(capsys, "import", *files, "-o", tmp_path)
    assert code == 0, err
    written = sorted(p.name for p in tmp_path.iterdir())
    assert written == ["herz-pla-red_80.json", "herz_petg_white_40.json",
                       "kaisertech_pla_white_80.json", "noname_pla_blue_80.json",
                       "pla_40.json", "pla_80.json"]
    assert out.count("wrote ") == 6
    for path in tmp_path.iterdir():
        P.decode_profile(path.read_bytes())


def test_import_names_unreadable_files_and_exits_non_zero(tmp_path, capsys):
    broken = tmp_path / "broken.json"
    broken.write_text("{ not json")
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    code, out, err = run(capsys, "import", MAT / "abs.json", broken, MAT / "nylon.json",
                         "-o", out_dir)
    assert code == 1
    assert "abs.json: no properties_NN" in err
    assert "broken.json: not a ddPrint file: line 1" in err
    assert "nylon.json properties_40: no real-print point" in err
    assert [p.name for p in out_dir.iterdir()] == ["nylon_80.json"]


def test_import_warns_about_a_real_print_line_above_into_air(tmp_path, capsys):
    code, out, err = run(capsys, "import", MAT / "JP-1/kaiser-pla-grey.json",
                         "-o", tmp_path)
    assert code == 0  # imported: a warning, not a refusal
    assert [p.name for p in tmp_path.iterdir()] == ["kaiser-pla-grey_80.json"]
    assert "warning: kaiser-pla-grey_80: the real-print line lies above" in err
    code, out, _ = run(capsys, "show", tmp_path / "kaiser-pla-grey_80.json")
    assert code == 0 and "  warning: the real-print line lies above" in out


def test_import_nozzle_option(tmp_path, capsys):
    code, out, err = run(capsys, "import", MAT / "pla.json", "--nozzle", "0.4",
                         "-o", tmp_path)
    assert code == 0 and [p.name for p in tmp_path.iterdir()] == ["pla_40.json"]


def test_show_prints_the_flow_table(imported, capsys):
    code, out, _ = run(capsys, "show", imported, "--wp", "0.5")
    assert code == 0
    assert "herz-pla-red_80" in out and "UM2-1" in out
    # 230 degC at WP 0.5: 0.146*230 - 19.0018276 = 14.58
    assert "230.0 degC ->  14.58 mm^3/s" in out
    code, out, _ = run(capsys, "show", imported, "--json")
    assert json.loads(out)["identity"]["name"] == "herz-pla-red_80"


def test_validate_reports_each_file(imported, tmp_path, capsys):
    bad = tmp_path / "bad.json"
    data = json.loads(imported.read_text())
    data["lines"]["into_air"]["slope_mm3_s_per_c"] = -1
    bad.write_text(json.dumps(data))
    code, out, err = run(capsys, "validate", imported, bad)
    assert code == 1
    assert f"{imported}: ok (herz-pla-red_80)" in out
    assert "bad.json: invalid profile: lines.into_air.slope_mm3_s_per_c must be > 0" \
        in err


def test_a_ddprint_file_given_to_show_gets_a_hint(capsys):
    code, _, err = run(capsys, "show", MAT / "pla.json")
    assert code == 2 and "run 'flowloop profile import" in err


def test_plot_writes_svg_and_png(imported, tmp_path, capsys):
    out = tmp_path / "p.svg"
    code, _, _ = run(capsys, "plot", imported, "-o", out, "--wp", "0.2")
    assert code == 0
    ET.fromstring(out.read_bytes())
    code, _, _ = run(capsys, "plot", imported, "-o", tmp_path / "p.png")
    assert code == 0 and (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"
    code, _, err = run(capsys, "plot", imported, "-o", tmp_path / "p.pdf")
    assert code == 2 and ".svg or .png" in err


def test_export_writes_a_ddprint_file(imported, tmp_path, capsys):
    out = tmp_path / "herz.ddprint.json"
    code, _, _ = run(capsys, "export", imported, "-o", out)
    assert code == 0
    data = ddprint.parse_text(out.read_text())
    assert data["properties_80"]["P0temp"] == 171.6312
    assert data["properties_80"]["FR0pwmPrint"] == 10.1356
    code, text, _ = run(capsys, "export", imported)
    assert text == out.read_text()


@pytest.mark.parametrize("name, stem", [("../../etc/passwd", "etc_passwd"),
                                        (".hidden", "hidden"), ("a/b\\c", "a_b_c"),
                                        ("PLA 0.4; \"x\"", "PLA_0_4_x"),
                                        ("...", "profile")])
def test_file_names_from_profile_names_cannot_escape(name, stem):
    assert safe_file_stem(name) == stem
    assert "/" not in safe_file_stem(name) and not safe_file_stem(name).startswith(".")


def test_import_into_a_missing_directory_is_refused(tmp_path, capsys):
    code, _, err = run(capsys, "import", tmp_path / "x.json", "-o", tmp_path / "nope")
    assert code == 2 and "no such directory" in err


def test_safe_file_stem_is_used_for_written_files(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    p = P.profile_from_dict(make(name="../evil"))
    src = tmp_path / "in.json"
    src.write_bytes(P.encode_profile(p))
    code, _, _ = run(capsys, "plot", src)
    assert code == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["evil.svg", "in.json"]


def test_import_never_overwrites_what_it_wrote_in_the_same_run(tmp_path, capsys):
    for folder, base in (("a", 190), ("b", 185)):
        (tmp_path / folder).mkdir()
        text = (MAT / "pla.json").read_text()
        data = ddprint.parse_text(text)
        data["hotendBaseTemp"] = base
        (tmp_path / folder / "pla.json").write_text(json.dumps(data))
    out = tmp_path / "out"
    out.mkdir()
    code, text, err = run(capsys, "import", tmp_path / "a/pla.json",
                          tmp_path / "b/pla.json", "-o", out)
    assert code == 1
    assert text.count("pla_40.json") == 1 and "was written above" in err
    assert P.decode_profile((out / "pla_40.json").read_bytes()).bounds.min_temp_c == 190


@pytest.mark.parametrize("action", ["export", "plot"])
def test_export_and_plot_never_overwrite_the_profile(action, tmp_path, capsys):
    from flowloop.cli import main as cli_main
    src = tmp_path / "p.json"
    src.write_text((Path(__file__).resolve().parents[2] / "docs" / "examples"
                    / "weak.json").read_text())
    before = src.read_bytes()
    assert cli_main(["profile", action, str(src), "-o",
                     str(tmp_path / "." / "p.json")]) == 2
    assert "would overwrite FILE" in capsys.readouterr().err
    assert src.read_bytes() == before


def test_store_refuses_a_bad_extruder_before_it_stores_anything(capsys):
    # no Moonraker at that port: had it tried to store, it would say "no answer"
    from devtools.stack import free_port
    weak = Path(__file__).resolve().parents[2] / "docs" / "examples" / "weak.json"
    assert main(["profile", "store", str(weak), "--activate", "nozzle",
                 "--moonraker", f"127.0.0.1:{free_port()}"]) == 2
    assert capsys.readouterr().err == (
        'flowloop profile: error: --activate: "nozzle" is not an extruder name'
        " (extruder, extruder1, ...)\n")
