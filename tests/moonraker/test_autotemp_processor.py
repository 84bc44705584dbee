"""The moonraker tier: a G-code upload through Moonraker's file API comes
back annotated for [autotemp], once, with its metadata; a file the annotator
refuses stays as it was, printable."""

from __future__ import annotations

import shutil
import urllib.request
from pathlib import Path
from urllib.parse import quote

from devtools import stack
from flowloop.cli import main
from flowloop.gcode import ahead
from flowloop.gcode.annotate import annotate_file, is_annotated
from flowloop.gcode.bulk_planner import PROCESS_FROM_BYTES

DATA = Path(__file__).resolve().parents[1] / "data" / "gcode"
GCODE = DATA / "block_layers_1_2.gcode"
# the printer fixture (tests/moonraker/conftest.py): Moonraker alone
PRINTER_STACK = {"with_klippy": False, "moonraker_conf": "annotate_uploads: True"}


def metadata(moonraker, name: str):
    status, body = moonraker.request(
        "GET", "/server/files/metadata?filename=" + quote(name))
    return body["result"] if status == 200 else None


def download(moonraker, name: str) -> bytes:
    with urllib.request.urlopen(moonraker.url + "/server/files/gcodes/"
                                + quote(name), timeout=30) as resp:
        return resp.read()


def test_an_upload_comes_back_annotated_once_with_its_metadata(printer):
    m = printer.moonraker
    assert m.upload("block.gcode", GCODE.read_bytes())["item"]["path"] == "block.gcode"
    assert stack.wait_until(lambda: (metadata(m, "block.gcode") or {}).get(
        "file_processors"), 120)
    meta = metadata(m, "block.gcode")
    assert "flowloop_autotemp" in meta["file_processors"]
    assert meta["slicer"] == "PrusaSlicer"          # the slicer's data is kept
    first = download(m, "block.gcode")
    assert is_annotated(first[:4096])
    assert first.count(b"\nAUTOTEMP_FLOW ") > 3
    status, body = m.request("GET", "/server/flowloop/annotation?filename=block.gcode")
    assert status == 200
    info = body["result"]
    assert info["annotated"] is True and info["processed"] is True
    assert info["peak_flow"] > 0 and info["windows"] > 3
    # a rescan runs the processors again: the marker keeps the file as it is
    status, _ = m.request("POST", "/server/files/metascan?filename=block.gcode",
                          timeout=120)
    assert status == 200
    assert download(m, "block.gcode") == first
    assert "flowloop_autotemp" in metadata(m, "block.gcode")["file_processors"]


def test_a_large_upload_planned_in_a_child_process_comes_back_as_planned_here(
        printer, tmp_path, monkeypatch):
    # a file of PROCESS_FROM_BYTES or more: in Moonraker's processor run the
    # planner runs in a process of its own (flowloop.gcode.ahead)
    excerpt = GCODE.read_bytes()
    body = excerpt.index(b";LAYER_CHANGE")
    layers = b"G92 E0\n" + excerpt[body:]
    data = excerpt[:body] + layers * (PROCESS_FROM_BYTES // len(layers) + 1)
    assert len(data) >= PROCESS_FROM_BYTES
    m = printer.moonraker
    m.upload("large.gcode", data)
    assert stack.wait_until(lambda: (metadata(m, "large.gcode") or {}).get(
        "file_processors"), 120)
    uploaded = download(m, "large.gcode")
    assert is_annotated(uploaded[:4096])
    # the same file annotated here, the planner in a thread
    monkeypatch.setattr(ahead, "can_fork", lambda: False)
    here = tmp_path / "large.gcode"
    here.write_bytes(data)
    annotate_file(here)
    assert uploaded == here.read_bytes()


def test_a_file_the_annotator_refuses_stays_printable_and_says_so(printer):
    m = printer.moonraker
    data = GCODE.read_bytes().replace(b"G1 Z5 F5000", b"G1 Z5.5.5 F5000", 1)
    assert data != GCODE.read_bytes()
    assert m.upload("bad.gcode", data)["item"]["path"] == "bad.gcode"
    assert stack.wait_until(lambda: metadata(m, "bad.gcode") is not None, 120)
    assert download(m, "bad.gcode") == data            # untouched
    meta = metadata(m, "bad.gcode")
    assert "flowloop_autotemp" not in meta.get("file_processors", [])
    info = m.request("GET", "/server/flowloop/annotation?filename=bad.gcode")[1][
        "result"]
    assert info["annotated"] is False and info["peak_flow"] is None
    log = (printer.data_dir / "moonraker.log").read_text(errors="replace")
    assert "flowloop_autotemp failed" in log


def test_an_unknown_file_is_a_404(printer):
    status, body = printer.moonraker.request(
        "GET", "/server/flowloop/annotation?filename=../moonraker.conf")
    assert status == 404


def test_flowloop_info_names_the_registered_processor(printer):
    # what `flowloop doctor`'s "gcode processor" check reads
    status, body = printer.moonraker.request("GET", "/server/flowloop/info")
    assert status == 200, body
    assert body["result"]["gcode_processor"] == "flowloop_autotemp"


def test_moonraker_started_from_a_home_holding_the_clone_annotates_uploads(
        moonraker_venv, capsys):
    # `python -m moonraker` from a folder with flowloop/ in it (the clone):
    # the component loads, uploads are annotated, the check says so
    home = stack.short_tempdir("fl-home-")
    (home / "flowloop" / "flowloop").mkdir(parents=True)
    data_dir = home / "printer_data"
    mr = stack.Moonraker(moonraker_venv, data_dir,
                         extra_conf="annotate_uploads: True", cwd=home)
    try:
        mr.wait_ready()
        info = mr.request("GET", "/server/info")[1]["result"]
        assert "flowloop" in info["components"], mr.log_tail()
        mr.upload("home.gcode", GCODE.read_bytes())
        assert stack.wait_until(lambda: (metadata(mr, "home.gcode") or {}).get(
            "file_processors"), 120)
        assert is_annotated(download(mr, "home.gcode")[:4096]), mr.log_tail()
        status, body = mr.request("POST", "/server/flowloop/annotation/check",
                                  timeout=90)
        assert status == 200, body
        check = body["result"]
        assert check["ok"] is True and check["message"] is None, check
        assert check["cwd"] == str(home) and "-m" in check["command"]
        # doctor asks Moonraker to run it, and says it ran
        capsys.readouterr()
        main(["doctor", "--moonraker", mr.url])
        out = capsys.readouterr().out
        line = next(x for x in out.splitlines() if " gcode processor:" in x)
        assert line.startswith("ok") and "annotates a test file" in line, out
    finally:
        mr.stop()
        shutil.rmtree(home, ignore_errors=True)


def test_the_check_says_when_uploads_are_not_annotated(moonraker_venv):
    data_dir = stack.short_tempdir("fl-off-")
    mr = stack.Moonraker(moonraker_venv, data_dir)
    try:
        mr.wait_ready()
        status, body = mr.request("POST", "/server/flowloop/annotation/check")
        assert status == 200, body
        assert body["result"]["ok"] is False
        assert body["result"]["message"] == ("annotate_uploads is off: uploads"
                                             " are not annotated")
    finally:
        mr.stop()
        shutil.rmtree(data_dir, ignore_errors=True)
