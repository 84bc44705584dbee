"""`flowloop profile list|store|activate|remove` against a real Moonraker with
a batch-mode klippy behind it: the workflow the docs give ends at the CLI."""

from __future__ import annotations

import json

from devtools import stack
from flowloop.cli import main

WEAK = stack.PROJECT / "docs" / "examples" / "weak.json"


def flowloop(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_store_activate_list_remove_reach_the_printer(printer, capsys):
    # an address without http:// is Moonraker's host and port
    address = f"127.0.0.1:{printer.moonraker.port}"
    code, out, _ = flowloop(capsys, "profile", "store", str(WEAK), "--activate",
                            "--wp", "0.3", "--moonraker", address)
    assert code == 0
    assert out.splitlines() == [
        f'stored "weak" on http://{address}',
        '"weak" active on extruder at working point 0.3']
    # klippy holds it, as a print would use it
    active = printer.query("flowloop")["profiles"]["extruder"]
    assert (active["name"], active["working_point"]) == ("weak", 0.3)
    code, out, _ = flowloop(capsys, "profile", "list", "--moonraker", address)
    assert (code, out) == (0, '"weak": active on extruder at working point 0.3\n')

    code, out, _ = flowloop(capsys, "profile", "activate", "weak", "--wp", "0.6",
                            "--moonraker", f"http://{address}/")
    assert (code, out) == (0, '"weak" active on extruder at working point 0.6\n')

    code, out, _ = flowloop(capsys, "profile", "remove", "weak", "--moonraker",
                            address)
    assert (code, out) == (0, f'removed "weak" from http://{address}\n')
    status, body = printer.moonraker.request("GET", "/server/flowloop/profiles")
    assert body["result"]["profiles"] == [] and body["result"]["active"] == {}


def test_a_refusal_is_moonrakers_one_line_and_changes_nothing(printer, capsys):
    address = f"127.0.0.1:{printer.moonraker.port}"
    code, out, err = flowloop(capsys, "profile", "activate", "no-such",
                              "--moonraker", address)
    assert code == 2 and out == ""
    assert err == (f'flowloop profile: error: http://{address}: HTTP 404 no profile'
                   f' named "no-such"\n')
    code, _, err = flowloop(capsys, "profile", "activate", "x", "--extruder",
                            "nozzle", "--moonraker", address)
    assert code == 2 and "is not an extruder name" in err
    assert len(err.splitlines()) == 1
    # an extruder this printer does not have: klippy refuses, and the line
    # says the profile was stored but is not active
    code, out, err = flowloop(capsys, "profile", "store", str(WEAK), "--activate",
                              "extruder7", "--moonraker", address)
    assert code == 2 and out.startswith('stored "weak"')
    assert err.startswith(f"flowloop profile: error: stored, but not active:"
                          f" http://{address}: HTTP 400 ")
    status, body = printer.moonraker.request("GET", "/server/flowloop/profiles")
    assert "extruder7" not in body["result"]["active"]
    flowloop(capsys, "profile", "remove", "weak", "--moonraker", address)


def test_no_moonraker_there_is_one_line(capsys):
    code, _, err = flowloop(capsys, "profile", "list", "--moonraker",
                            f"127.0.0.1:{stack.free_port()}")
    assert code == 2
    assert "no answer from Moonraker" in err and len(err.splitlines()) == 1


def test_a_file_that_is_no_profile_is_refused_before_anything_is_sent(
        printer, capsys, tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"identity": {"name": "x"}}))
    code, _, err = flowloop(capsys, "profile", "store", str(bad), "--moonraker",
                            f"127.0.0.1:{printer.moonraker.port}")
    assert code == 2 and str(bad) in err
    status, body = printer.moonraker.request("GET", "/server/flowloop/profiles")
    assert "x" not in [p["name"] for p in body["result"]["profiles"]]
