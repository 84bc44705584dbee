"""A job printed through a real Moonraker on the fil printer (klippy in
normal mode on the simulated atmega2560, the EMS22 read by the firmware) gets
a flow report: listed under its job id in /server/flowloop/reports, served as
HTML by /server/flowloop/report, with the sensor's flow, the layers and the
job's file. This is the path a user's print takes; the moonraker tier's
job-through tests cannot take it (Moonraker sees no job start on a batch-mode
klippy)."""

from __future__ import annotations

import time
import xml.etree.ElementTree as ET

import pytest

from devtools.demo_flowrate_limiter import WEAK_PROFILE
from flowloop.report import job_figures
from tests.fil.conftest import (
    JOB_SECTIONS,
    ended_job,
    fil_moonraker,
    job_report,
    start_job,
    wait_for,
)

# The thermistor pin reads this (the harness holds it): the profile's range
HOTEND_C = 215.0
LAYERS = 4
KEEP = 2   # number_of_reports_to_keep
SVG = "{http://www.w3.org/2000/svg}"


def gcode_file(layers: int = LAYERS) -> str:
    """Layers of 8 mm of filament at 2 mm/s (4.8 mm^3/s), 4 s each: below
    what the weak profile melts at HOTEND_C, so the limiter lets it."""
    out = ["M83", f"SET_PRINT_STATS_INFO TOTAL_LAYER={layers}"]
    for layer in range(1, layers + 1):
        out += [f"SET_PRINT_STATS_INFO CURRENT_LAYER={layer}", "G1 E8 F120"]
    return "\n".join(out) + "\n"


# The model starts at the profile's line (no first print's climb): these
# jobs are about the report and Moonraker's nozzle health, which stores
# what the model believes and carries it to the next activation; a
# climbing model believes only a lower bound, and nozzle health is told
# none (tests/fil/test_fil_worn_nozzle.py prints with the climb)
REPORT_SECTIONS = JOB_SECTIONS + "climb_from: 1\n"


@pytest.fixture(scope="module")
def mr(fil_build, moonraker_venv):
    """Moonraker on the fil printer's klippy, its gcodes folder the
    printer's virtual_sdcard, the weak profile active."""
    with fil_moonraker(fil_build, moonraker_venv, WEAK_PROFILE,
                       sections=REPORT_SECTIONS,
                       extra_conf=f"number_of_reports_to_keep: {KEEP}\n",
                       hotend_temp_c=HOTEND_C) as (_, server):
        yield server


def _print_job(mr, name, states, cancel_after_s=None, layers=LAYERS):
    """Upload and print a file; its job in the history once it ended."""
    start_job(mr, name, gcode_file(layers))
    if cancel_after_s is not None:
        time.sleep(cancel_after_s)
        # the running job's report so far, served while it prints
        recording = mr.request("GET", "/server/flowloop/reports")[1]["result"][
            "recording"]
        status, live = mr.request("GET",
                                  f"/server/flowloop/report?job_id={recording}")
        assert status == 200 and name in live, live[:300]
        status, body = mr.request("POST", "/printer/print/cancel")
        assert status == 200, body
    return ended_job(mr, name, states)


def _print(mr, name, states, cancel_after_s=None):
    """_print_job; (its job, its report's summary, the report's HTML)."""
    job = _print_job(mr, name, states, cancel_after_s)
    summary = job_report(mr, job)
    status, page = mr.request("GET", f"/server/flowloop/report?job_id={job['job_id']}")
    assert status == 200, page
    assert "flowloop: the flow report" not in mr.log_path.read_text()
    return job, summary, ET.fromstring(page)


def test_a_job_printed_through_moonraker_gets_a_flow_report(mr):
    job, summary, root = _print(mr, "report_job.gcode", ("completed",))
    assert summary["filename"] == "report_job.gcode", summary
    assert summary["state"] == "completed", summary
    # the print lasts about 11 s, sampled throughout: no gap, no fault
    assert summary["duration_s"] > 8, summary
    assert summary["lost_s"] == 0, summary
    # 32 mm commanded at the model's grip 1.0: nothing under-extruded
    assert summary["under_extruded_mm"] == pytest.approx(0.0, abs=0.5), summary
    # what the report lacks: only what this printer has not (no autotemp)
    assert not any("sensor" in why or "file" in why or "layer" in why
                   for why in summary["lacks"]), summary
    text = "".join(root.itertext())
    assert "report_job.gcode" in text
    assert list(root.iter(f"{SVG}polyline")), "no series drawn"
    # the job in Moonraker's history holds flowloop's figures as numbers with
    # units (what Mainsail and Fluidd show as their own), the report's
    # figures among them; no string field (Mainsail would show "NaN"); the
    # nozzle not judged yet is [] (both UIs' "--")
    status, body = mr.request("GET", f"/server/history/job?uid={job['job_id']}")
    assert status == 200, body
    figures = {f["name"]: f for f in body["result"]["job"]["auxiliary_data"]
               if f["provider"] == job_figures.PROVIDER}
    assert set(figures) == {"under_extruded", "lowest_grip", "limiter_slowed",
                            "peak_flow", "melt_ratio"}, figures
    for field in figures.values():
        assert field["units"] and (field["value"] == [] or isinstance(
            field["value"], (int, float))), field
    assert figures["under_extruded"]["value"] == pytest.approx(
        summary["under_extruded_mm"], abs=0.05)
    assert figures["limiter_slowed"]["value"] == pytest.approx(
        summary["slowed_s"], abs=0.2)
    assert figures["peak_flow"]["value"] > 0, figures
    # its grip judged throughout (the default 1.25 mm windows take 0.6 s at
    # this flow; a window over 2 s is not judged): the model's grip 1.0
    print("lowest grip", figures["lowest_grip"]["value"])
    assert figures["lowest_grip"]["value"] >= 97, figures


