"""The live page's core: the one HTML document, the profile's lines it
draws, and an annotated file's plan (flowloop.host.live_page)."""

from __future__ import annotations

import hashlib
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from flowloop.control.autotemp import GRID_S, Autotemp
from flowloop.errors import FlowloopError
from flowloop.gcode.annotate import AnnotateSettings, annotate_file
from flowloop.gcode.bake import plan_announcements, replay
from flowloop.gcode.reference_planner import PrinterLimits
from flowloop.host import live_page
from flowloop.material.profile import profile_from_dict, profile_line
from tests.samples import make
from tests.unit.test_autotemp_bake import WEAK

pytestmark = pytest.mark.unit

EXCERPT = Path(__file__).resolve().parents[1] / "data" / "gcode" / \
    "block_layers_1_2.gcode"
PROFILE = profile_from_dict(make())


@pytest.fixture(scope="module")
def annotated(tmp_path_factory):
    path = tmp_path_factory.mktemp("plan") / "annotated.gcode"
    annotate_file(EXCERPT, path)
    return path


def test_the_document_carries_every_file_it_links_inline():
    page = live_page.document().decode()
    assert not re.search(r"<script[^>]*\ssrc=", page)
    assert not re.search(r'<link rel="stylesheet"', page)
    assert "https://github.com/leeoniya/uPlot (v1.6.32)" in page  # uPlot's header
    assert "printer.objects.subscribe" in page                      # page.js
    assert "--panel" in page                                        # page.css
    # each script ends where it should: none holds a "</script" of its own
    assert page.count("<script>") == page.count("</script>") == 2


def test_the_page_draws_in_the_plots_colours():
    from flowloop.material.plot import COLORS
    page = live_page.document().decode()
    (served,) = re.findall(r"const COLORS = (\{.*?\});", page)
    assert json.loads(served) == COLORS
    assert live_page.PALETTE_MARK not in page


def test_a_missing_page_file_is_named(tmp_path):
    shutil.copytree(live_page.ASSETS, tmp_path / "page")
    (tmp_path / "page" / "page.js").unlink()
    with pytest.raises(FlowloopError, match="page.js"):
        live_page.document(tmp_path / "page")


def test_the_vendored_uplot_is_the_one_its_readme_names():
    readme = (live_page.ASSETS / "README.md").read_text()
    listed = dict((name, digest) for digest, name in
                  re.findall(r"^([0-9a-f]{64})  (\S+)$", readme, re.MULTILINE))
    assert set(listed) == {"uPlot.iife.min.js", "uPlot.min.css", "uPlot.LICENSE"}
    for name, digest in listed.items():
        data = (live_page.ASSETS / name).read_bytes()
        assert hashlib.sha256(data).hexdigest() == digest, name
    assert "MIT" in (live_page.ASSETS / "uPlot.LICENSE").read_text()


def test_the_profile_lines_are_the_one_melt_line():
    lines = live_page.profile_lines(PROFILE, 0.3)
    working = profile_line(PROFILE, 0.3)
    air = PROFILE.lines.into_air.line()
    assert len(lines["temp_c"]) == live_page.LINE_POINTS
    assert lines["temp_c"][0] < PROFILE.bounds.min_temp_c
    assert lines["temp_c"][-1] > PROFILE.bounds.max_temp_c
    for temp, flow, into_air in zip(lines["temp_c"], lines["working"],
                                    lines["into_air"]):
        assert flow == pytest.approx(working.flow_mm3_s(temp), abs=1e-3)
        assert into_air == pytest.approx(air.flow_mm3_s(temp), abs=1e-3)
        assert flow <= into_air + 1e-3


def test_the_heater_max_temp_bounds_the_profile_lines():
    lines = live_page.profile_lines(PROFILE, 0.5, heater_max_temp_c=240.0)
    assert lines["max_temp_c"] == 240.0
    assert lines["temp_c"][-1] < 260.0


@pytest.mark.parametrize("heater_max_temp_c, bound", [(None, 260.0), (300.0, 260.0),
                                                      (250.0, 250.0)])
def test_max_temp_is_the_bound_the_printer_runs_to_not_the_plot_margin(
        heater_max_temp_c, bound):
    # the profile allows 260 degC: the plot reaches past it, the bound does not
    lines = live_page.profile_lines(PROFILE, 0.5, heater_max_temp_c)
    assert lines["max_temp_c"] == bound
    assert lines["min_temp_c"] == 190.0
    span = bound - 190.0
    assert lines["temp_c"][0] == pytest.approx(190.0 - 0.1 * span, abs=0.01)
    assert lines["temp_c"][-1] == pytest.approx(bound + 0.1 * span, abs=0.01)


