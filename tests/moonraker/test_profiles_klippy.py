"""Material profiles between the real Moonraker and a real batch-mode klippy:
activation reaches klippy's [flowloop] object (through its webhooks endpoint,
not G-code) and a klippy macro hands a profile over with flowloop_store_profile."""

from __future__ import annotations

import json
import socket
from urllib.parse import quote

import pytest

from devtools import stack
from flowloop.material import profile as fl_profile
from tests.samples import make

MACRO_PROFILE = make(name="from-klippy", bounds=(200.0, 215.0, 250.0))

# klippy's config in the printer fixture (tests/moonraker/conftest.py)
PRINTER_CFG = """\
[include {project}/config/printer.cfg]

# What a measurement command will do: hand a profile over to Moonraker.
[gcode_macro FLOWLOOP_TEST_STORE]
variable_profile: {profile!r}
gcode:
  {{action_call_remote_method("flowloop_store_profile", profile=profile,
                              activate_extruder="extruder", working_point=0.8)}}

[gcode_macro FLOWLOOP_TEST_STORE_BAD_WP]
variable_profile: {bad_wp_profile!r}
gcode:
  {{action_call_remote_method("flowloop_store_profile", profile=profile,
                              activate_extruder="extruder", working_point="abc")}}
"""
BAD_WP_PROFILE = make(name="bad-wp-from-klippy")
# what the printer fixture formats PRINTER_CFG with (tests/moonraker/conftest.py)
PRINTER_CFG_ARGS = {"profile": MACRO_PROFILE, "bad_wp_profile": BAD_WP_PROFILE}


def request(ps, method, path, body=None):
    return ps.moonraker.request(method, path, body)


def store(ps, **kw):
    status, body = request(ps, "POST", "/server/flowloop/profile",
                           {"profile": make(**kw)})
    assert status == 200, body


def activate(ps, name, **kw):
    return request(ps, "POST", "/server/flowloop/profile/activate",
                   {"name": name, **kw})


def klippy_profiles(ps):
    return ps.query("flowloop").get("profiles", {})


WAIT_S = 20.0


def test_activation_reaches_klippy_and_shows_in_get_status(printer):
    store(printer, name="hot pla", bounds=(190.0, 210.0, 280.0))
    status, body = activate(printer, "hot pla", working_point=0.3)
    assert status == 200, body
    assert body["result"]["sent_to_klippy"] is True
    shown = klippy_profiles(printer)["extruder"]
    assert shown["name"] == "hot pla" and shown["working_point"] == 0.3
    assert shown["into_air"] == {"slope_mm3_s_per_c": 0.146, "temp_c": 171.6312,
                                 "flow_mm3_s": 7.5789}
    assert shown["real_print"]["temp_c"] == 210.0
    # C = C2 + 0.3 (C1 - C2) = -20.5244 + 0.3 * 3.0451448
    assert shown["working_line"]["intercept_mm3_s"] == pytest.approx(-19.61085656)
    # the profile allows 280 degC, config/printer.cfg's heater only 260
    assert shown["heater_max_temp_c"] == 260.0 and shown["max_temp_c"] == 260.0
    assert printer.query("webhooks")["state"] == "ready"
    # the live page bounds its lines the same way
    status, body = request(printer, "GET", "/server/flowloop/page/lines")
    assert status == 200, body
    assert body["result"]["lines"]["max_temp_c"] == 260.0


def test_klippy_refuses_an_extruder_it_does_not_have(printer):
    store(printer, name="second nozzle")
    status, body = activate(printer, "second nozzle", extruder="extruder1")
    assert status == 400
    assert "no extruder named 'extruder1'" in body["error"]["message"]
    active = request(printer, "GET", "/server/flowloop/profiles")[1]["result"]["active"]
    assert "extruder1" not in active


def test_klippy_refuses_a_profile_its_heater_cannot_reach(printer):
    # config/printer.cfg's extruder stops at 260 degC, this material needs 270+
    store(printer, name="peek", bounds=(270.0, 380.0, 420.0),
          real=(0.146, 390.0, 10.0), air=(0.146, 380.0, 12.0))
    status, body = activate(printer, "peek")
    assert status == 400
    assert "max_temp 260 degC is not above the profile's min_temp_c 270" in (
        body["error"]["message"])
    assert klippy_profiles(printer).get("extruder", {}).get("name") != "peek"


def test_storing_the_active_profile_again_updates_klippy(printer):
    store(printer, name="hot pla", bounds=(195.0, 215.0, 240.0))
    assert stack.wait_until(
        lambda: klippy_profiles(printer)["extruder"]["min_temp_c"] == 195.0, WAIT_S)
    assert klippy_profiles(printer)["extruder"]["max_temp_c"] == 240.0


