"""Nozzle health in Moonraker: each job's estimate stored per hotend and
profile, the history served at /server/flowloop/nozzle_health, a hotend
that degrades print after print warned through an announcement and
notify_flowloop_nozzle_health, a healthy one never."""

from __future__ import annotations

import copy
import functools
import xml.etree.ElementTree as ET

import pytest

from flowloop.control import nozzle_health as nh
from tests.nozzle_prints import PROFILE, simulate_print
from tests.samples import twin_known

PRINTER_STACK = {"with_klippy": False, "moonraker_conf": "hotend: v6-0.4\n"}
# a profile name that would forge a console line or carry markup if shown raw
MARKUP = "PETG <img src=x onerror=alert(1)> & 'co'"
NOZZLE = "/server/flowloop/nozzle_health"


def prepare_printer(ps):
    """Evidence is kept for stored profiles: the twin's, and one named MARKUP."""
    for name in ("known", MARKUP):
        data = twin_known()
        data["identity"]["name"] = name
        status, body = ps.moonraker.request("POST", "/server/flowloop/profile",
                                            {"profile": data})
        assert status == 200, body


@functools.cache
def _evidence(ratio, seed):
    return nh.evidence_of(simulate_print(ratio, seed=seed), PROFILE).to_dict()


def evidence(ratio, seed, name="known"):
    """A print's evidence under the twin's profile, stored as `name`."""
    return {**copy.deepcopy(_evidence(ratio, seed)), "profile": name}


def post(ps, job_id, ratio, seed, name="known"):
    return ps.moonraker.request("POST", NOZZLE, {
        "job_id": job_id, "evidence": evidence(ratio, seed, name)})


def histories(ps):
    status, body = ps.moonraker.request("GET", NOZZLE)
    assert status == 200, body
    return body["result"]["histories"]


def test_a_degrading_hotend_is_warned_with_its_history(printer, rpc):
    verdicts = []
    for k in range(6):
        status, body = post(printer, f"{k + 1:06X}", 1.0 - 0.02 * k, k)
        assert status == 200, body
        verdicts.append(body["result"]["verdict"])
    assert [v["warn"] for v in verdicts] == [False] * 4 + [True, True]
    status, body = printer.moonraker.request("GET", "/server/flowloop/nozzle_health")
    assert status == 200, body
    result = body["result"]
    assert result["hotend"] == "v6-0.4"
    [history] = result["histories"]
    assert history["profile"] == "known"
    assert [p["job_id"] for p in history["prints"]] == [
        "000001", "000002", "000003", "000004", "000005", "000006"]
    assert history["prints"][0]["ratio"] is None
    assert "kept up" in history["prints"][0]["reason"]
    assert abs(history["prints"][5]["ratio"] - 0.90) < 0.01
    assert history["verdict"]["rule"] == "persistent"
    status, body = printer.moonraker.request("GET", "/server/announcements/list")
    entries = [e for e in body["result"]["entries"] if e["feed"] == "flowloop"]
    assert len(entries) == 1, entries          # once, when it started
    assert 'profile "known"' in entries[0]["title"]
    assert "92%" in entries[0]["description"]
    assert "?." not in entries[0]["description"]
    # the announcement links the health plot, a path from the UI's origin
    assert entries[0]["url"] == (
        "/server/flowloop/nozzle_health/plot?profile=known&hotend=v6-0.4")
    status, svg = printer.moonraker.request("GET", entries[0]["url"])
    assert status == 200 and "<svg" in svg

    async def steps(client):
        await client.call("server.connection.identify", client_name="test",
                          version="1", type="web", url="none")
        await client.in_thread(lambda: post(printer, "000007", 0.88, 7))
        return await client.notification("notify_flowloop_nozzle_health")
    note = rpc(printer.moonraker.port, steps)
    assert "melt capacity 88% of the profile" in note["params"][0]["text"]
    status, svg = printer.moonraker.request(
        "GET", "/server/flowloop/nozzle_health/plot?profile=known")
    assert status == 200
    assert len(ET.fromstring(svg).findall(".//{*}circle[@class='estimate']")) == 6


