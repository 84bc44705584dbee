"""Material profiles served by the real Moonraker (no klippy): HTTP, JSON-RPC,
names, errors, notifications, plots, persistence, concurrency, authorization.
The Spoolman link runs against a real Spoolman in test_spoolman.py."""

from __future__ import annotations

import json
import re
import shutil
import xml.etree.ElementTree as ET
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from urllib.parse import quote

import pytest

from devtools import stack
from flowloop.material.profile import MAX_POINTS
from tests.samples import make


class Server:
    """One Moonraker on a fixed port and data dir, so it can be restarted."""

    def __init__(self, venv, data_dir: Path, **kw):
        self.venv, self.data_dir, self.kw = venv, data_dir, kw
        self.port = stack.free_port()
        self.mr = None
        self.start()

    def start(self):
        self.mr = stack.Moonraker(self.venv, self.data_dir, port=self.port, **self.kw)
        try:
            self.mr.wait_ready()
        except Exception:
            self.mr.stop()
            raise

    def stop(self):
        self.mr.stop()

    def restart(self):
        self.stop()
        self.start()

    def request(self, method, path, body=None):
        return self.mr.request(method, path, body)


@pytest.fixture(scope="module")
def server(moonraker_venv):
    data_dir = stack.short_tempdir("fl-prof-")
    srv = Server(moonraker_venv, data_dir)
    yield srv
    srv.stop()
    shutil.rmtree(data_dir, ignore_errors=True)


def store(srv, **kw):
    status, body = srv.request("POST", "/server/flowloop/profile",
                               {"profile": make(**kw)})
    assert status == 200, body
    return body["result"]


def listed_names(srv):
    body = srv.request("GET", "/server/flowloop/profiles")[1]
    return {p["name"] for p in body["result"]["profiles"]}


def get(srv, name):
    return srv.request("GET", "/server/flowloop/profile?name=" + quote(name, safe=""))


# --- CRUD over HTTP ---------------------------------------------------------


def test_crud_over_http(server):
    assert store(server, name="crud-http") == {"name": "crud-http", "action": "created",
                                               "deactivated": []}
    status, body = get(server, "crud-http")
    assert status == 200
    assert body["result"]["profile"]["lines"]["into_air"]["temp_c"] == 171.6312
    assert store(server, name="crud-http",
                 bounds=(195.0, 215.0, 255.0))["action"] == "updated"
    assert get(server, "crud-http")[1]["result"]["profile"]["bounds"][
        "max_temp_c"] == 255.0
    assert "crud-http" in listed_names(server)
    status, body = server.request("DELETE", "/server/flowloop/profile?name=crud-http")
    assert status == 200 and body["result"]["action"] == "deleted"
    assert get(server, "crud-http")[0] == 404


def test_crud_over_json_rpc(server, rpc):
    async def steps(client):
        created = await client.call("server.flowloop.post_profile",
                                    profile=make(name="crud-rpc"))
        assert created["result"] == {"name": "crud-rpc", "action": "created",
                                     "deactivated": []}
        got = await client.call("server.flowloop.get_profile", name="crud-rpc")
        assert got["result"]["profile"]["identity"]["name"] == "crud-rpc"
        listed = await client.call("server.flowloop.profiles")
        assert "crud-rpc" in [p["name"] for p in listed["result"]["profiles"]]
        plot = await client.call("server.flowloop.profile.plot", name="crud-rpc")
        ET.fromstring(plot["result"].encode())
        act = await client.call("server.flowloop.profile.activate", name="crud-rpc",
                                extruder="extruder1", working_point=0.7)
        assert act["result"]["sent_to_klippy"] is False  # no klippy here
        deleted = await client.call("server.flowloop.delete_profile", name="crud-rpc")
        assert deleted["result"]["deactivated"] == ["extruder1"]
        missing = await client.call("server.flowloop.get_profile", name="crud-rpc")
        # Moonraker's JSON-RPC reports a 404 as -32601
        assert missing["error"]["code"] == -32601
        assert missing["error"]["message"] == 'no profile named "crud-rpc"'
        bad = await client.call("server.flowloop.post_profile",
                                profile=make(name="x", bounds=(190, 210, 900)))
        assert bad["error"]["code"] == 400
        assert "bounds.max_temp_c must be in 0..500" in bad["error"]["message"]
    rpc(server.port, steps)