def test_storing_the_active_profile_as_one_klippy_refuses_drops_the_activation(
        printer):
    store(printer, name="will overheat")
    assert activate(printer, "will overheat")[0] == 200
    # config/printer.cfg's extruder stops at 260 degC, this version needs 270+
    status, body = request(printer, "POST", "/server/flowloop/profile", {
        "profile": make(name="will overheat", bounds=(270.0, 380.0, 420.0),
                        real=(0.146, 390.0, 10.0), air=(0.146, 380.0, 12.0))})
    assert status == 200, body
    assert body["result"]["deactivated"] == ["extruder"]
    # klippy does not run the older version either
    assert "extruder" not in klippy_profiles(printer)
    active = request(printer, "GET", "/server/flowloop/profiles")[1]["result"]["active"]
    assert "extruder" not in active


def klippy_state(ps):
    status, body = ps.moonraker.request("GET", "/server/info")
    return status == 200 and body["result"]["klippy_state"]


def test_an_activation_made_while_klippy_is_away_stands_only_if_klippy_accepts_it(
        printer):
    store(printer, name="queued")
    assert request(printer, "POST", "/printer/emergency_stop")[0] == 200
    assert stack.wait_until(lambda: klippy_state(printer) == "shutdown", WAIT_S)
    for extruder in ("extruder7", "extruder"):  # klippy has no extruder7
        status, body = activate(printer, "queued", extruder=extruder,
                                working_point=0.4)
        assert status == 200, body
        assert body["result"]["sent_to_klippy"] is False
    assert request(printer, "POST", "/printer/restart")[0] == 200
    printer.moonraker.wait_ready(klippy=True)

    def active():
        return request(printer, "GET", "/server/flowloop/profiles")[1]["result"][
            "active"]
    # klippy refused extruder7 when it came back: Moonraker keeps none of it
    assert stack.wait_until(lambda: "extruder7" not in active(), WAIT_S), active()
    info = request(printer, "GET", "/server/flowloop/info")[1]["result"]
    assert "extruder7" not in info["active_profiles"]
    lines = request(printer, "GET", "/server/flowloop/page/lines?extruder=extruder7")
    assert lines[1]["result"]["lines"] is None
    stored = request(printer, "GET",
                     "/server/database/item?namespace=flowloop&key=active")
    assert "extruder7" not in stored[1]["result"]["value"]
    assert ("the active profile for extruder7 dropped: klippy refused the profile: "
            in printer.moonraker.log_path.read_text())
    # the one klippy accepted stands on both sides
    assert active()["extruder"] == {"name": "queued", "working_point": 0.4}
    assert stack.wait_until(
        lambda: klippy_profiles_or_none(printer) == "queued", WAIT_S)


def test_a_queued_activation_klippy_refuses_does_not_stick_across_a_moonraker_restart(
        printer):
    store(printer, name="queued over restart")
    assert request(printer, "POST", "/printer/emergency_stop")[0] == 200
    assert stack.wait_until(lambda: klippy_state(printer) == "shutdown", WAIT_S)
    status, body = activate(printer, "queued over restart", extruder="extruder6")
    assert status == 200 and body["result"]["sent_to_klippy"] is False, body

    def restarts():
        return printer.moonraker.log_path.read_text().count(
            "Attempting Server Restart...")
    before = restarts()
    assert request(printer, "POST", "/server/restart")[0] == 200
    assert stack.wait_until(lambda: restarts() > before, WAIT_S)
    printer.moonraker.wait_ready()
    assert stack.wait_until(lambda: klippy_state(printer) == "shutdown", WAIT_S)

    def active():
        return request(printer, "GET", "/server/flowloop/profiles")[1]["result"][
            "active"]
    # read back from the database; klippy, still shut down, was not asked
    assert active()["extruder6"]["name"] == "queued over restart"
    assert request(printer, "POST", "/printer/restart")[0] == 200
    printer.moonraker.wait_ready(klippy=True)
    assert stack.wait_until(lambda: "extruder6" not in active(), WAIT_S), active()
    stored = request(printer, "GET",
                     "/server/database/item?namespace=flowloop&key=active")
    assert "extruder6" not in stored[1]["result"]["value"]


def test_names_with_gcode_characters_never_reach_gcode(printer):
    name = 'inject"; M112 ; {action_emergency_stop()}'
    store(printer, name=name)
    status, body = activate(printer, name)
    assert status == 200, body
    assert klippy_profiles(printer)["extruder"]["name"] == name
    assert printer.query("webhooks")["state"] == "ready"


def test_active_profile_is_sent_again_when_klippy_comes_back(printer):
    store(printer, name="after restart")
    assert activate(printer, "after restart", working_point=0.6)[0] == 200

    def resent():
        return printer.moonraker.log_path.read_text().count(
            "active profile for extruder sent to klippy")
    before = resent()
    request(printer, "POST", "/printer/restart")
    # klippy forgets on restart; Moonraker sends the stored activation on ready
    assert stack.wait_until(lambda: resent() > before, 60.0)
    assert stack.wait_until(
        lambda: klippy_profiles_or_none(printer) == "after restart", WAIT_S)
    assert klippy_profiles(printer)["extruder"]["working_point"] == 0.6


