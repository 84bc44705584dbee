"""A job printed through Moonraker gets a flow report: listed under its job id
in /server/flowloop/reports and served as HTML by /server/flowloop/report.
A job cancelled half-way gets one that says so; a report that cannot be
stored is one line in moonraker.log and the job's history is kept."""

from __future__ import annotations

import asyncio
import shutil
import time
import xml.etree.ElementTree as ET

import pytest

from devtools import stack
from tests.moonraker.conftest import Rpc
from tests.moonraker.test_page import REALTIME_CFG

# klippy paced to the wall clock. Skipped: on the realtime batch-mode klippy
# of this tree (2026-11-26, with or without flowloop's own subscription)
# Moonraker's subscribers get no print_stats update until the print has
# ended: job_state infers the start at 'complete', with no file name, so the
# job's report has no samples. Earlier the same day, with a client
# subscribed and polling (print_watched), the job started on time and its
# report was stored and listed. Unskip once updates flow during a print.
# The same path runs on klippy in normal mode (the simulated MCU) in
# tests/fil/test_fil_report.py: a completed and a cancelled job.
pytestmark = [pytest.mark.alone, pytest.mark.skip(
    reason="realtime klippy: Moonraker gets no status update during a print")]

# klippy's config in the printer fixture (tests/moonraker/conftest.py): the
# page's printer on klippy paced to the clock, as its live test runs it
PRINTER_CFG = REALTIME_CFG
PRINTER_STACK = {"realtime": True,
                 "moonraker_conf": "number_of_reports_to_keep: 2\n"}
SVG = "{http://www.w3.org/2000/svg}"


def gcode_file(layers: int, seconds_per_layer: float) -> str:
    """Lines along X at 5 mm^3/s-ish, one per layer, Z up 0.2 mm a layer."""
    out = ["G28", "M83", "SET_HEATER_TEMPERATURE HEATER=extruder TARGET=210",
           "G1 X10 Y10 Z0.2 F3000"]
    for layer in range(1, layers + 1):
        out.append(f"SET_PRINT_STATS_INFO CURRENT_LAYER={layer}")
        speed = 40.0 / seconds_per_layer
        # a 0.4 x 0.2 line 40 mm long, from X10 to X50 and back
        e = 40 * 0.4 * 0.2 / 2.405
        out.append(f"G1 X{50 if layer % 2 else 10} E{e:.3f} F{speed * 60:.0f}")
        out.append(f"G1 Z{0.2 * (layer + 1):.1f} F600")
    return "\n".join(out) + "\n"


def find_job(ps, filename, states):
    status, body = ps.moonraker.request("GET", "/server/history/list?limit=5")
    assert status == 200, body
    for job in body["result"]["jobs"]:
        if job["filename"] == filename and job["status"] in states:
            return job
    return None


def print_watched(ps, filename, states, cancel_after_s=None, timeout=90.0):
    """Print a file while a client is subscribed to print_stats and polls
    klippy (as a frontend does), until the history has its job in one of
    `states`. On the realtime batch-mode klippy, Moonraker's own subscribers
    (job_state, history, flowloop) were seen to get no update with neither
    (its history then records no job, 2026-11-26); on a printer they do."""
    async def steps(client):
        await client.call("printer.objects.subscribe",
                          objects={"print_stats": ["state"]})
        await client.call("printer.gcode.script",
                          script=f"SDCARD_PRINT_FILE FILENAME={filename}")
        start = time.monotonic()
        cancelled = cancel_after_s is None
        while time.monotonic() - start < timeout:
            await client.in_thread(lambda: ps.query("print_stats"))
            if not cancelled and time.monotonic() - start > cancel_after_s:
                await client.call("printer.print.cancel")
                cancelled = True
            job = await client.in_thread(lambda: find_job(ps, filename, states))
            if job:
                return job
            await asyncio.sleep(0.5)
        return None

    async def main():
        async with Rpc(f"ws://127.0.0.1:{ps.moonraker.port}/websocket") as client:
            return await steps(client)
    job = asyncio.run(main())
    assert job is not None, (f"no {states} job for {filename} in the history: "
                             + ps.moonraker.log_tail(3000) + ps.klippy.log_tail(3000))
    return job