# --- errors -----------------------------------------------------------------


@pytest.mark.parametrize("body, message", [
    ({"profile": make(name="bad", air=(-0.1, 171.6, 7.5))},
     "lines.into_air.slope_mm3_s_per_c must be > 0"),
    ({"profile": dict(make(name="bad"), colour="red")}, "unknown field `colour`"),
    ({"profile": "{not json"}, "argument 'profile': not a JSON profile"),
    ({"profile": [1, 2]}, "must be a JSON object"),
    ({}, "the profile is missing (argument 'profile')"),
    ({"profile": make(name="bad", points=[
        {"kind": "into_air", "temp_c": 200.0, "flow_mm3_s": 5.0, "grip": 0.9}]
        * (MAX_POINTS + 1))}, f"at most {MAX_POINTS}"),
    ({"profile": make(name="plot\ufffebreaker")}, "profile name contains"),
])
def test_bad_writes_answer_400_with_the_reason_and_change_nothing(server, body,
                                                                  message):
    before = server.request("GET", "/server/flowloop/profiles")[1]
    status, answer = server.request("POST", "/server/flowloop/profile", body)
    assert status == 400
    assert answer["error"]["code"] == 400
    assert message in answer["error"]["message"]
    assert server.request("GET", "/server/flowloop/profiles")[1] == before


def test_unknown_names_answer_404(server):
    for method, path in (("GET", "/server/flowloop/profile?name=nope"),
                         ("DELETE", "/server/flowloop/profile?name=nope"),
                         ("GET", "/server/flowloop/profile/plot?name=nope")):
        status, body = server.request(method, path)
        assert status == 404, (method, path)
        assert body["error"]["message"] == 'no profile named "nope"'
    status, body = server.request("POST", "/server/flowloop/profile/activate",
                                  {"name": "nope"})
    assert status == 404


def test_bad_activation_arguments_answer_400(server):
    store(server, name="act-args")
    for args, message in (({"name": "act-args", "working_point": 1.5},
                           "working_point: got 1.5; accepts"),
                          ({"name": "act-args", "working_point": "x"},
                           "working_point: got 'x'; accepts a number"),
                          ({"name": "act-args", "extruder": "heater_bed"},
                           "is not an extruder name"),
                          ({"name": "act-args", "extruder": "extruder\n"},
                           "is not an extruder name"),
                          ({"name": "act-args", "extruder": ["extruder"]},
                           "the extruder name must be a string"),
                          ({}, "the profile name is missing")):
        status, body = server.request("POST", "/server/flowloop/profile/activate",
                                      args)
        assert status == 400 and message in body["error"]["message"], body


# --- profile text that cannot be decoded ---------------------------------------

DEEP = 1000
UNDECODABLE = [
    pytest.param('{"identity": ' * DEEP + "1" + "}" * DEEP, id="objects-1000-deep"),
    pytest.param("[" * DEEP + "]" * DEEP, id="arrays-1000-deep"),
    pytest.param('{"a": ' * 100_000 + "1" + "}" * 100_000, id="objects-100000-deep"),
    pytest.param('{"identity": {"name": "x"', id="truncated"),
    pytest.param("", id="empty"),
    pytest.param("NaN", id="nan"),
    pytest.param('{"bounds": {"min_temp_c": 1e999}}', id="number-out-of-range"),
    pytest.param("{} trailing", id="trailing-text"),
    pytest.param('"\\ud800"', id="json-escaped-lone-surrogate"),
    pytest.param("\x00{}", id="nul"),
    pytest.param("\ufeff{}", id="byte-order-mark"),
]