def klippy_profiles_or_none(ps):
    try:
        return klippy_profiles(ps).get("extruder", {}).get("name")
    except (RuntimeError, OSError, KeyError):
        return None  # klippy is restarting


def test_deleting_the_active_profile_clears_it_in_klippy(printer):
    store(printer, name="short lived")
    assert activate(printer, "short lived")[0] == 200
    status, body = request(printer, "DELETE",
                           "/server/flowloop/profile?name=short%20lived")
    assert status == 200 and body["result"]["deactivated"] == ["extruder"]
    assert "extruder" not in klippy_profiles(printer)


def test_a_klippy_macro_stores_a_profile_with_flowloop_store_profile(printer, rpc):
    def run_macro():
        try:
            printer.gcode("FLOWLOOP_TEST_STORE")
        except RuntimeError as e:  # Moonraker registers remote methods on ready
            if "not registered" in str(e):
                return False
            raise
        return True

    async def steps(client):
        assert await client.in_thread(lambda: stack.wait_until(run_macro, 15.0))
        stored = await client.notification(
            "notify_flowloop_profile_changed",
            where=lambda p: p[0]["name"] == "from-klippy")
        activated = await client.notification(
            "notify_flowloop_profile_changed",
            where=lambda p: p[0]["action"] == "activated")
        return stored["params"][0], activated["params"][0]
    stored, activated = rpc(printer.moonraker.port, steps)
    assert stored["source"] == "klippy" and stored["action"] in ("created", "updated")
    assert activated["name"] == "from-klippy" and activated["working_point"] == 0.8
    status, body = request(printer, "GET", "/server/flowloop/profile?name="
                           + quote("from-klippy"))
    assert status == 200
    # every field the macro handed over, with the schema's defaults filled in
    assert body["result"]["profile"] == fl_profile.profile_to_dict(
        fl_profile.profile_from_dict(MACRO_PROFILE))
    assert stack.wait_until(
        lambda: klippy_profiles_or_none(printer) == "from-klippy", WAIT_S)
    assert klippy_profiles(printer)["extruder"]["working_point"] == 0.8


def test_a_profile_from_klippy_with_a_bad_working_point_is_refused_unstored(
        printer, rpc):
    def run_macro():
        try:
            printer.gcode("FLOWLOOP_TEST_STORE_BAD_WP")
        except RuntimeError as e:  # Moonraker registers remote methods on ready
            if "not registered" in str(e):
                return False
            raise
        return True

    async def steps(client):
        assert await client.in_thread(lambda: stack.wait_until(run_macro, 15.0))
        refused = await client.notification(
            "notify_flowloop_profile_changed",
            where=lambda p: p[0]["action"] == "refused")
        return refused["params"][0]
    refused = rpc(printer.moonraker.port, steps)
    assert refused["reason"] == ("working_point: got 'abc'; accepts a number from 0 "
                                 "(real print) to 1 (into air)")
    assert request(printer, "GET", "/server/flowloop/profile?name="
                   + quote("bad-wp-from-klippy"))[0] == 404


def klippy_api(ps, method, params):
    """One request on klippy's API socket (what Moonraker itself uses)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(10.0)
        sock.connect(str(ps.klippy.api_socket))
        sock.sendall(json.dumps({"id": 1, "method": method,
                                 "params": params}).encode() + b"\x03")
        data = b""
        while not data.endswith(b"\x03"):
            chunk = sock.recv(65536)
            assert chunk, "klippy closed the API socket"
            data += chunk
    return json.loads(data[:-1])


ACCEPTS = {
    "working_point": "a number from 0 (real print) to 1 (into air)",
    "melt_ratio": ("a number from 0.3 to 1.5 (the hotend's melt capacity "
                   "against its profile's)"),
}


@pytest.mark.parametrize("parameter, value, shown", [
    ("working_point", "abc", "'abc'"), ("working_point", 1.5, "1.5"),
    ("working_point", True, "true"), ("working_point", [0.5], "[0.5]"),
    ("melt_ratio", "abc", "'abc'"), ("melt_ratio", 1.6, "1.6"),
    ("melt_ratio", 0.2, "0.2"), ("melt_ratio", True, "true")])
def test_klippy_names_a_bad_activation_value_and_keeps_the_active_profile(
        printer, parameter, value, shown):
    store(printer, name="kept")
    assert activate(printer, "kept", working_point=0.4)[0] == 200
    answer = klippy_api(printer, "flowloop/set_active_profile", {
        "extruder": "extruder", "profile": make(name="other"),
        "working_point": 0.5, parameter: value})
    assert answer["error"]["message"] == (
        f"flowloop: {parameter}: got {shown}; accepts {ACCEPTS[parameter]}")
    shown_status = klippy_profiles(printer)["extruder"]
    assert shown_status["name"] == "kept" and shown_status["working_point"] == 0.4
