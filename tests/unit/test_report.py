"""The flow report: a recorder that stays small over hours of printing and
keeps the extremes, under-extrusion by layer, the dump round trip, and an
HTML report that shows the series and says what it lacks."""

from __future__ import annotations

import json
import math
import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from flowloop.cli import main
from flowloop.errors import FlowloopError
from flowloop.report import dump, render
from flowloop.report.recorder import (
    DEFAULT_MAX_BINS,
    MAX_EVENTS,
    MAX_SPANS,
    Job,
    Recorder,
    Sample,
    one_tool,
    sample_from_status,
    status_objects,
)

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "docs" / "examples" / "flow_report_dump.json"
SVG = "{http://www.w3.org/2000/svg}"
AREA = math.pi / 4 * 1.75 ** 2


def steady(time_s, **changes):
    values = dict(commanded_flow_mm3_s=10.0, measured_flow_mm3_s=10.0, grip=1.0,
                  temp_c=210.0, target_c=210.0, planned_temp_c=210.0,
                  slowed_time_s=0.0, profile="PLA", working_point=0.5, layer=1)
    values.update(changes)
    return Sample(time_s, **values)


def parse(text: str) -> ET.Element:
    return ET.fromstring(text.split("\n", 1)[1])   # past <!DOCTYPE html>


def by_id(root: ET.Element, ident: str) -> ET.Element:
    (el,) = [e for e in root.iter() if e.get("id") == ident]
    return el


def lacks(root: ET.Element):
    el = by_id(root, "lacks")
    return [li.text for li in el] if el.tag == "ul" else []


# --- bounded memory --------------------------------------------------------------

def test_ten_hours_at_4_hz_stay_in_a_bounded_number_of_bins_with_the_extremes():
    rec = Recorder()
    spike_at, dip_at = 7 * 3600 + 0.25, 2 * 3600 + 0.5
    for i in range(10 * 3600 * 4):
        t = i / 4
        flow = 30.0 if t == spike_at else 10.0
        grip = 0.31 if t == dip_at else 1.0
        rec.sample(steady(t, commanded_flow_mm3_s=flow, grip=grip))
    assert len(rec.bins.rows) <= DEFAULT_MAX_BINS
    assert rec.bins.width_s >= 10 * 3600 / DEFAULT_MAX_BINS
    # one sample in 144,000 survives every merge as its bin's max / min
    assert rec.bins.extreme("commanded_flow", "max") == 30.0
    assert rec.bins.extreme("grip", "min") == 0.31
    # and the means are exact: count and sum merge without loss
    means = [v for _, v in rec.bins.series("commanded_flow") if v is not None]
    assert max(means) < 10.1
    total = sum(row[0][0] for row in rec.bins.rows if row is not None)
    assert total == 10 * 3600 * 4
    # the dump of ten hours is small
    assert len(dump.dumps(rec)) < 200_000


def test_spans_and_events_stay_bounded_and_keep_their_total_cost():
    rec = Recorder()
    slowed = 0.0
    for i in range(4000):
        t = i * 3.0  # a slowdown every other sample, never joined to the last
        if i % 2:
            slowed += 0.1
        rec.sample(steady(t, slowed_time_s=slowed, cap_reason="grip",
                          sensor_fault="magnet" if i % 2 else None))
    assert len(rec.slowdowns.items) <= MAX_SPANS
    assert len(rec.faults.items) <= MAX_SPANS
    assert len(rec.events) == MAX_EVENTS and rec.events_dropped > 0
    assert sum(rec.slowdown_by_reason().values()) == pytest.approx(slowed)


# --- what the recorder counts ---------------------------------------------------