def assert_one_line_400(status, body):
    assert status == 400, body
    message = body["error"]["message"]
    assert message.startswith("argument 'profile': "), message
    assert "\n" not in message and "Traceback" not in message and len(message) < 300


@pytest.mark.parametrize("text", UNDECODABLE)
def test_profile_text_that_cannot_be_decoded_is_one_line_400_over_http(server,
                                                                        text):
    before = server.request("GET", "/server/flowloop/profiles")[1]
    status, body = server.request("POST", "/server/flowloop/profile",
                                  {"profile": text})
    assert_one_line_400(status, body)
    assert server.request("GET", "/server/flowloop/profiles")[1] == before


def test_profile_text_that_cannot_be_decoded_is_one_line_400_over_json_rpc(server,
                                                                            rpc):
    async def steps(client):
        for param in UNDECODABLE:
            answer = await client.call("server.flowloop.post_profile",
                                       profile=param.values[0])
            assert answer["error"]["code"] == 400, (param.id, answer)
            assert_one_line_400(400, answer)
    rpc(server.port, steps)


def test_a_profile_sent_as_json_text_is_stored(server):
    text = json.dumps(make(name="as text"))
    status, body = server.request("POST", "/server/flowloop/profile",
                                  {"profile": text})
    assert status == 200, body
    assert get(server, "as text")[0] == 200


# --- numeric parameters -----------------------------------------------------------

WP_ACCEPTS = "accepts a number from 0 (real print) to 1 (into air)"
BAD_WORKING_POINTS = [("abc", "'abc'"), ("nan", "'nan'"), ("inf", "'inf'"),
                      ("1.5", "'1.5'"), (1.5, "1.5"), (-0.1, "-0.1"), (True, "true"),
                      ([0.5], "[0.5]"), ({"wp": 1}, '{"wp":1}'), (None, "null")]


def test_bad_working_points_name_the_parameter_the_value_and_the_range(server,
                                                                       rpc):
    store(server, name="wp-args")
    for value, shown in BAD_WORKING_POINTS:
        expected = f"working_point: got {shown}; {WP_ACCEPTS}"
        status, body = server.request("POST", "/server/flowloop/profile/activate",
                                      {"name": "wp-args", "working_point": value})
        assert status == 400 and body["error"]["message"] == expected, body
        if isinstance(value, str):  # a query argument is always text
            status, body = server.request(
                "GET", "/server/flowloop/profile/plot?name=wp-args&working_point="
                + quote(value))
            assert status == 400 and body["error"]["message"] == expected, body

    async def steps(client):
        for value, shown in BAD_WORKING_POINTS:
            expected = f"working_point: got {shown}; {WP_ACCEPTS}"
            for method in ("server.flowloop.profile.activate",
                           "server.flowloop.profile.plot"):
                answer = await client.call(method, name="wp-args",
                                           working_point=value)
                assert answer["error"] == {"code": 400, "message": expected}, (
                    method, value, answer)
    rpc(server.port, steps)
    active = server.request("GET", "/server/flowloop/profiles")[1]["result"]["active"]
    assert "wp-args" not in [entry["name"] for entry in active.values()]


# --- names ------------------------------------------------------------------

ODD_NAMES = ["a.b.c", "x/y", "..", "../../etc/passwd", "semi;colon M112",
             'quote"s', "it's", "üñï 0.4 mm", "{printer}", "%2e%2e", "a" * 128]


def test_odd_names_round_trip_over_http_and_rpc_and_never_become_key_paths(server,
                                                                           rpc):
    for name in ODD_NAMES:
        assert store(server, name=name)["name"] == name
        status, body = get(server, name)
        assert status == 200, name
        assert body["result"]["name"] == name
        assert body["result"]["profile"]["identity"]["name"] == name

    async def over_rpc(client):
        for name in ODD_NAMES:
            got = await client.call("server.flowloop.get_profile", name=name)
            assert got["result"]["name"] == name
    rpc(server.port, over_rpc)
    assert set(ODD_NAMES) <= listed_names(server)
    status, body = server.request("GET", "/server/database/item?namespace=flowloop")
    assert status == 200
    keys = set(body["result"]["value"])
    assert all(re.fullmatch(r"profile:[0-9a-f]+|active", key) for key in keys), keys
    for name in ODD_NAMES:
        assert server.request("DELETE", "/server/flowloop/profile?name="
                              + quote(name, safe=""))[0] == 200


