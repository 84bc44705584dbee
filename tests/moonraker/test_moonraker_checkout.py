"""The moonraker tier's representative part on Moonraker as KIAUH installs it:
a git checkout (MOONRAKER_PATH, default ~/moonraker) run from its source with
its own scripts/moonraker-requirements.txt, instead of Moonraker from PyPI.

The checkout is copied into the cache (devtools.stack.moonraker_checkout)
and flowloop installed into the copy as `flowloop install` installs it into
a checkout: the user's checkout is never written. Here: the component loads,
profiles are stored and served, an upload comes back annotated, and the
update manager sees the checkout clean with flowloop in it.
"""

from __future__ import annotations

import http.client
import json
import shutil
import subprocess
import urllib.request
from pathlib import Path
from urllib.parse import quote

import pytest

from devtools import stack
from flowloop.gcode.annotate import is_annotated
from tests.samples import make

DATA = Path(__file__).resolve().parents[1] / "data" / "gcode"
GCODE = DATA / "block_layers_1_2.gcode"
CONF = ("annotate_uploads: True\n\n[update_manager]\nenable_system_updates: False\n"
        "enable_auto_refresh: False\n")


def _git_status(path: Path) -> str:
    return subprocess.run(["git", "-C", str(path), "status", "--porcelain"],
                          capture_output=True, text=True, check=True).stdout


@pytest.fixture(scope="module")
def checkout():
    reason = stack.missing_moonraker_checkout_reason()
    if reason:
        pytest.skip("!!! " + reason)
    before = _git_status(stack.moonraker_checkout_path())
    built = stack.moonraker_checkout()
    yield built
    # Moonraker run from the copy wrote nothing into the user's checkout
    assert _git_status(stack.moonraker_checkout_path()) == before


@pytest.fixture(scope="module")
def moonraker(checkout):
    data_dir = stack.short_tempdir("fl-mrgit-")
    mr = stack.Moonraker(checkout.venv, data_dir, extra_conf=CONF,
                         script=checkout.script)
    try:
        mr.wait_ready()
        yield mr
    finally:
        mr.stop()
        shutil.rmtree(data_dir, ignore_errors=True)


def test_the_component_loads_from_the_checkout(checkout, moonraker):
    info = moonraker.request("GET", "/server/info")[1]["result"]
    assert "flowloop" in info["components"], moonraker.log_tail()
    assert "flowloop" not in info["failed_components"]
    # it ran the checkout's source, with the component linked into it
    assert (checkout.tree / "moonraker" / "components" / "flowloop").is_symlink()
    assert str(checkout.tree) in moonraker.log_path.read_text(errors="replace")


def test_a_profile_is_stored_and_served(moonraker):
    profile = make(name="git-pla")
    status, body = moonraker.request("POST", "/server/flowloop/profile",
                                     {"profile": profile})
    assert status == 200, body
    status, body = moonraker.request("GET", "/server/flowloop/profile?name=git-pla")
    assert status == 200, body
    assert body["result"]["profile"]["identity"]["name"] == "git-pla"


def test_a_refusal_naming_a_bracket_arrives_whole(moonraker):
    """Moonraker's own handler serves flowloop's endpoints in the checkout
    too: the refusal is the same line as reason phrase and body message,
    its quoted name JSON that decodes to the name."""
    conn = http.client.HTTPConnection("127.0.0.1", moonraker.port, timeout=10)
    try:
        conn.request("GET", "/server/flowloop/profile?name=PLA%20%3Cfast%3E")
        resp = conn.getresponse()
        status, reason, body = resp.status, resp.reason, json.loads(resp.read())
    finally:
        conn.close()
    assert (status, body["error"]["message"]) == (404, reason)
    assert json.loads(reason[len("no profile named "):]) == "PLA <fast>"


def test_nozzle_health_has_its_own_versioned_namespace(moonraker):
    status, body = moonraker.request(
        "GET", "/server/database/item?namespace=flowloop_schema")
    assert status == 200, body
    assert body["result"]["value"] == {"flowloop": 1, "flowloop_nozzle_health": 1}


def test_an_upload_comes_back_annotated(moonraker):
    moonraker.upload("git.gcode", GCODE.read_bytes())

    def processed():
        status, body = moonraker.request(
            "GET", "/server/files/metadata?filename=" + quote("git.gcode"))
        return status == 200 and body["result"].get("file_processors")
    assert stack.wait_until(processed, 120), moonraker.log_tail()
    with urllib.request.urlopen(moonraker.url + "/server/files/gcodes/git.gcode",
                                timeout=30) as resp:
        assert is_annotated(resp.read(4096))
    status, body = moonraker.request("POST", "/server/flowloop/annotation/check",
                                     timeout=90)
    assert status == 200 and body["result"]["ok"] is True, body


def test_the_update_manager_sees_the_checkout_clean_with_flowloop_in_it(
        checkout, moonraker):
    def status():
        code, body = moonraker.request("GET", "/machine/update/status")
        return body["result"]["version_info"].get("moonraker") if code == 200 \
            else None
    entry = stack.wait_until(status, 60, 1.0)
    assert entry, moonraker.log_tail()
    # flowloop's link in moonraker/components/ is excluded, not a change
    assert entry["is_dirty"] is False, entry
    assert entry.get("corrupt", False) is False, entry
    assert _git_status(checkout.tree) == ""
