"""The flow report endpoints of a Moonraker with flowloop: the stored
reports listed newest first, one served as HTML, bad or unknown job ids
refused in one line. (Jobs printed through it: tests/fil/test_fil_report.py.)"""

from __future__ import annotations

import pytest

from flowloop.report import dump, job_figures, render
from flowloop.report.recorder import Job, Recorder, Sample

PRINTER_STACK = {"with_klippy": False,
                 "moonraker_conf": "number_of_reports_to_keep: 3\n"}


def stored(ps, job_id, filename, state="completed"):
    rec = Recorder(job=Job(job_id=job_id, filename=filename))
    for i in range(40):
        rec.sample(Sample(i / 4, commanded_flow_mm3_s=5.0, measured_flow_mm3_s=5.0,
                          grip=1.0, layer=1))
    rec.finish(state)
    folder = ps.data_dir / "flowloop" / "reports"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{job_id}.json").write_text(dump.dumps(rec))
    (folder / f"{job_id}.html").write_text(render.html(rec))


def get(ps, path):
    return ps.moonraker.request("GET", path)


def test_no_report_yet_is_an_empty_list(printer):
    status, body = get(printer, "/server/flowloop/reports")
    assert status == 200, body
    assert body["result"] == {"reports": [], "recording": None,
                              "number_of_reports_to_keep": 3}


def test_stored_reports_are_listed_newest_first_and_served(printer):
    stored(printer, "000009", "a.gcode")
    stored(printer, "00000A", "b.gcode", "cancelled")
    (printer.data_dir / "flowloop" / "reports" / "00000B.json").write_text("{}")
    reports = get(printer, "/server/flowloop/reports")[1]["result"]["reports"]
    assert [r["job_id"] for r in reports] == ["00000B", "00000A", "000009"]
    assert "not a flowloop flow report dump" in reports[0]["problem"]
    assert reports[1]["state"] == "cancelled"
    assert any("did not complete (cancelled" in x for x in reports[1]["lacks"])
    status, text = get(printer, "/server/flowloop/report?job_id=00000a")
    assert status == 200 and text.startswith("<!DOCTYPE html>")
    assert "Flow report: b.gcode" in text


@pytest.mark.parametrize("query, code, says", [
    ("job_id=FFFFFF", 404, 'no flow report for job "FFFFFF"'),
    ("job_id=../x", 400, 'job id "../x" is not a job of Moonraker\'s history'),
    ("", 400, "the job id is missing (argument 'job_id')"),
])
def test_a_bad_or_unknown_job_id_is_refused_in_one_line(printer, query, code, says):
    status, body = get(printer, f"/server/flowloop/report?{query}")
    assert status == code and says in body["error"]["message"], body


def test_the_jobs_figures_are_numeric_history_fields_with_totals(printer):
    # each job's history entry gets flowloop's figures as numbers with units
    # (Mainsail renders every auxiliary value as a number); the report is no
    # history field: it is served at an absolute /server/ path instead
    status, body = printer.moonraker.request("POST", "/server/history/reset_totals")
    assert status == 200, body
    status, body = get(printer, "/server/history/totals")
    assert status == 200, body
    totals = {t["field"]: t for t in body["result"]["auxiliary_totals"]
              if t["provider"] == job_figures.PROVIDER}
    # summed figures only: Mainsail shows a total's sum, never a maximum
    assert totals == {
        "under_extruded": {"provider": "sensor flowloop", "field": "under_extruded",
                           "maximum": None, "total": 0},
        "limiter_slowed": {"provider": "sensor flowloop", "field": "limiter_slowed",
                           "maximum": None, "total": 0},
    }, totals
    # named in the parsed configuration as a [sensor flowloop] section's
    # history fields: where Mainsail takes their names and units from
    status, body = get(printer, "/server/config")
    assert status == 200, body
    assert body["result"]["config"]["sensor flowloop"] == \
        job_figures.mainsail_history_fields()
    # and no such section in moonraker.conf (Moonraker's sensor component
    # would warn of an unknown sensor type)
    assert "sensor flowloop" not in body["result"]["orig"]
    status, body = get(printer, "/server/info")
    assert not [w for w in body["result"]["warnings"] if "sensor" in w], body