@pytest.mark.parametrize("name", ["new\nline", "tab\there", "nul\x00", "", "   ",
                                  "a" * 129])
def test_names_that_cannot_be_one_line_are_refused(server, name):
    status, body = server.request("POST", "/server/flowloop/profile",
                                  {"profile": make(name=name)})
    assert status == 400
    assert "profile name" in body["error"]["message"]
    assert "\n" not in body["error"]["message"]
    # Over HTTP tornado already drops NUL and similar from query arguments.
    status, body = get(server, name)
    assert status in (400, 404)
    assert name not in listed_names(server)


PADDED_NAMES = [" pad ", "pad ", " pad", "\u00a0nbsp", "nbsp\u00a0", "\u3000wide"]
INVISIBLE_NAMES = ["rtl\u202eevil", "zero\u200bwidth", "\u2066isolate\u2069",
                   "\u2067rtl", "\u2068first", "pop\u2069", "bom\ufeff",
                   "soft\u00adhyphen"]


@pytest.mark.parametrize("name", PADDED_NAMES + INVISIBLE_NAMES)
def test_names_that_would_not_round_trip_or_show_as_another_are_refused(server, rpc,
                                                                        name):
    status, body = server.request("POST", "/server/flowloop/profile",
                                  {"profile": make(name=name)})
    assert status == 400, body
    message = body["error"]["message"]
    assert message.startswith("argument 'profile': ") and "profile name" in message
    assert ("whitespace" if name in PADDED_NAMES else
            f"U+{ord(next(c for c in name if not c.isalnum())):04X}") in message

    async def steps(client):
        stored = await client.call("server.flowloop.post_profile",
                                   profile=make(name=name))
        assert stored["error"]["code"] == 400
        for method in ("server.flowloop.get_profile", "server.flowloop.delete_profile",
                       "server.flowloop.profile.plot",
                       "server.flowloop.profile.activate"):
            answer = await client.call(method, name=name)
            assert answer["error"]["code"] == 400, (method, answer)
            assert "profile name" in answer["error"]["message"]
    rpc(server.port, steps)
    assert name not in listed_names(server) and name.strip() not in listed_names(
        server)


def test_database_api_cannot_write_around_validation(server):
    status, body = server.request("POST", "/server/database/item",
                                  {"namespace": "flowloop", "key": "profile:00",
                                   "value": {"junk": True}})
    assert status == 403


# --- notifications, plot -----------------------------------------------------


def test_every_change_is_notified(server, rpc):
    async def steps(client):
        await client.call("server.connection.identify", client_name="flowloop-test",
                          version="1", type="other", url="http://x")
        # written over HTTP by another client: the websocket client hears it
        status, _ = await client.in_thread(
            lambda: server.request("POST", "/server/flowloop/profile",
                                   {"profile": make(name="notified")}))
        assert status == 200
        msg = await client.notification("notify_flowloop_profile_changed",
                                        where=lambda p: p[0]["name"] == "notified")
        assert msg["params"][0]["action"] == "created"
        assert msg["params"][0]["profile"]["printer"] == "UM2-1"
        await client.call("server.flowloop.profile.activate", name="notified")
        msg = await client.notification("notify_flowloop_profile_changed",
                                        where=lambda p: p[0]["action"] == "activated")
        assert msg["params"][0]["extruder"] == "extruder"
        await client.call("server.flowloop.delete_profile", name="notified")
        msg = await client.notification("notify_flowloop_profile_changed",
                                        where=lambda p: p[0]["action"] == "deleted")
        assert msg["params"][0] == {"action": "deleted", "name": "notified",
                                    "deactivated": ["extruder"]}
    rpc(server.port, steps)