def test_under_extrusion_is_counted_per_layer_where_grip_is_below_the_noise():
    rec = Recorder()
    t = 0.0
    # layer 1: 100 s at grip 0.99 (within the noise); layer 2: 50 s at 0.8
    for layer, grip, seconds in ((1, 0.99, 100), (2, 0.8, 50), (3, 1.0, 10)):
        for _ in range(seconds * 4):
            rec.sample(steady(t, layer=layer, grip=grip,
                              measured_flow_mm3_s=10 * grip))
            t += 0.25
    rec.finish("completed", t)
    commanded_2 = 10 * 50 / AREA
    assert rec.layers[1].under_mm == 0.0
    assert rec.layers[2].under_mm == pytest.approx(0.2 * commanded_2, rel=0.01)
    assert rec.layers[2].commanded_mm == pytest.approx(commanded_2, rel=0.01)
    assert rec.under_mm == pytest.approx(rec.layers[2].under_mm)


def test_a_faulted_sensor_counts_lost_time_and_no_under_extrusion():
    rec = Recorder()
    for i in range(400):
        fault = "magnet" if 100 <= i < 200 else None
        rec.sample(steady(i / 4, grip=None if fault else 1.0, sensor_fault=fault))
    assert rec.under_mm == 0.0
    (span,) = rec.faults.items
    assert span.kind == "magnet"
    assert span.cost_s == pytest.approx(25.0, abs=0.3)
    assert [e.text for e in rec.events] == ["sensor fault 'magnet'",
                                            "sensor fault cleared"]


def test_a_gap_in_the_data_is_lost_time_not_integrated_flow():
    rec = Recorder()
    rec.sample(steady(0.0, grip=0.5))
    rec.sample(steady(60.0, grip=0.5))   # klippy away for a minute
    assert rec.under_mm == 0.0
    assert [(s.kind, s.cost_s) for s in rec.faults.items] == [("no data", 60.0)]
    assert any("no data for 1 min" in x for x in rec.lacks())


def test_the_limiters_cost_is_its_running_total_split_by_reason():
    rec = Recorder()
    slowed = 5.0  # what klippy had counted before the print
    for i in range(200):
        reason = "temperature" if i < 100 else "grip"
        if 40 <= i < 60 or 140 <= i < 150:
            slowed += 0.05
        rec.sample(steady(i / 4, slowed_time_s=slowed, cap_reason=reason,
                          cap_mm3_s=8.0))
    costs = rec.slowdown_by_reason()
    assert costs["temperature"] == pytest.approx(1.0)
    assert costs["grip"] == pytest.approx(0.5)


def test_a_restarted_klippy_resets_the_limiters_total_without_a_negative_cost():
    rec = Recorder()
    rec.sample(steady(0.0, slowed_time_s=30.0))
    rec.sample(steady(0.25, slowed_time_s=0.0))   # klippy restarted
    rec.sample(steady(0.5, slowed_time_s=0.2, cap_reason="grip"))
    assert rec.slowdown_by_reason() == {"grip": pytest.approx(0.2)}


def test_layers_are_counted_from_z_where_the_slicer_gives_no_numbers():
    rec = Recorder()
    t = 0.0
    for z, extruding in ((0.2, True), (0.6, False), (0.2, True), (0.4, True),
                         (0.8, False), (0.4, True), (0.6, True)):
        rec.sample(steady(t, layer=None, z_mm=z,
                          commanded_flow_mm3_s=5.0 if extruding else 0.0))
        t += 1.0
    # the travels at a Z hop (0.6, 0.8) start no layer
    assert sorted(rec.layers) == [1, 2, 3]
    assert [rec.layers[k].z_mm for k in (1, 2, 3)] == [0.2, 0.4, 0.6]