def test_no_estimate_and_bad_evidence_are_one_line(printer):
    status, body = printer.moonraker.request(
        "POST", "/server/flowloop/nozzle_health", {"job_id": "0000FF"})
    assert status == 200 and body["result"]["verdict"] is None
    assert "no active profile" in body["result"]["entry"]["reason"]
    status, body = printer.moonraker.request(
        "POST", "/server/flowloop/nozzle_health",
        {"job_id": "0000FE", "evidence": {"version": 1}})
    assert status == 400 and "not nozzle evidence" in body["error"]["message"]
    status, body = printer.moonraker.request(
        "GET", "/server/flowloop/nozzle_health/plot?profile=nothing")
    assert status == 404


@pytest.mark.parametrize("change, says", [
    ({"min_grip": "nan"}, "min_grip must be a number"),
    ({"noise_sum": 1e308}, "noise_sum must be a number within"),
    ({"noise_sum_sq": -1}, "noise_sum_sq is a sum of squares"),
    ({"windows": "12"}, "windows must be a whole number"),
    ({"profile": "x" * 100_000}, "longer than 128"),
    ({"profile": "never stored"}, 'no profile named "never stored"'),
    ({"job_id": 12}, "job id int is not a job of Moonraker's history"),
    ({"job_id": "0000\ufb00"}, "is not a job of Moonraker's history"),
    ({"job_id": "A" * 100_000}, "is not a job of Moonraker's history"),
])
def test_a_post_is_checked_whole_and_a_refusal_stores_nothing(printer, change,
                                                              says):
    before = histories(printer)
    body = {"job_id": "0000A1", "evidence": evidence(0.9, 1)}
    if "job_id" in change:
        body.update(change)
    else:
        body["evidence"].update(change)
    status, answer = printer.moonraker.request("POST", NOZZLE, body)
    assert status == 400, answer
    assert says in answer["error"]["message"], answer
    assert histories(printer) == before
    # and the next good print is judged as ever
    status, answer = post(printer, "0000A2", 0.9, 2, MARKUP)
    assert status == 200, answer


def test_a_job_posted_again_is_one_record_and_warns_no_one(printer):
    for _ in range(3):
        status, body = post(printer, "0000B1", 0.85, 11, MARKUP)
        assert status == 200, body
    [history] = [h for h in histories(printer) if h["profile"] == MARKUP]
    assert [p["job_id"] for p in history["prints"]].count("0000B1") == 1
    assert not history["verdict"]["warn"]


def test_names_in_a_warning_are_one_line_without_markup(printer, rpc):
    async def steps(client):
        await client.call("server.connection.identify", client_name="test",
                          version="1", type="web", url="none")
        for k in range(5):
            await client.in_thread(functools.partial(
                post, printer, f"0000C{k}", 0.88, 20 + k, MARKUP))
        note = await client.notification("notify_flowloop_nozzle_health")
        console = await client.notification(
            "notify_gcode_response", where=lambda p: "nozzle health" in p[0])
        return note, console
    note, console = rpc(printer.moonraker.port, steps)
    title = note["params"][0]["title"]
    line = console["params"][0]
    assert '"PETG \\u003cimg src=x onerror=alert(1)\\u003e' in title, title
    for shown in (title, line):
        assert not set("<>&\n") & set(shown), shown
    status, body = printer.moonraker.request("GET", "/server/announcements/list")
    [entry] = [e for e in body["result"]["entries"]
               if e["feed"] == "flowloop" and "PETG" in e["title"]]
    assert entry["title"] == title


def test_delete_removes_one_profiles_history(printer):
    assert post(printer, "0000D1", 0.9, 30)[0] == 200
    assert post(printer, "0000D2", 0.9, 31, MARKUP)[0] == 200
    status, body = printer.moonraker.request(
        "DELETE", f"{NOZZLE}?profile=known&hotend=v6-0.4")
    assert status == 200, body
    assert body["result"]["action"] == "deleted" and body["result"]["prints"] >= 1
    assert [h["profile"] for h in histories(printer)] == [MARKUP]
    status, body = printer.moonraker.request("DELETE", f"{NOZZLE}?profile=known")
    assert status == 404, body
    assert printer.moonraker.request(
        "GET", f"{NOZZLE}/plot?profile=known")[0] == 404
    # the profile itself is kept
    assert printer.moonraker.request(
        "GET", "/server/flowloop/profile?name=known")[0] == 200