def reports(ps):
    status, body = ps.moonraker.request("GET", "/server/flowloop/reports")
    assert status == 200, body
    return body["result"]


def report_of(ps, job_id):
    def ready():
        return [r for r in reports(ps)["reports"] if r["job_id"] == job_id] or None
    (entry,) = stack.wait_until(ready, 10.0, interval=0.25)
    return entry


def fetch_html(ps, job_id):
    status, body = ps.moonraker.request(
        "GET", f"/server/flowloop/report?job_id={job_id}")
    assert status == 200, body
    return ET.fromstring(body.split("\n", 1)[1])


def lacks(root):
    (el,) = [e for e in root.iter() if e.get("id") == "lacks"]
    return [li.text for li in el] if el.tag == "ul" else []


def test_a_printed_job_gets_a_report_listed_and_served(printer):
    printer.moonraker.upload("lines.gcode", gcode_file(6, 2.0).encode())
    job = print_watched(printer, "lines.gcode", ("completed",))
    entry = report_of(printer, job["job_id"])
    assert entry["filename"] == "lines.gcode" and entry["state"] == "completed"
    assert entry["duration_s"] > 5
    root = fetch_html(printer, job["job_id"])
    series = {e.get("id") for e in root.iter() if e.get("class") == "series"
              and len(e)}
    assert {"commanded_flow", "measured_flow", "temp"} <= series
    bars = [r for r in root.iter(f"{SVG}rect") if r.get("class") == "layer"]
    assert len(bars) >= 5   # the file's layers, from SET_PRINT_STATS_INFO
    assert not any("no flow sensor" in x for x in lacks(root))
    # and the dump is in the data path, for `flowloop report` offline
    stored = printer.data_dir / "flowloop" / "reports"
    assert (stored / f"{job['job_id']}.json").is_file()


def test_a_cancelled_job_gets_a_report_that_says_so(printer):
    printer.moonraker.upload("long.gcode", gcode_file(40, 2.0).encode())
    job = print_watched(printer, "long.gcode", ("cancelled",), cancel_after_s=4)
    report_of(printer, job["job_id"])
    said = lacks(fetch_html(printer, job["job_id"]))
    assert any("did not complete (cancelled" in x for x in said), said


def test_only_the_newest_reports_are_kept_and_an_unknown_job_is_404(printer):
    for name in ("a.gcode", "b.gcode"):
        printer.moonraker.upload(name, gcode_file(2, 1.0).encode())
        job = print_watched(printer, name, ("completed",))
        report_of(printer, job["job_id"])
    listed = reports(printer)
    assert listed["number_of_reports_to_keep"] == 2
    assert [r["filename"] for r in listed["reports"]] == ["b.gcode", "a.gcode"]
    status, body = printer.moonraker.request(
        "GET", "/server/flowloop/report?job_id=FFFFFF")
    assert status == 404 and 'no flow report for job "FFFFFF"' in str(body)
    status, body = printer.moonraker.request(
        "GET", "/server/flowloop/report?job_id=../x")
    assert status == 400


def test_a_report_that_cannot_be_stored_is_one_line_and_the_history_is_kept(
        printer):
    folder = printer.data_dir / "flowloop" / "reports"
    shutil.rmtree(folder, ignore_errors=True)
    folder.write_text("not a folder: every write fails as on a full disk")
    try:
        printer.moonraker.upload("c.gcode", gcode_file(2, 1.0).encode())
        job = print_watched(printer, "c.gcode", ("completed",))
        said = f"flow report of job {job['job_id']} was not stored"

        def logged():
            log = printer.moonraker.log_path.read_text()
            return [x for x in log.splitlines() if said in x]
        lines = stack.wait_until(logged, 5.0)
        assert len(lines) == 1, lines
        log = printer.moonraker.log_path.read_text()
        assert "Traceback" not in log.split(lines[0], 1)[1][:200]
        assert printer.moonraker.request("GET", "/server/info")[0] == 200
    finally:
        folder.unlink()