def test_a_toolchangers_report_follows_the_tool_that_prints():
    from flowloop.control.tools import tool_objects
    objects = ["extruder", "extruder1", "flow_sensor t0", "flow_sensor t1",
               "flowrate_limiter", "flowrate_limiter extruder1", "autotemp",
               "toolhead", "print_stats"]
    settings = {"flow_sensor t0": {}, "flow_sensor t1": {"extruder": "extruder1"},
                "flowrate_limiter": {}, "autotemp": {"extruder": "extruder"}}
    tools = {e: tool_objects(objects, settings, e) for e in ("extruder", "extruder1")}
    assert tools["extruder1"] == {"sensor": "flow_sensor t1",
                                  "limiter": "flowrate_limiter extruder1",
                                  "autotemp": None}
    wanted = status_objects(tools)
    assert {"flow_sensor t0", "flow_sensor t1", "flowrate_limiter extruder1",
            "extruder1"} <= set(wanted)
    status = {"toolhead": {"extruder": "extruder1"},
              "extruder": {"temperature": 175.0}, "extruder1": {"temperature": 240.0},
              "flow_sensor t0": {"grip": 1.0}, "flow_sensor t1": {"grip": 0.91},
              "flowrate_limiter": {"reason": "none"},
              "flowrate_limiter extruder1": {"cap": 8.0, "reason": "grip"},
              "autotemp": {"active": True, "target": 200.0}}
    s = sample_from_status(3.0, status, tools)
    assert (s.grip, s.temp_c, s.cap_reason, s.planned_temp_c) == \
        (0.91, 240.0, "grip", None)
    status["toolhead"]["extruder"] = "extruder"
    s = sample_from_status(4.0, status, tools)
    assert (s.grip, s.temp_c, s.cap_reason, s.planned_temp_c) == \
        (1.0, 175.0, "none", 200.0)


def test_a_sample_is_read_from_klippys_objects_and_missing_ones_are_unknown():
    status = {
        "print_stats": {"state": "printing", "info": {"current_layer": 4}},
        "toolhead": {"position": [1, 2, 0.8, 100]},
        "extruder": {"temperature": 214.9, "target": 215.0},
        "flowrate_limiter": {"cap": 9.5, "reason": "grip", "slowed_time": 1.5},
        "autotemp": {"active": True, "target": 216.0, "profile": "PLA",
                     "working_point": 0.4},
        "flow_sensor sim": {"grip": 0.93, "measured_flow": 8.1,
                            "commanded_flow": 8.7, "fault": None,
                            "filament_position": 55.0},
    }
    s = sample_from_status(12.0, status, one_tool("sim"))
    assert (s.layer, s.z_mm, s.grip, s.cap_reason, s.planned_temp_c) == \
        (4, 0.8, 0.93, "grip", 216.0)
    assert (s.profile, s.working_point, s.sensor) == ("PLA", 0.4, True)
    bare = sample_from_status(1.0, {"print_stats": {"state": "printing"}},
                              one_tool(None))
    assert bare.sensor is False and bare.grip is None and bare.temp_c is None


# --- the dump ---------------------------------------------------------------------

def scenario() -> Recorder:
    """The worked example of docs/flow_report.md: a 20-minute print of 30
    layers, 40 s per layer. The hotend falls behind on layers 12 to 14 (grip
    0.85, the limiter's grip cap slows them), the sensor loses its magnet for
    20 s on layer 20, and autotemp plans the temperature throughout."""
    rec = Recorder(job=Job(job_id="00002A", filename="benchy.gcode",
                           started_at=1764100000.0, sensor_name="sim"))
    slowed = 12.0   # klippy's running total from earlier prints
    for i in range(30 * 40 * 4):
        t = i / 4
        layer = 1 + i // 160
        flow = 6.0 + 6.0 * (layer % 5) / 4
        weak = 12 <= layer <= 14
        fault = "magnet" if layer == 20 and 40 <= i % 160 < 120 else None
        grip = None if fault else (0.85 if weak else 1.0)
        if weak:
            slowed += 0.25 * 0.12
        rec.sample(Sample(
            t, commanded_flow_mm3_s=flow,
            measured_flow_mm3_s=flow * (grip or 1.0), grip=grip,
            temp_c=200 + flow * 2 - (3 if weak else 0), target_c=200 + flow * 2,
            planned_temp_c=200 + flow * 2, cap_mm3_s=flow * 0.9 if weak else None,
            cap_reason="grip" if weak else "none", slowed_time_s=slowed,
            sensor_fault=fault, layer=layer, z_mm=round(0.2 * layer, 2),
            profile="Herz PLA red", working_point=0.5))
    rec.finish("completed", 30 * 40.0)
    return rec


