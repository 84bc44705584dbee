"""A database written before flowloop's namespaces had versions migrates
without loss, against the real Moonraker: the old layout (profiles, the
active profiles and the nozzle histories all in the namespace `flowloop`)
is written through Moonraker's own database API by a Moonraker that has no
flowloop yet, then flowloop is installed and Moonraker started again on the
same data directory. The profiles and activations are served as they were,
each history moves to `flowloop_nozzle_health` whole, the namespaces' schema
versions are recorded, and a later start migrates nothing again."""

from __future__ import annotations

import copy
import functools
import shutil
from urllib.parse import quote

import pytest

from devtools import stack
from flowloop.control import nozzle_health as nh
from flowloop.host import db_schema as schema
from flowloop.host import install
from flowloop.material import profile as fl_profile
from flowloop.material.active import ActiveProfile, active_to_stored
from tests.moonraker.conftest import copy_of_moonraker
from tests.nozzle_prints import PROFILE, simulate_print
from tests.samples import make, twin_known

MARKUP = "PETG <img src=x> & 'co'"
MIGRATING = "migrating from schema version 0"


def profile(name):
    data = twin_known() if name == "known" else make(name=name)
    data["identity"]["name"] = name
    return fl_profile.profile_to_dict(fl_profile.profile_from_dict(data))


@functools.cache
def _estimate(ratio, seed):
    return nh.estimate(nh.evidence_of(simulate_print(ratio, seed=seed), PROFILE))


def legacy_history(hotend, name, ratios):
    """A history as the component before versions wrote it."""
    prints = []
    for k, ratio in enumerate(ratios):
        found = copy.deepcopy(_estimate(ratio, k).to_dict())
        prints = nh.with_print(prints, {"job_id": f"{k + 1:06X}",
                                        "time": 1.7e9 + k, **found,
                                        "profile": name})
    verdict = nh.judge([nh.PrintEstimate.from_dict(p) for p in prints])
    return {"hotend": hotend, "profile": name, "prints": prints,
            "verdict": verdict.__dict__}


def legacy_key(hotend, name):
    return (f"nozzle_health:{hotend.encode().hex()}:"
            f"{name.encode().hex()}")


PROFILES = {name: profile(name) for name in ("known", MARKUP, "herz-pla-red_80")}
ACTIVE = active_to_stored({
    "extruder": ActiveProfile(name="known", working_point=0.3),
    "extruder1": ActiveProfile(name=MARKUP, working_point=0.5)})


# built on first use, not at import: simulating the prints takes seconds of
# CPU, which every worker of `make test` would spend collecting the module
@functools.cache
def histories():
    return [legacy_history("v6-0.4", "known", [1.0, 0.98, 0.9, 0.88, 0.87]),
            legacy_history("v6-0.4 extruder1", MARKUP, [1.0, 0.99]),
            legacy_history("v6-0.4", "herz-pla-red_80", [0.97])]


@functools.cache
def old_layout():
    return {**{schema.profile_key(n): p for n, p in PROFILES.items()},
            "active": ACTIVE,
            **{legacy_key(h["hotend"], h["profile"]): h for h in histories()}}


def namespace(mr, name):
    status, body = mr.request("GET", f"/server/database/item?namespace={name}")
    assert status == 200, body
    return body["result"]["value"]


@pytest.fixture(scope="module")
def migrated(moonraker_venv, tmp_path_factory):
    """(Moonraker after the migration, its data directory, its site)."""
    site = tmp_path_factory.mktemp("site")
    copy_of_moonraker(moonraker_venv, site)
    data_dir = stack.short_tempdir("fl-migrate-")
    old = stack.Moonraker(moonraker_venv, data_dir, moonraker_path=site)
    try:
        old.wait_ready()
        assert "flowloop" not in old.request("GET", "/server/info")[1][
            "result"]["components"]
        for key, value in old_layout().items():
            status, body = old.request("POST", "/server/database/item", {
                "namespace": "flowloop", "key": key, "value": value})
            assert status == 200, body
        assert namespace(old, "flowloop") == old_layout()
    finally:
        old.stop()
    install.apply(install.plan_moonraker(site, stack.PROJECT))
    mr = stack.Moonraker(moonraker_venv, data_dir, moonraker_path=site,
                         extra_conf="hotend: v6-0.4\n")
    try:
        mr.wait_ready()
        yield mr, data_dir, site
    finally:
        mr.stop()
        shutil.rmtree(data_dir, ignore_errors=True)


