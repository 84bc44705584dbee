"""GET /server/flowloop/profile against Moonraker's own GET /server/database/item.

Both read the same stored record (the profile record in the flowloop
namespace, which the database API may read), so the value is the same size.
Same Moonraker, same run, loopback, keep-alive connections; the two paths are
interleaved round by round so drift hits both, for latency and for throughput
under load alike (measured one after the other in 1.5 s windows, the same code
gave 0.63x to 1.30x on the shared 2-core machine).

Where the time goes (cProfile of Moonraker under this load): about 94 % of a
profile GET is Moonraker and tornado (parsing, routing, writing); the
component's handler is the rest, mostly the name check. It answers with the
profile's JSON-able dict held since the write, not converted per request
(msgspec.to_builtins was ~18 us of it). The database GET reads sqlite in a
thread on every request. Figures are ratios against the
database endpoint (goal: <= 1.2 for latency and for time per request under
concurrent load).
"""

from __future__ import annotations

import http.client
import json
import statistics
import threading
import time

from devtools import stack
from flowloop.material.profile import MAX_POINTS
from tests.bench.size import pick
from tests.samples import make

ROUNDS = pick(6, 1)
PER_ROUND = pick(150, 10)
CLIENTS = pick(4, 2)
LOAD_SECONDS = pick(4.0, 0.5)  # per path, in LOAD_ROUNDS alternating rounds
LOAD_ROUNDS = pick(8, 1)


def timed_gets(port: int, path: str, count: int) -> list:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    times = []
    try:
        for _ in range(count):
            start = time.perf_counter()
            conn.request("GET", path)
            resp = conn.getresponse()
            body = resp.read()
            times.append(time.perf_counter() - start)
            assert resp.status == 200, body[:200]
    finally:
        conn.close()
    return times


def p95_ms(times: list) -> float:
    return sorted(times)[int(len(times) * 0.95)] * 1e3


def throughput(port: int, path: str, seconds: float) -> tuple:
    """(requests, seconds) with CLIENTS keep-alive clients for `seconds`."""
    counts = [0] * CLIENTS
    stop = time.monotonic() + seconds

    def client(i):
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        while time.monotonic() < stop:
            conn.request("GET", path)
            resp = conn.getresponse()
            resp.read()
            assert resp.status == 200
            counts[i] += 1
        conn.close()
    threads = [threading.Thread(target=client, args=(i,)) for i in range(CLIENTS)]
    start = time.monotonic()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return sum(counts), time.monotonic() - start


def interleaved_throughput(port: int, ours: str, theirs: str) -> tuple:
    """Requests per second of both paths, measured in alternating rounds so
    that load from elsewhere on the machine hits both alike."""
    done = {ours: [0, 0.0], theirs: [0, 0.0]}
    for r in range(LOAD_ROUNDS):
        for path in ((ours, theirs) if r % 2 == 0 else (theirs, ours)):
            count, seconds = throughput(port, path, LOAD_SECONDS / LOAD_ROUNDS)
            done[path][0] += count
            done[path][1] += seconds
    return tuple(count / seconds for count, seconds in (done[ours], done[theirs]))


def test_profile_get_latency_and_throughput_vs_database_item(moonraker_venv, bench):
    with stack.printer_stack(with_klippy=False) as ps:
        mr = ps.moonraker
        name = "bench pla 0.8"
        status, body = mr.request("POST", "/server/flowloop/profile",
                                  {"profile": make(name=name, points=[
                                      {"kind": "into_air", "temp_c": 200.0 + i,
                                       "flow_mm3_s": 10.0 + i / 10, "grip": 0.9}
                                      for i in range(20)])})
        assert status == 200, body
        ours = "/server/flowloop/profile?name=bench%20pla%200.8"
        key = "profile:" + name.encode().hex()
        theirs = f"/server/database/item?namespace=flowloop&key={key}"
        a = mr.request("GET", ours)[1]["result"]["profile"]
        b = mr.request("GET", theirs)[1]["result"]["value"]
        assert a == b  # the same value through both endpoints
        bench.figure("profile value size", len(json.dumps(a)), " bytes")
        timed_gets(mr.port, ours, 50)  # warm up both
        timed_gets(mr.port, theirs, 50)
        lat_ours, lat_theirs = [], []
        for r in range(ROUNDS):
            order = [(ours, lat_ours), (theirs, lat_theirs)]
            for path, sink in (order if r % 2 == 0 else order[::-1]):
                sink += timed_gets(mr.port, path, PER_ROUND)
        med_ours = statistics.median(lat_ours) * 1e3
        med_theirs = statistics.median(lat_theirs) * 1e3
        bench.ratio("GET profile median latency", med_ours, med_theirs, " ms",
                    goal="<= 1.2x")
        bench.ratio("GET profile p95 latency", p95_ms(lat_ours), p95_ms(lat_theirs),
                    " ms", goal="<= 1.2x")
        rps_ours, rps_theirs = interleaved_throughput(mr.port, ours, theirs)
        bench.figure(f"GET profile throughput ({CLIENTS} clients)", rps_ours, " req/s")
        bench.figure(f"GET database item throughput ({CLIENTS} clients)", rps_theirs,
                     " req/s")
        bench.ratio("GET profile time per request under load", 1e3 / rps_ours,
                    1e3 / rps_theirs, " ms", goal="<= 1.2x")


def test_profile_list_latency_while_another_client_stores_large_profiles(
        moonraker_venv, bench):
    """A profile store validates off Moonraker's event loop: other clients'
    requests wait for it as little as possible (largest profile: MAX_POINTS)."""
    big = json.dumps({"profile": make(name="big", points=[
        {"kind": "into_air", "temp_c": 200.0 + i / 10, "flow_mm3_s": 10.0 + i / 100,
         "grip": 0.9} for i in range(MAX_POINTS)])}).encode()
    with stack.printer_stack(with_klippy=False) as ps:
        port = ps.moonraker.port
        stop = threading.Event()

        def store_big():
            conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
            while not stop.is_set():
                conn.request("POST", "/server/flowloop/profile", big,
                             {"Content-Type": "application/json"})
                resp = conn.getresponse()
                resp.read()
                assert resp.status == 200
            conn.close()
        path = "/server/flowloop/profiles"
        timed_gets(port, path, 50)
        idle = timed_gets(port, path, 300)
        writer = threading.Thread(target=store_big)
        writer.start()
        try:
            busy = timed_gets(port, path, 300)
        finally:
            stop.set()
            writer.join()
        bench.ratio("GET profiles median latency while 1000-point profiles are "
                    "stored", statistics.median(busy) * 1e3,
                    statistics.median(idle) * 1e3, " ms")
        bench.ratio("GET profiles p95 latency while 1000-point profiles are stored",
                    p95_ms(busy), p95_ms(idle), " ms")