def test_the_dump_round_trips_and_renders_the_same_report():
    rec = scenario()
    again = dump.loads(dump.dumps(rec))
    assert dump.dumps(again) == dump.dumps(rec)
    assert render.html(again) == render.html(rec)   # the dump loses nothing drawn
    assert dump.summary(again) == dump.summary(rec)


def test_the_docs_example_dump_is_the_scenarios():
    # regenerate: python -c "from tests.unit.test_report import *; \
    #   EXAMPLE.write_text(dump.dumps(scenario()) + '\n')"
    assert EXAMPLE.read_text() == dump.dumps(scenario()) + "\n"


@pytest.mark.parametrize("text, says", [
    ('{"format": "flowloop-flow-report", "version": 99}', "version 99"),
    ('{"name": "PLA"}', "not a flowloop flow report dump"),
    ("[1, 2]", "not a flowloop flow report dump"),
    ("{not json", "not JSON"),
    ('{"format": "flowloop-flow-report", "version": 1, "bins": {}}', "damaged"),
])
def test_a_dump_it_cannot_read_gives_one_clear_error(text, says):
    with pytest.raises(FlowloopError, match=says) as exc:
        dump.loads(text, "x.json")
    assert "\n" not in str(exc.value) and "x.json" in str(exc.value)


# --- the rendered report -------------------------------------------------------

def test_the_report_is_one_offline_document_with_every_series():
    text = render.html(scenario())
    root = parse(text)
    assert "http://" not in text.replace("http://www.w3.org/2000/svg", "")
    assert "https://" not in text
    svgs = {svg.get("id") for svg in root.iter(f"{SVG}svg")}
    assert svgs == {"flow-plot", "grip-plot", "temperature-plot", "layers-plot"}
    for ident in ("commanded_flow", "measured_flow", "cap", "grip", "temp",
                  "target", "planned_temp", "under_extrusion"):
        assert len(by_id(root, ident)), ident
    # the under-extruded layers are drawn, 12 to 14 the tallest
    bars = {int(r.get("data-layer")): float(r.get("height"))
            for r in root.iter(f"{SVG}rect") if r.get("class") == "layer"}
    assert set(sorted(bars, key=bars.get)[-3:]) == {12, 13, 14}
    assert sum(1 for r in root.iter(f"{SVG}rect")
               if r.get("class") == "fault") >= 3   # the magnet, in each time panel
    assert lacks(root) == []
    reasons = [row[0].text for row in by_id(root, "slowdowns")[1:]]
    assert reasons == ["grip"]


@pytest.mark.parametrize("make, says", [
    (lambda r: r.finish("cancelled", 30.0), "did not complete (cancelled"),
    (lambda r: None, "had not ended"),
])
def test_a_report_says_the_print_did_not_end_well(make, says):
    rec = Recorder(job=Job(filename="a.gcode"))
    for i in range(120):
        rec.sample(steady(i / 4))
    make(rec)
    assert any(says in x for x in lacks(parse(render.html(rec))))


def test_a_report_without_sensor_data_or_file_says_so_and_draws_empty_panels():
    rec = Recorder(job=Job(job_id="000003"))
    for i in range(40):
        rec.sample(Sample(i / 4, temp_c=200.0, target_c=200.0, sensor=False))
    rec.finish("completed")
    root = parse(render.html(rec))
    said = lacks(root)
    assert "the job has no file name" in said
    assert any("no flow sensor data" in x for x in said)
    assert any("autotemp planned no temperature" in x for x in said)
    missing = [t.text for t in root.iter(f"{SVG}text") if t.get("class") == "missing"]
    assert any("no flow data" in x for x in missing)
    assert any("no grip" in x for x in missing)


def test_a_sensor_faulted_for_the_whole_print_is_said():
    rec = Recorder(job=Job(filename="a.gcode"))
    for i in range(40):
        rec.sample(steady(i / 4, grip=None, sensor_fault="missing"))
    rec.finish("completed")
    said = lacks(parse(render.html(rec)))
    assert any("faulted for the whole print" in x for x in said)
    assert rec.lost_s() == pytest.approx(39 / 4)