def test_the_plan_times_each_announcement_where_the_planner_placed_it(annotated):
    rec = plan_announcements(EXCERPT, PrinterLimits(), AnnotateSettings())
    plan = live_page.file_plan(annotated, None, 0.5)
    assert plan["windows"] == len(rec.commands)
    placed = [t for _, t, _ in rec.commands]
    read = [t for _, t in plan["positions"][:-1]]
    # the file's end at the print's end
    assert plan["positions"][-1] == (annotated.stat().st_size, plan["print_time_s"])
    # only the announcements' rounding (0.01 s a window) separates them
    assert max(abs(a - b) for a, b in zip(placed, read)) < 0.5
    assert plan["print_time_s"] == pytest.approx(rec.end_s, abs=1.5)
    offsets = [o for o, _ in plan["positions"]]
    assert offsets == sorted(offsets)


def test_the_planned_temperature_is_autotemps_replay(annotated):
    plan = live_page.file_plan(annotated, PROFILE, 0.5)
    rec = plan_announcements(EXCERPT, PrinterLimits(), AnnotateSettings())
    controller = Autotemp()
    controller.set_profile(PROFILE, 0.5)
    targets = replay(rec.commands, rec.end_s, controller)
    known = [t for t in targets if t is not None]
    shown = [t for t in plan["target_c"] if t is not None]
    assert plan["why"] is None
    assert max(shown) == pytest.approx(max(known), abs=1.0)
    assert min(shown) == pytest.approx(min(known), abs=1.0)
    assert PROFILE.bounds.min_temp_c <= min(shown) <= max(shown) \
        <= PROFILE.bounds.max_temp_c


def test_the_plan_starts_where_the_files_wait_leaves_the_nozzle(tmp_path):
    """The page replays from the start G-code's M109, as [autotemp] starts
    from the heater's target at the printer's first flush: a file that
    waits hot is not shown pushed to the maximum as if it started cold."""
    line = dict(WEAK["lines"]["real_print"], slope_mm3_s_per_c=0.25)
    profile = profile_from_dict(dict(
        WEAK, lines={"into_air": line, "real_print": line},
        bounds=dict(WEAK["bounds"], max_temp_c=260.0)))
    first = {}
    for wait_c in (200, 235):   # the first layer needs about 215 C
        src = tmp_path / f"s{wait_c}.gcode"
        src.write_text(EXCERPT.read_text().replace("M109 S200", f"M109 S{wait_c}"))
        annotate_file(src, tmp_path / f"a{wait_c}.gcode")
        plan = live_page.file_plan(tmp_path / f"a{wait_c}.gcode", profile, 0.5)
        first[wait_c] = plan["target_c"][0]
    assert first[200] == profile.bounds.max_temp_c     # pushed from 200 C
    assert first[235] < 220                            # already hot enough


def test_the_plan_flow_is_the_announced_flow(annotated):
    plan = live_page.file_plan(annotated, None, 0.5)
    rec = plan_announcements(EXCERPT, PrinterLimits(), AnnotateSettings())
    announced = max(float(line.split("FLOW=")[1].split()[0])
                    for _, _, line in rec.commands)
    assert max(plan["flow_mm3_s"]) == pytest.approx(announced)
    assert plan["target_c"] == [None] * len(plan["time_s"])
    assert "no active profile" in plan["why"]


def test_a_long_plan_is_bounded(annotated, monkeypatch):
    monkeypatch.setattr(live_page, "MAX_PLAN_POINTS", 50)
    plan = live_page.file_plan(annotated, PROFILE, 0.5)
    assert len(plan["time_s"]) == len(plan["flow_mm3_s"]) == len(plan["target_c"])
    assert len(plan["time_s"]) <= 51
    assert len(plan["positions"]) <= 51
    assert plan["time_s"][-1] <= plan["print_time_s"] + GRID_S * 200


def test_a_file_without_annotations_is_said_in_words():
    with pytest.raises(FlowloopError, match="has no autotemp annotations"):
        live_page.file_plan(EXCERPT, PROFILE, 0.5)


def test_an_unreadable_file_is_one_line(tmp_path):
    with pytest.raises(FlowloopError, match="cannot read"):
        live_page.file_plan(tmp_path / "gone.gcode", PROFILE, 0.5)


def test_the_plan_process_answers_what_file_plan_answers(annotated):
    argv, stdin = live_page.plan_command(sys.executable, annotated, PROFILE, 0.5)
    out = subprocess.run(argv, input=stdin, capture_output=True, check=True).stdout
    answer = json.loads(out)
    direct = live_page.file_plan(annotated, PROFILE, 0.5)
    assert answer["annotated"] is True
    assert answer["target_c"] == direct["target_c"]
    assert answer["positions"] == [list(p) for p in direct["positions"]]


def test_the_plan_process_says_why_in_one_answer():
    argv, stdin = live_page.plan_command(sys.executable, EXCERPT, None, 0.5)
    out = subprocess.run(argv, input=stdin, capture_output=True, check=True).stdout
    answer = json.loads(out)
    assert answer["annotated"] is False
    assert "has no autotemp annotations" in answer["why"]