def test_profiles_and_activations_are_served_as_they_were_stored(migrated):
    mr, _, _ = migrated
    assert namespace(mr, "flowloop") == {
        key: value for key, value in old_layout().items()
        if not key.startswith("nozzle_health:")}
    for name, stored in PROFILES.items():
        status, body = mr.request("GET", "/server/flowloop/profile?name="
                                  + quote(name, safe=""))
        assert status == 200, body
        assert body["result"]["profile"] == stored
    listed = mr.request("GET", "/server/flowloop/profiles")[1]["result"]
    assert listed["active"] == ACTIVE
    assert sorted(p["name"] for p in listed["profiles"]) == sorted(PROFILES)


def test_every_history_moves_to_its_own_namespace_whole(migrated):
    mr, _, _ = migrated
    assert namespace(mr, schema.NOZZLE_HEALTH_NAMESPACE) == {
        schema.nozzle_health_key(h["hotend"], h["profile"]): h for h in histories()}
    status, body = mr.request("GET", "/server/flowloop/nozzle_health")
    assert status == 200, body
    assert sorted(body["result"]["histories"], key=str) == sorted(histories(), key=str)
    assert namespace(mr, schema.SCHEMA_NAMESPACE) == {
        schema.PROFILES_NAMESPACE: schema.PROFILES_VERSION,
        schema.NOZZLE_HEALTH_NAMESPACE: schema.NOZZLE_HEALTH_VERSION}


def test_a_migrated_history_goes_on_with_the_next_print(migrated):
    mr, _, _ = migrated
    evidence = {**nh.evidence_of(simulate_print(0.86, seed=9), PROFILE).to_dict(),
                "profile": "known"}
    status, body = mr.request("POST", "/server/flowloop/nozzle_health",
                              {"job_id": "0000AA", "evidence": evidence})
    assert status == 200, body
    assert body["result"]["verdict"]["warn"] is True
    [history] = [h for h in mr.request("GET", "/server/flowloop/nozzle_health")[1][
        "result"]["histories"] if h["profile"] == "known"]
    assert history["prints"][:-1] == histories()[0]["prints"]
    assert history["prints"][-1]["job_id"] == "0000AA"
    # it warned before the migration: going on, it is not announced again
    assert histories()[0]["verdict"]["warn"] is True
    entries = mr.request("GET", "/server/announcements/list")[1]["result"]["entries"]
    assert [e for e in entries if e["feed"] == "flowloop"] == []


def test_the_database_api_cannot_write_the_new_namespaces(migrated):
    mr, _, _ = migrated
    for ns in (schema.NOZZLE_HEALTH_NAMESPACE, schema.SCHEMA_NAMESPACE):
        status, _ = mr.request("POST", "/server/database/item",
                               {"namespace": ns, "key": "x", "value": 1})
        assert status == 403, ns


def test_a_later_start_migrates_nothing_again(migrated, moonraker_venv):
    """Last in the module: it stops the module's Moonraker."""
    mr, data_dir, site = migrated
    assert mr.log_path.read_text().count(MIGRATING) == 2   # one per namespace
    before = {ns: namespace(mr, ns) for ns in (
        "flowloop", schema.NOZZLE_HEALTH_NAMESPACE, schema.SCHEMA_NAMESPACE)}
    mr.stop()
    mr.log_path.unlink()
    again = stack.Moonraker(moonraker_venv, data_dir, moonraker_path=site,
                            extra_conf="hotend: v6-0.4\n")
    try:
        again.wait_ready()
        assert MIGRATING not in again.log_path.read_text()
        assert {ns: namespace(again, ns) for ns in before} == before
    finally:
        again.stop()