def test_an_empty_recording_renders_and_says_it_has_no_data():
    rec = Recorder()
    rec.finish("klippy_shutdown")
    root = parse(render.html(rec))
    assert "no data was recorded" in lacks(root)


# --- the command ------------------------------------------------------------------

def test_flowloop_report_writes_the_html_beside_the_dump(tmp_path, capsys):
    src = tmp_path / "job.json"
    src.write_text(dump.dumps(scenario()))
    assert main(["report", str(src)]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"wrote {tmp_path / 'job.html'}")
    parse((tmp_path / "job.html").read_text())


def test_flowloop_report_refuses_a_file_that_is_no_dump_in_one_line(tmp_path, capsys):
    src = tmp_path / "profile.json"
    src.write_text(json.dumps({"name": "PLA"}))
    assert main(["report", str(src), "-o", str(tmp_path / "r.html")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not a flowloop flow report dump" in err
    assert not (tmp_path / "r.html").exists()


def test_the_flow_report_worked_example(tmp_path, capsys):
    from tests.unit.test_docs_examples import _example, _run
    section, command, output = _example("flow_report.md", "### Worked example")
    assert _run(command, tmp_path, capsys).splitlines() == output
    # the layer figures the prose gives are the report's layer table
    root = parse((tmp_path / "benchy_report.html").read_text())
    rows = [[td.text for td in tr] for tr in by_id(root, "layer-table")[1:]]
    figures = re.search(r"names the three layers: ([0-9.]+), ([0-9.]+) and "
                        r"([0-9.]+) mm", section).groups()
    assert [int(r[0]) for r in rows] == list(range(1, 31))   # every layer
    assert [r for r in rows if r[2] != "0.00"] == [
        [layer, z, under, commanded, "15.0"] for (layer, z, commanded), under
        in zip((("12", "2.4", "149.7"), ("13", "2.6", "174.6"),
                ("14", "2.8", "199.6")), figures)]
    assert "a 20-minute print of 30 layers" in section


# --- the charts -------------------------------------------------------------------

def _points(root: ET.Element, ident: str):
    """The (x, y) of every vertex of a series' polylines."""
    return [tuple(map(float, pair.split(",")))
            for line in by_id(root, ident).iter(f"{SVG}polyline")
            for pair in line.get("points").split()]


def _frame(root: ET.Element, plot: str):
    """The plot frame's top and bottom y (the grid lines' extent)."""
    svg = by_id(root, plot)
    ys = [float(line.get(k)) for line in svg.iter(f"{SVG}line")
          if line.get("x1") == line.get("x2") for k in ("y1", "y2")]
    return min(ys), max(ys)


def test_samples_three_seconds_apart_still_draw_every_series():
    # the demo samples every 3 s: one sample per three 1 s bins
    rec = Recorder(job=Job(filename="a.gcode"))
    for i in range(40):
        rec.sample(steady(3.0 * i, grip=0.9))
    rec.finish("completed")
    root = parse(render.html(rec))
    for ident in ("commanded_flow", "measured_flow", "grip", "temp"):
        (line,) = by_id(root, ident).iter(f"{SVG}polyline")   # one line, not dots
        xs = {pair.split(",")[0] for pair in line.get("points").split()}
        assert len(xs) == 40, ident


def test_a_lone_sample_draws_a_stroke_not_nothing():
    rec = Recorder(job=Job(filename="a.gcode"))
    rec.sample(steady(0.0))
    rec.sample(steady(30.0, grip=0.95))    # after a gap: a lone point
    rec.finish("completed")
    for line in parse(render.html(rec)).iter(f"{SVG}polyline"):
        xs = {pair.split(",")[0] for pair in line.get("points").split()}
        assert len(xs) >= 2, line.get("id")


def test_negative_measured_flow_and_grip_stay_inside_the_frame():
    # a retraction the sensor sees: measured flow and grip below zero
    rec = Recorder(job=Job(filename="a.gcode"))
    for i in range(40):
        rec.sample(steady(i / 4, measured_flow_mm3_s=-4.0 if i % 10 == 0 else 10.0,
                          grip=-0.3 if i % 10 == 0 else 1.6))
    rec.finish("completed")
    root = parse(render.html(rec))
    for plot, idents in (("flow-plot", ("measured_flow", "measured_flow_max")),
                         ("grip-plot", ("grip", "grip_min"))):
        top, bottom = _frame(root, plot)
        for ident in idents:
            ys = [y for _, y in _points(root, ident)]
            assert ys and top <= min(ys) and max(ys) <= bottom, (plot, ident)


def test_the_layer_table_lists_every_layer_also_those_that_extruded_well():
    rec = Recorder(job=Job(filename="two_layers.gcode"))
    for i in range(80):
        rec.sample(steady(i / 4, layer=1 + i // 40,
                          grip=0.8 if i < 40 else 1.0))
    rec.finish("completed")
    rows = [[td.text for td in tr]
            for tr in by_id(parse(render.html(rec)), "layer-table")[1:]]
    assert [r[0] for r in rows] == ["1", "2"]
    assert rows[1][2] == "0.00" and float(rows[1][3]) > 0


# --- storing ----------------------------------------------------------------------

def test_only_the_newest_jobs_reports_are_kept_and_other_files_are_left(tmp_path):
    for k, job_id in enumerate(("000009", "00000A", "000010", "0000FF")):
        (tmp_path / f"{job_id}.json").write_text("{}")
        (tmp_path / f"{job_id}.html").write_text("")
        # a dump that does not say when its job ended: its file's time does
        os.utime(tmp_path / f"{job_id}.json", (1000.0 + k, 1000.0 + k))
    (tmp_path / "notes.json").write_text("{}")
    assert [p.stem for p in dump.stored(tmp_path)] == [
        "0000FF", "000010", "00000A", "000009"]   # ended last first
    assert dump.prune(tmp_path, 2) == ["00000A", "000009"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "000010.html", "000010.json", "0000FF.html", "0000FF.json", "notes.json"]
    assert dump.stored(tmp_path / "none") == []


def test_a_full_disk_leaves_the_old_file_and_no_partial_one(tmp_path, monkeypatch):
    target = tmp_path / "00002A.json"
    target.write_text("the stored one")

    def full(*args):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr("flowloop.files.os.replace", full)
    with pytest.raises(OSError, match="No space left"):
        dump.save(target, dump.dumps(scenario()))
    assert [p.name for p in tmp_path.iterdir()] == ["00002A.json"]
    assert target.read_text() == "the stored one"


def _stored_dump(folder, job_id, started_at, length_s):
    rec = Recorder(job=Job(job_id=job_id, started_at=started_at))
    rec.finish("completed", length_s)
    (folder / f"{job_id}.json").write_text(dump.dumps(rec))
    (folder / f"{job_id}.html").write_text("")


def test_reports_are_pruned_by_when_their_job_ended_not_by_the_ids_number(tmp_path):
    # ten jobs, then Moonraker's history cleared: the next print is 000001 again
    for k in range(10):
        _stored_dump(tmp_path, f"{k + 2:06X}", 1000.0 + 100 * k, 50.0)
    _stored_dump(tmp_path, "000001", 5000.0, 30.0)
    assert dump.stored(tmp_path)[0].stem == "000001"    # ended last
    removed = dump.prune(tmp_path, 3)
    assert "000001" not in removed and len(removed) == 8
    assert [p.stem for p in dump.stored(tmp_path)] == ["000001", "00000B", "00000A"]


def test_a_report_of_a_job_no_longer_in_the_history_goes_first(tmp_path):
    _stored_dump(tmp_path, "000001", 5000.0, 30.0)      # the new job 000001
    _stored_dump(tmp_path, "000002", 1000.0, 30.0)      # deleted from the history
    _stored_dump(tmp_path, "000003", 1100.0, 30.0)      # its id now another job's
    _stored_dump(tmp_path, "000004", 1200.0, 30.0)
    history = {"000001": 5000.0, "000003": 4000.0, "000004": 1200.0}
    assert sorted(dump.prune(tmp_path, 10, history)) == ["000002", "000003"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "000001.html", "000001.json", "000004.html", "000004.json"]
    # without a history to ask, only the count decides
    assert dump.prune(tmp_path, 1) == ["000004"]


def test_storing_a_report_prunes_the_old_ones_before_it_is_written(tmp_path,
                                                                    monkeypatch):
    """A listing between the new report's write and the pruning showed
    keep + 1 reports (the fil tier's report test under load): the old ones
    now go first, so any listing that shows the new one shows at most keep."""
    _stored_dump(tmp_path, "000001", 1000.0, 30.0)
    _stored_dump(tmp_path, "000002", 1100.0, 30.0)
    seen = []
    real_save = dump.save

    def save(path, text):
        seen.append(sorted(p.stem for p in tmp_path.glob("*.json")))
        real_save(path, text)
    monkeypatch.setattr(dump, "save", save)
    rec = Recorder(job=Job(job_id="000003", started_at=1200.0))
    rec.finish("completed", 30.0)
    history = {"000001": 1000.0, "000002": 1100.0, "000003": 1200.0}
    assert dump.store(tmp_path, rec, 2, history, lambda r: "<html>")
    assert seen[0] == ["000002"]     # 000001 gone before 000003 was written
    assert [p.stem for p in dump.stored(tmp_path)] == ["000003", "000002"]
    assert (tmp_path / "000003.html").read_text() == "<html>"


def test_a_stored_report_replaces_the_one_of_a_reused_id_and_one_of_no_job_is_not_kept(
        tmp_path):
    _stored_dump(tmp_path, "000001", 1000.0, 30.0)     # before the history was cleared
    rec = Recorder(job=Job(job_id="000001", started_at=5000.0))
    rec.finish("completed", 30.0)
    assert dump.store(tmp_path, rec, 2, {"000001": 5000.0})
    (stored,) = dump.stored_reports(tmp_path)
    assert stored.started_at == 5000.0
    # a job Moonraker's history does not hold: nothing written
    rec = Recorder(job=Job(job_id="000009", started_at=6000.0))
    rec.finish("completed", 30.0)
    assert not dump.store(tmp_path, rec, 2, {"000001": 5000.0})
    assert [p.stem for p in dump.stored(tmp_path)] == ["000001"]


def test_a_report_pruned_while_it_is_listed_is_left_out_not_listed_as_a_problem(
        tmp_path, monkeypatch):
    """The fil tier's report test polled the listing while a job's end
    pruned an old report: the report gone between the listing and its
    reading was listed as {job_id, problem}, without its filename."""
    for k in range(3):
        _stored_dump(tmp_path, f"00000{k + 1}", 1000.0 + 100 * k, 30.0)
    (tmp_path / "00000F.json").write_text("{")         # stays unreadable
    real_load = dump.load

    def load_as_pruned(path):
        if path.stem == "000001":           # pruned at this moment
            dump.prune(tmp_path, 3)
        return real_load(path)
    monkeypatch.setattr(dump, "load", load_as_pruned)
    listed = dump.summaries(tmp_path)
    assert [e["job_id"] for e in listed] == ["00000F", "000003", "000002"]
    assert "is not JSON" in listed[0]["problem"]
    assert all(e["state"] == "completed" for e in listed[1:])


def test_a_job_id_is_moonrakers_and_never_case_folded():
    assert dump.check_job_id("00002a") == "00002A"
    for bad in ("\ufb00\ufb00\ufb00", "0000\ufb00", "2A", "00002A\n", "../x", 42):
        with pytest.raises(FlowloopError, match="not a job of Moonraker's history"):
            dump.check_job_id(bad)


def test_a_job_whose_report_is_not_kept_gets_a_page_that_says_so():
    # its link (from an old tab, a console line) opened raw JSON in a browser
    root = parse(render.not_kept_html("000001", "a<b>.gcode", 3))
    text = "".join(root.itertext())
    assert "No report kept for job 000001" in text
    assert "(a<b>.gcode)" in text and "newest 3 jobs" in text
