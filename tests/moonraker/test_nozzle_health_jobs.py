"""Nozzle health in Moonraker: each job's estimate stored per hotend and
profile, the history served at /server/flowloop/nozzle_health, a hotend
that degrades print after print warned through an announcement and
notify_flowloop_nozzle_health, a healthy one never."""

from __future__ import annotations

import xml.etree.ElementTree as ET

from flowloop.control import nozzle_health as nh
from tests.nozzle_prints import PROFILE, simulate_print

PRINTER_STACK = {"with_klippy": False, "moonraker_conf": "hotend: v6-0.4\n"}


def evidence(ratio, seed):
    return nh.evidence_of(simulate_print(ratio, seed=seed), PROFILE).to_dict()


def post(ps, job_id, ratio, seed):
    return ps.moonraker.request("POST", "/server/flowloop/nozzle_health",
                                {"job_id": job_id, "evidence": evidence(ratio, seed)})


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
    assert "profile known" in entries[0]["title"]
    assert "92%" in entries[0]["description"]

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
