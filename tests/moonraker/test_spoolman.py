"""The Spoolman link against a real Spoolman (devtools/spoolman.py: its own
source and virtualenv, its real API and database; the web client is a
placeholder) and a real Moonraker whose [spoolman] talks to it: loading a
spool activates the profile of its filament; a spool loaded while Spoolman
is down changes nothing until Spoolman is back."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import time

import pytest

from devtools import postgres, spoolman, stack
from tests.samples import make


@contextlib.contextmanager
def linked_spoolman(prefix):
    """(a running Spoolman, [flowloop] lines linking Moonraker to it, a data
    folder for the rest), all removed after; skipped without Spoolman."""
    reason = spoolman.missing_spoolman_reason()
    if reason:
        pytest.skip(reason)
    data_dir = stack.short_tempdir(prefix)
    sm = spoolman.Spoolman(data_dir / "spoolman")
    try:
        sm.wait_ready()
        yield sm, f"spoolman_link: True\n\n[spoolman]\nserver: {sm.url}\n", data_dir
    finally:
        sm.stop()
        shutil.rmtree(data_dir, ignore_errors=True)


@pytest.fixture(scope="module")
def farm(moonraker_venv):
    """(Spoolman, Moonraker with flowloop's spoolman_link on it)."""
    with linked_spoolman("fl-spoolman-") as (sm, conf, data_dir):
        mr = stack.Moonraker(moonraker_venv, data_dir / "moonraker",
                             extra_conf=conf)
        try:
            mr.wait_ready()
            yield sm, mr
        finally:
            mr.stop()


def _active(mr):
    result = mr.request("GET", "/server/flowloop/profiles")[1]
    return result["result"]["active"].get("extruder")


def _active_name(mr):
    return (_active(mr) or {}).get("name")


def _load_spool(mr, spool_id):
    status, body = mr.request("POST", "/server/spoolman/spool_id",
                              {"spool_id": spool_id})
    assert status == 200, body


def test_loading_a_spool_activates_the_profile_of_its_filament(farm):
    sm, mr = farm
    red = sm.add_filament("PLA red")
    other = sm.add_filament("PETG grey", material="PETG", density=1.27)
    red_spool = sm.add_spool(red["id"])["id"]
    other_spool = sm.add_spool(other["id"])["id"]
    profile = make(name="red pla", identity={"spoolman_filament_id": red["id"]})
    assert mr.request("POST", "/server/flowloop/profile",
                      {"profile": profile})[0] == 200
    assert _active(mr) is None
    _load_spool(mr, red_spool)
    assert stack.wait_until(lambda: _active(mr), 10.0) == {
        "name": "red pla", "working_point": 0.5}
    # a spool whose filament has no profile leaves the active one alone
    _load_spool(mr, other_spool)
    time.sleep(1.0)
    assert _active(mr) == {"name": "red pla", "working_point": 0.5}


def test_a_spool_loaded_while_spoolman_is_down_is_looked_up_when_it_is_back(farm):
    sm, mr = farm
    blue = sm.add_filament("PLA blue")
    blue_spool = sm.add_spool(blue["id"])["id"]
    assert mr.request("POST", "/server/flowloop/profile", {"profile": make(
        name="blue pla", identity={"spoolman_filament_id": blue["id"]})})[0] == 200
    before = _active(mr)
    sm.stop()
    try:
        # Moonraker takes the spool id; flowloop cannot read its filament
        mr.request("POST", "/server/spoolman/spool_id", {"spool_id": blue_spool})
        time.sleep(3.0)    # flowloop's request times out in 2 s
        assert _active(mr) == before
        log = (mr.data_dir / "moonraker.log").read_text()
        assert f"flowloop: Spoolman spool {blue_spool}:" in log
    finally:
        sm.restart()    # the same Spoolman, its data kept
    sm.wait_ready()
    # Moonraker does not announce the same spool again: flowloop asks once
    # Moonraker has reconnected to Spoolman
    assert stack.wait_until(lambda: _active(mr) == {
        "name": "blue pla", "working_point": 0.5}, 20.0)
    assert f"flowloop: looking up Spoolman spool {blue_spool} again" in (
        mr.data_dir / "moonraker.log").read_text()


@contextlib.contextmanager
def hung(sm):
    """Spoolman stopped in its tracks (SIGSTOP): connections are taken and
    nothing is answered, and Moonraker's websocket to it stays open (its
    ping comes every 20 s), so Moonraker never reconnects."""
    os.kill(sm.pid, signal.SIGSTOP)
    try:
        yield
    finally:
        os.kill(sm.pid, signal.SIGCONT)


def _disconnects(mr):
    return (mr.data_dir / "moonraker.log").read_text().count(
        "Spoolman Disconnected")


def test_a_spool_loaded_while_spoolman_hangs_is_looked_up_once_it_answers(farm):
    sm, mr = farm
    pink = sm.add_filament("PLA pink")
    pink_spool = sm.add_spool(pink["id"])["id"]
    assert mr.request("POST", "/server/flowloop/profile", {"profile": make(
        name="pink pla", identity={"spoolman_filament_id": pink["id"]})})[0] == 200
    disconnects = _disconnects(mr)
    with hung(sm):
        _load_spool(mr, pink_spool)
        time.sleep(3.0)     # flowloop's request times out in 2 s
        assert _active_name(mr) != "pink pla"
        info = mr.request("GET", "/server/flowloop/info")[1]["result"]
        assert info["spoolman"]["unresolved_spool"] == pink_spool
    # no reconnect to wait for: the link tries again on its own timer
    assert stack.wait_until(lambda: _active_name(mr) == "pink pla", 20.0)
    assert _disconnects(mr) == disconnects


# --- a farm: profiles kept on the filament, shared by hotend ------------------


@pytest.fixture(scope="module", params=["sqlite", "postgres"])
def printers(request, moonraker_venv):
    """(Spoolman, {name: Moonraker}, {name: PrinterStack}): printers a and b
    share a hotend key,
    c has another; Spoolman on its default SQLite, then on PostgreSQL."""
    reason = spoolman.missing_spoolman_reason()
    if reason:
        pytest.skip(reason)
    with contextlib.ExitStack() as stack_:
        env = {}
        if request.param == "postgres":
            reason = postgres.missing_postgres_reason()
            if reason:
                pytest.skip(reason)
            env = stack_.enter_context(postgres.postgres())
        yield from _farm(moonraker_venv, env)


def _farm(moonraker_venv, env):
    """Printers a and b are whole stacks (klippy in batch mode behind
    Moonraker: an activation reaches klippy), c is Moonraker alone."""
    data_dir = stack.short_tempdir("fl-farm-")
    sm = spoolman.Spoolman(data_dir / "spoolman", env=env)
    started = {}
    try:
        # Spoolman 0.26 says 'sqlite', or 'DatabaseType.POSTGRES'
        db_type = sm.wait_ready()["db_type"].lower()
        assert env.get("SPOOLMAN_DB_TYPE", "sqlite") in db_type, db_type
        with contextlib.ExitStack() as printers:
            for name, hotend in (("a", "revo_0.4"), ("b", "revo_0.4"),
                                 ("c", "v6_0.6")):
                conf = (f"spoolman_link: True\nhotend: {hotend}\n\n"
                        f"[spoolman]\nserver: {sm.url}\n")
                ps = printers.enter_context(stack.printer_stack(
                    with_klippy=name != "c", moonraker_conf=conf,
                    data_dir=data_dir / name))
                started[name] = ps
            yield sm, {name: ps.moonraker for name, ps in started.items()}, started
    finally:
        sm.stop()
        shutil.rmtree(data_dir, ignore_errors=True)


def _shared(sm, filament_id):
    """{hotend: profile name} Spoolman keeps on the filament."""
    from flowloop.material import spoolman_field
    filament = sm.request("GET", f"/api/v1/filament/{filament_id}")[1]
    return {hotend: p.name for hotend, p in
            spoolman_field.read_field(filament).items()}


def _names(mr):
    result = mr.request("GET", "/server/flowloop/profiles")[1]["result"]
    return [p["name"] for p in result["profiles"]]


def _store(mr, **kw):
    return mr.request("POST", "/server/flowloop/profile", {"profile": make(**kw)})


def _measured(name, fid, when, flow=10.1356):
    data = make(name=name, identity={"spoolman_filament_id": fid},
                real=(0.146, 210.0, flow))
    data["provenance"]["measured_at"] = when
    return data


def test_a_profile_stored_on_one_printer_follows_the_spool_to_its_twin(printers):
    sm, mr, stacks = printers
    green = sm.add_filament("PLA green")
    assert _store(mr["a"], name="green pla",
                  identity={"spoolman_filament_id": green["id"]})[0] == 200
    # a store answered is a store shared: on the filament already
    assert _shared(sm, green["id"]) == {"revo_0.4": "green pla"}
    # b (same hotend) has never seen it: loading a spool fetches and uses it
    assert "green pla" not in _names(mr["b"])
    _load_spool(mr["b"], sm.add_spool(green["id"])["id"])
    assert stack.wait_until(lambda: _active(mr["b"]), 10.0) == {
        "name": "green pla", "working_point": 0.5}
    assert "green pla" in _names(mr["b"])
    # and klippy behind b runs it
    klippy_profiles = stacks["b"].query("flowloop")["profiles"]
    assert klippy_profiles["extruder"]["name"] == "green pla"
    # c (another hotend) gets nothing from it
    _load_spool(mr["c"], sm.add_spool(green["id"])["id"])
    time.sleep(1.5)
    assert _active(mr["c"]) is None


def test_a_filament_spoolman_does_not_know_is_refused_by_name(printers):
    _, mr, _ = printers
    status, body = _store(mr["a"], name="ghost pla",
                          identity={"spoolman_filament_id": 9999})
    assert status == 400
    assert body["error"]["message"] == ('profile "ghost pla": Spoolman has no'
                                        " filament 9999"
                                        " (identity.spoolman_filament_id)")
    assert "ghost pla" not in _names(mr["a"])


def test_bad_data_on_the_filament_is_never_activated(printers):
    sm, mr, _ = printers
    odd = sm.add_filament("PLA odd")
    sm.request("POST", f"/api/v1/field/filament/{'flowloop_profiles'}",
               {"name": "flowloop profiles", "field_type": "text", "order": 0})
    status, _ = sm.request("PATCH", f"/api/v1/filament/{odd['id']}", {
        "extra": {"flowloop_profiles": '"{\\"flowloop\\": 7}"'}})
    assert status == 200
    before = _active(mr["b"])
    _load_spool(mr["b"], sm.add_spool(odd["id"])["id"])
    time.sleep(1.5)
    assert _active(mr["b"]) == before
    info = mr["b"].request("GET", "/server/flowloop/info")[1]["result"]
    assert info["spoolman"]["problem"].startswith(
        f"Spoolman filament {odd['id']} ('PLA odd'): its flowloop_profiles field"
        " is not a flowloop document of version 1")


def test_two_printers_storing_at_once_converge_on_the_later_measurement(printers):
    sm, mr, _ = printers
    white = sm.add_filament("PLA white")
    older = _measured("white pla a", white["id"], "2026-11-20T10:00:00Z")
    newer = _measured("white pla b", white["id"], "2026-11-21T10:00:00Z", 11.0)
    from concurrent.futures import ThreadPoolExecutor
    with ThreadPoolExecutor(2) as pool:
        done = [pool.submit(m.request, "POST", "/server/flowloop/profile",
                            {"profile": p})
                for m, p in ((mr["a"], older), (mr["b"], newer))]
        assert [f.result()[0] for f in done] == [200, 200]
    # both stores answered, both writes are done; Spoolman has no conditional
    # write, so one from an older read can have won the race: b puts its
    # later one back at its next spool of it
    _load_spool(mr["b"], sm.add_spool(white["id"])["id"])
    assert stack.wait_until(
        lambda: _shared(sm, white["id"]) == {"revo_0.4": "white pla b"}, 10.0)
    assert stack.wait_until(lambda: _active_name(mr["b"]) == "white pla b", 10.0)
    # and a learns of b's at its next spool of the filament
    _load_spool(mr["a"], sm.add_spool(white["id"])["id"])
    assert stack.wait_until(lambda: _active_name(mr["a"]) == "white pla b", 10.0)


def test_a_profile_stored_while_spoolman_is_down_is_written_when_it_is_back(printers):
    sm, mr, _ = printers
    black = sm.add_filament("PLA black")
    sm.stop()
    try:
        assert _store(mr["a"], name="black pla",
                      identity={"spoolman_filament_id": black["id"]})[0] == 200
        info = mr["a"].request("GET", "/server/flowloop/info")[1]["result"]
        assert stack.wait_until(lambda: "black pla" in mr["a"].request(
            "GET", "/server/flowloop/info")[1]["result"]["spoolman"]["unwritten"],
            5.0), info
    finally:
        sm.restart()
    sm.wait_ready()
    assert stack.wait_until(lambda: _shared(sm, black["id"]) == {
        "revo_0.4": "black pla"}, 20.0)
    info = mr["a"].request("GET", "/server/flowloop/info")[1]["result"]
    assert info["spoolman"]["unwritten"] == []


def test_a_profile_stored_while_spoolman_hangs_is_written_once_it_answers(printers):
    sm, mr, _ = printers
    grey = sm.add_filament("PLA grey")
    disconnects = _disconnects(mr["c"])
    with hung(sm):
        # the filament check times out (2 s): stored, written later
        assert _store(mr["c"], name="grey pla",
                      identity={"spoolman_filament_id": grey["id"]})[0] == 200
        # answered once the write was tried: listed unwritten already
        assert "grey pla" in mr["c"].request("GET", "/server/flowloop/info")[1][
            "result"]["spoolman"]["unwritten"]
    # (a write sent while it hung may land when it resumes: the link knows
    # only once its own next try reads the field back)
    assert stack.wait_until(lambda: mr["c"].request(
        "GET", "/server/flowloop/info")[1]["result"]["spoolman"]["unwritten"]
        == [], 30.0)
    assert _shared(sm, grey["id"]) == {"v6_0.6": "grey pla"}
    assert _disconnects(mr["c"]) == disconnects


def test_a_filament_id_spoolman_cannot_hold_is_refused_not_left_unwritten(printers):
    _, mr, _ = printers
    status, body = _store(mr["a"], name="huge pla",
                          identity={"spoolman_filament_id": 10 ** 30})
    assert status == 400, body
    assert body["error"]["message"] == (
        'profile "huge pla": Spoolman numbers filaments 1..2147483647, not '
        f"{10 ** 30} (identity.spoolman_filament_id)")
    assert "huge pla" not in _names(mr["a"])


def test_a_field_nested_3000_deep_is_one_line_not_a_recursion_error(printers):
    sm, mr, _ = printers
    deep = sm.add_filament("PLA deep")
    sm.request("POST", "/api/v1/field/filament/flowloop_profiles",
               {"name": "flowloop profiles", "field_type": "text", "order": 0})
    status, answer = sm.request("PATCH", f"/api/v1/filament/{deep['id']}", {
        "extra": {"flowloop_profiles": json.dumps("[" * 3000 + "]" * 3000)}})
    assert status == 200, answer
    before = _active(mr["b"])
    _load_spool(mr["b"], sm.add_spool(deep["id"])["id"])
    assert stack.wait_until(lambda: "nests 3000 levels deep" in (
        mr["b"].request("GET", "/server/flowloop/info")[1]["result"]["spoolman"]
        ["problem"] or ""), 10.0)
    assert _active(mr["b"]) == before
    log = (mr["b"].data_dir / "moonraker.log").read_text()
    assert "RecursionError" not in log
