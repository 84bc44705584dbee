"""What a farm's printers ask of Spoolman (issue #26), counted in Spoolman's
own access log against a real Spoolman (devtools/spoolman.py) and three real
Moonrakers with flowloop (one hotend key), and the same spool loads on a
Moonraker without flowloop's link as the baseline (Moonraker's own
[spoolman] asks too). Figures: requests per spool load and per stored
profile, the time from loading a spool to its profile being active, and
what that makes for a farm of 100 printers (docs/material_profiles.md).
"""

from __future__ import annotations

import re
import shutil
import statistics
import time

import pytest

from devtools import spoolman, stack
from tests.bench.size import pick
from tests.samples import make

pytestmark = pytest.mark.bench

ACCESS = re.compile(r'"(GET|POST|PATCH|PUT|DELETE) (/api/v1/[^ ?"]*)')
LOADS = pick(5, 2)  # the per-store figure of later stores needs two


def _requests(sm) -> list:
    text = (sm.data_dir / "logs" / "spoolman.log").read_text()
    return [m.groups() for m in ACCESS.finditer(text)]


def _active(mr):
    result = mr.request("GET", "/server/flowloop/profiles")[1]["result"]
    return (result["active"].get("extruder") or {}).get("name")


def _counted(sm, action, settle_s=1.0, until=None):
    """Spoolman requests (method, path kind) an action caused (once `until`
    holds, if given, and settle_s later)."""
    before = len(_requests(sm))
    action()
    if until is not None:
        stack.wait_until(until, 10.0, 0.005)
    time.sleep(settle_s)
    return [(m, re.sub(r"/\d+", "/ID", p)) for m, p in _requests(sm)[before:]]


def test_requests_to_spoolman_per_spool_load_and_per_store(moonraker_venv, bench):
    reason = spoolman.missing_spoolman_reason()
    if reason:
        pytest.skip(reason)
    data_dir = stack.short_tempdir("fl-bench-spool-")
    sm = spoolman.Spoolman(data_dir / "spoolman")
    printers = []
    try:
        sm.wait_ready()
        for i, link in enumerate((True, True, True, False)):
            conf = (("spoolman_link: True\nhotend: revo_0.4\n" if link else "")
                    + f"\n[spoolman]\nserver: {sm.url}\n")
            printers.append(stack.Moonraker(moonraker_venv, data_dir / f"p{i}",
                                            extra_conf=conf))
        for mr in printers:
            mr.wait_ready()
        time.sleep(2.0)   # Moonrakers' own connection to Spoolman settles
        filaments = [sm.add_filament(f"PLA {i}") for i in range(LOADS)]
        spools = [sm.add_spool(f["id"])["id"] for f in filaments]
        store = []
        for i, f in enumerate(filaments):
            data = make(name=f"pla {i}", identity={"spoolman_filament_id": f["id"]})
            store.append(_counted(sm, lambda d=data: printers[0].request(
                "POST", "/server/flowloop/profile", {"profile": d})))
        loads, waits, baseline = [], [], []
        for i, spool in enumerate(spools):
            start = time.monotonic()

            def active(i=i, start=start):
                if _active(printers[1]) == f"pla {i}":
                    waits.append(time.monotonic() - start)
                    return True
                return False
            loads.append(_counted(sm, lambda s=spool: printers[1].request(
                "POST", "/server/spoolman/spool_id", {"spool_id": s}),
                until=active))
            baseline.append(_counted(sm, lambda s=spool: printers[3].request(
                "POST", "/server/spoolman/spool_id", {"spool_id": s})))
        per_store = statistics.mean(len(r) for r in store)
        per_load = statistics.mean(len(r) for r in loads)
        per_base = statistics.mean(len(r) for r in baseline)
        print("store:", store[0], "\nload:", loads[0], "\nbaseline:", baseline[0])
        bench.figure("spoolman requests per stored profile (first write"
                     " registers the field)", len(store[0]))
        bench.figure("spoolman requests per stored profile (later ones)",
                     statistics.mean(len(r) for r in store[1:]))
        bench.figure("spoolman requests per spool load, printer with flowloop",
                     per_load)
        bench.figure("spoolman requests per spool load, Moonraker's [spoolman]"
                     " alone (its websocket carries the rest)", per_base)
        bench.figure("spool load to its profile active, median",
                     statistics.median(waits) * 1e3, " ms")
        # a farm of 100 printers, a spool change per printer per hour and a
        # stored profile per printer per day
        farm = 100 * per_load / 3600 + 100 * per_store / 86400
        bench.figure("a farm of 100 printers (1 spool change/h, 1 profile/day"
                     " each): flowloop's requests to Spoolman", farm, " per s")
        assert per_store >= 4 and per_load >= 1
    finally:
        for mr in printers:
            mr.stop()
        sm.stop()
        shutil.rmtree(data_dir, ignore_errors=True)