def test_plot_is_valid_svg_of_the_stored_profile(server):
    store(server, name='plot <&"> me', points=[
        {"kind": "into_air", "temp_c": 220.0, "flow_mm3_s": 14.0, "grip": 0.9}])
    status, text = server.request(
        "GET", "/server/flowloop/profile/plot?working_point=0.3&name="
        + quote('plot <&"> me', safe=""))
    assert status == 200
    root = ET.fromstring(text.encode())
    assert root.tag == "{http://www.w3.org/2000/svg}svg"
    assert root.get("data-profile") == 'plot <&"> me'
    ids = {e.get("id") for e in root.iter()}
    assert {"into_air", "real_print", "working_line", "points"} <= ids
    assert "working point 0.3" in text


# --- persistence and concurrency ---------------------------------------------


def test_concurrent_writes_all_land_and_survive_a_restart(server):
    names = [f"concurrent-{i:02d}" for i in range(24)]

    def write(name):
        return server.request("POST", "/server/flowloop/profile",
                              {"profile": make(name=name)})[0]
    with ThreadPoolExecutor(max_workers=8) as pool:
        assert list(pool.map(write, names)) == [200] * len(names)
    status, body = server.request("POST", "/server/flowloop/profile/activate",
                                  {"name": names[3], "extruder": "extruder",
                                   "working_point": 0.25})
    assert status == 200
    server.restart()
    listed = server.request("GET", "/server/flowloop/profiles")[1]["result"]
    assert set(names) <= {p["name"] for p in listed["profiles"]}
    assert listed["active"]["extruder"] == {"name": names[3], "working_point": 0.25}
    assert get(server, names[7])[1]["result"]["profile"]["lines"]["real_print"][
        "flow_mm3_s"] == 10.1356


# --- authorization ------------------------------------------------------------


@pytest.fixture(scope="module")
def untrusting_server(moonraker_venv):
    data_dir = stack.short_tempdir("fl-auth-")
    srv = Server(moonraker_venv, data_dir, trusted="10.99.0.0/16")
    yield srv
    srv.stop()
    shutil.rmtree(data_dir, ignore_errors=True)


@pytest.mark.parametrize("method, path, body", [
    ("GET", "/server/flowloop/profiles", None),
    ("GET", "/server/flowloop/profile?name=x", None),
    ("POST", "/server/flowloop/profile", {"profile": make(name="intruder")}),
    ("DELETE", "/server/flowloop/profile?name=x", None),
    ("POST", "/server/flowloop/profile/activate", {"name": "x"}),
    ("GET", "/server/flowloop/profile/plot?name=x", None),
    ("GET", "/server/flowloop/info", None),
])
def test_an_untrusted_client_is_refused(untrusting_server, method, path, body):
    status, _ = untrusting_server.request(method, path, body)
    assert status == 401


def test_an_untrusted_websocket_client_is_refused(untrusting_server, rpc):
    async def steps(client):
        answer = await client.call("server.flowloop.post_profile",
                                   profile=make(name="intruder"))
        # Moonraker's JSON-RPC reports a 401 as -32602
        assert answer["error"]["code"] == -32602
        assert "Unauthorized" in answer["error"]["message"]
    rpc(untrusting_server.port, steps)


# --- configuration -----------------------------------------------------------------


def test_a_bad_spoolman_extruder_names_the_section_and_option(moonraker_venv):
    data_dir = stack.short_tempdir("fl-conf-")
    mr = stack.Moonraker(moonraker_venv, data_dir,
                         extra_conf="spoolman_extruder: heater_bed\n")
    try:
        mr.wait_ready()
        info = mr.request("GET", "/server/info")[1]["result"]
        assert "flowloop" in info["failed_components"]
        log = (data_dir / "moonraker.log").read_text()
        assert ('Section [flowloop], option spoolman_extruder: "heater_bed" is not '
                "an extruder name (extruder, extruder1, ...)") in log
    finally:
        mr.stop()
        shutil.rmtree(data_dir, ignore_errors=True)
