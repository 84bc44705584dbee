"""What the flowloop API promises an HTTP client about refusals, against the
real Moonraker (no klippy) serving flowloop's endpoints with its own
handler: a message reaches it whole whatever characters it holds, a body
Moonraker cannot decode changes nothing, and every endpoint reads its
arguments (and words their refusals) the same way."""

from __future__ import annotations

import http.client
import json
import shutil

import pytest

from devtools import stack
from tests.samples import make


@pytest.fixture(scope="module")
def server(moonraker_venv):
    data_dir = stack.short_tempdir("fl-api-")
    mr = stack.Moonraker(moonraker_venv, data_dir)
    try:
        mr.wait_ready()
        (data_dir / "gcodes").mkdir(exist_ok=True)
        yield mr
    finally:
        mr.stop()
        shutil.rmtree(data_dir, ignore_errors=True)


def raw(mr, method, path, body=b"", content_type="application/json"):
    """(status, reason phrase, decoded JSON body) of one HTTP request sent
    byte for byte."""
    conn = http.client.HTTPConnection("127.0.0.1", mr.port, timeout=10)
    try:
        conn.request(method, path, body=body or None,
                     headers={"Content-Type": content_type} if body else {})
        resp = conn.getresponse()
        return resp.status, resp.reason, json.loads(resp.read())
    finally:
        conn.close()


# --- messages survive any character ---------------------------------------------

# `<` as JSON writes it, \u003c: tornado turns a reason phrase holding `<`
# into "Unknown", and Moonraker's HTTP error body repeats the reason phrase
ODD_ARGUMENTS = [
    ("GET", "/server/flowloop/profile?name=PLA%20%3Cfast%3E", 404,
     "server.flowloop.get_profile", {"name": "PLA <fast>"},
     'no profile named "PLA \\u003cfast>"'),
    ("GET", "/server/flowloop/page/lines?extruder=%3Cscript%3E", 400,
     "server.flowloop.page.lines", {"extruder": "<script>"},
     '"\\u003cscript>" is not an extruder name (extruder, extruder1, ...)'),
    ("GET", "/server/flowloop/page/lines?extruder=a%7Fb", 400,
     "server.flowloop.page.lines", {"extruder": "a\x7fb"},
     '"a\\u007fb" is not an extruder name (extruder, extruder1, ...)'),
]


@pytest.mark.parametrize("method, path, code, rpc_method, params, message",
                         ODD_ARGUMENTS)
def test_a_refusal_reaches_http_as_the_one_line_the_websocket_gets(
        server, rpc, method, path, code, rpc_method, params, message):
    status, reason, body = raw(server, method, path)
    assert status == code
    assert (body["error"]["code"], body["error"]["message"]) == (code, message)
    assert reason == message

    async def steps(client):
        return await client.call(rpc_method, **params)
    assert rpc(server.port, steps)["error"]["message"] == message


def test_a_profile_whose_name_holds_a_bracket_is_found_and_refused_whole(server):
    assert server.request("POST", "/server/flowloop/profile",
                          {"profile": make(name="PLA <fast>")})[0] == 200
    status, body = server.request("GET",
                                  "/server/flowloop/profile?name=PLA%20%3Cfast%3E")
    assert status == 200 and body["result"]["name"] == "PLA <fast>"
    # the name in a refusal is JSON: it decodes to the name, whole
    status, reason, body = raw(server, "DELETE",
                               "/server/flowloop/profile?name=PLA%20%3Cfast%3Ex")
    assert status == 404 and reason == body["error"]["message"]
    assert json.loads(reason[len("no profile named "):]) == "PLA <fast>x"
    status, reason, body = raw(server, "POST", "/server/flowloop/profile/activate",
                               b'{"name": "PLA <fast>", "working_point": 7}')
    assert status == 400
    assert body["error"]["message"] == ("working_point: got 7; accepts a number "
                                        "from 0 (real print) to 1 (into air)")
    assert reason == body["error"]["message"]


# --- a body Moonraker cannot decode ---------------------------------------------
# Moonraker decodes the body before flowloop is called, with no public hook
# around it: one that does not decode is dropped (the endpoint sees no
# arguments), one nested past its decoder's recursion limit or that is not
# an object fails in Moonraker itself (a 500). docs/reference.md, "Refusals",
# describes the upstream fix. Either way nothing is stored.