def test_a_job_cancelled_half_way_gets_a_report_that_says_so(mr):
    job, summary, root = _print(mr, "cancelled_job.gcode", ("cancelled",),
                                cancel_after_s=5.0)
    assert summary["state"] == "cancelled", summary
    assert any("cancelled" in why for why in summary["lacks"]), summary
    assert "cancelled" in "".join(root.itertext())


def test_each_job_is_judged_for_nozzle_health(mr):
    # Moonraker asked klippy's limiter for its grip evidence at the jobs'
    # start and end (flowrate_limiter/nozzle_evidence) and stored what the
    # difference says under the active profile; a short print is no
    # estimate, and says why
    status, body = mr.request("GET", "/server/flowloop/nozzle_health")
    assert status == 200, body
    histories = body["result"]["histories"]
    assert [h["profile"] for h in histories] == ["weak"], histories
    prints = histories[0]["prints"]
    jobs = mr.request("GET", "/server/history/list?limit=5")[1]["result"]["jobs"]
    assert [p["job_id"] for p in prints] == sorted(j["job_id"] for j in jobs)
    for p in prints:
        assert p["ratio"] is not None or p["reason"], p
    assert not histories[0]["verdict"]["warn"]
    # beside each, what the limiter's model believed at the job's end: these
    # jobs kept up below the profile's capacity, so what it was seeded with
    limiter = _limiter(mr)
    assert limiter["seed_melt_ratio"] is None, limiter
    for p in prints:
        assert p["model_ratio"] == pytest.approx(
            limiter["model"]["melt_ratio"], abs=1e-4), p
    # the next activation carries it to klippy: the model starts from it
    status, body = mr.request("POST", "/server/flowloop/profile/activate",
                              {"name": "weak"})
    assert status == 200 and body["result"]["sent_to_klippy"], body
    assert _limiter(mr)["seed_melt_ratio"] == prints[-1]["model_ratio"]


def _limiter(mr):
    status, body = mr.request("GET", "/printer/objects/query?flowrate_limiter")
    assert status == 200, body
    return body["result"]["status"]["flowrate_limiter"]


def test_a_report_that_cannot_be_stored_is_one_line_and_the_history_is_kept(mr):
    folder = mr.data_dir / "flowloop" / "reports"
    kept = folder.with_name("reports.kept")
    folder.mkdir(parents=True, exist_ok=True)
    folder.rename(kept)
    folder.write_text("not a folder: every write fails as on a full disk")
    try:
        job = _print_job(mr, "unstored.gcode", ("completed",), layers=1)
        said = f"flow report of job {job['job_id']} was not stored"

        def logged():
            return [x for x in mr.log_path.read_text().splitlines() if said in x]
        (line,) = wait_for("the line in moonraker.log", logged, 10)
        after = mr.log_path.read_text().split(line, 1)[1]
        assert "Traceback" not in after[:300], after[:300]
        assert mr.request("GET", "/server/info")[0] == 200
    finally:
        folder.unlink()
        kept.rename(folder)


def test_only_the_newest_reports_are_kept_and_an_unknown_job_is_404(mr):
    job = _print_job(mr, "newest.gcode", ("completed",), layers=1)

    def pruned():
        listed = mr.request("GET", "/server/flowloop/reports")[1]["result"]
        names = [r["filename"] for r in listed["reports"]]
        return names if names[:1] == ["newest.gcode"] else None
    names = wait_for("the newest job's report", pruned, 15)
    # the completed and cancelled jobs of the tests above, and this one:
    # number_of_reports_to_keep 2 keeps the newest two
    assert names == ["newest.gcode", "cancelled_job.gcode"], names
    assert job["job_id"] in mr.request("GET", "/server/flowloop/reports")[1][
        "result"]["reports"][0]["job_id"]
    status, body = mr.request("GET", "/server/flowloop/report?job_id=FFFFFF")
    assert status == 404 and 'no flow report for job "FFFFFF"' in str(body)
    status, body = mr.request("GET", "/server/flowloop/report?job_id=../x")
    assert status == 400