DROPPED = [
    ("/server/flowloop/profile", b'{"profile": {"identity": ',
     "the profile is missing (argument 'profile')"),
    ("/server/flowloop/profile", b'{"profile": NaN}',
     "the profile is missing (argument 'profile')"),
    ("/server/flowloop/profile", b"Infinity",
     "the profile is missing (argument 'profile')"),
    ("/server/flowloop/profile/activate", b'{"name": "p", "working_point": NaN}',
     "the profile name is missing (argument 'name')"),
]
FAILING_IN_MOONRAKER = [
    ("/server/flowloop/profile/activate", b'["p"]'),
    ("/server/flowloop/profile", b'{"profile": ' + b"[" * 1000 + b"]" * 1000
     + b"}"),
    ("/server/flowloop/nozzle_health", b'{"job_id": "000001", "evidence": '
     + b"{\"a\": " * 3000 + b"1" + b"}" * 3001),
]


@pytest.mark.parametrize("path, body, message", DROPPED)
def test_a_body_moonraker_drops_is_read_as_no_arguments(server, path, body,
                                                        message):
    before = server.request("GET", "/server/flowloop/profiles")[1]
    status, reason, answer = raw(server, "POST", path, body)
    assert (status, answer["error"]["message"], reason) == (400, message, message)
    assert server.request("GET", "/server/flowloop/profiles")[1] == before


@pytest.mark.parametrize("path, body", FAILING_IN_MOONRAKER)
def test_a_body_moonraker_fails_on_changes_nothing(server, path, body):
    before = server.request("GET", "/server/flowloop/profiles")[1]
    status, _, answer = raw(server, "POST", path, body)
    assert status >= 400, answer
    assert server.request("GET", "/server/flowloop/profiles")[1] == before


def test_a_form_body_is_still_read_as_moonraker_reads_it(server):
    status, _, answer = raw(server, "POST", "/server/flowloop/profile/activate",
                            b"name=nope", "application/x-www-form-urlencoded")
    assert status == 404 and answer["error"]["message"] == 'no profile named "nope"'


# --- one argument reader, one wording ----------------------------------------------

FILE_ENDPOINTS = ("server.flowloop.annotation", "server.flowloop.page.plan")


@pytest.mark.parametrize("params, message", [
    ({}, "the file name is missing (argument 'filename')"),
    ({"filename": ""}, "the file name is missing (argument 'filename')"),
    ({"filename": 12}, "the file name must be a string (argument 'filename': "
                       "got 12)"),
    ({"filename": ["x"]}, "the file name must be a string (argument 'filename': "
                          'got ["x"])'),
    ({"filename": "../moonraker.conf"}, 'no G-code file named "../moonraker.conf"'),
])
def test_every_endpoint_reads_a_file_name_the_same_way(server, rpc, params,
                                                       message):
    async def steps(client):
        return [await client.call(method, **params) for method in FILE_ENDPOINTS]
    for method, answer in zip(FILE_ENDPOINTS, rpc(server.port, steps)):
        assert answer["error"]["message"] == message, method
    if "filename" not in params or isinstance(params["filename"], str):
        query = "" if not params else "?filename=" + params["filename"]
        for path in ("/server/flowloop/annotation", "/server/flowloop/page/plan"):
            status, _, answer = raw(server, "GET", path + query)
            assert answer["error"]["message"] == message, path


@pytest.mark.parametrize("params, message", [
    ({"name": 12}, "the profile name must be a string (argument 'name': got 12)"),
    ({"name": "x", "extruder": ["extruder"]},
     "the extruder name must be a string (argument 'extruder': got "
     '["extruder"])'),
])
def test_name_and_extruder_are_read_the_same_way(server, rpc, params, message):
    async def steps(client):
        return [await client.call(method, **params) for method in (
            "server.flowloop.profile.activate", "server.flowloop.page.lines")]
    activate, lines = rpc(server.port, steps)
    assert activate["error"]["message"] == message
    if "extruder" in params:
        assert lines["error"]["message"] == message


# --- the live page's profile lines ---------------------------------------------------


def test_page_lines_max_temp_is_the_profiles_not_the_plots_margin(server):
    assert server.request("POST", "/server/flowloop/profile",
                          {"profile": make(name="lines 260")})[0] == 200
    assert server.request("POST", "/server/flowloop/profile/activate",
                          {"name": "lines 260", "extruder": "extruder2"})[0] == 200
    status, body = server.request("GET",
                                  "/server/flowloop/page/lines?extruder=extruder2")
    assert status == 200, body
    lines = body["result"]["lines"]
    assert (lines["min_temp_c"], lines["max_temp_c"]) == (190.0, 260.0)
    assert lines["temp_c"][-1] == pytest.approx(267.0)  # the plot's margin
