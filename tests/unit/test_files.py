"""flowloop.files: a file is written whole or not at all."""

from __future__ import annotations

import os

import pytest

from flowloop import files
from flowloop.errors import FlowloopError


def test_a_new_file_is_written_whole_with_the_usual_mode(tmp_path):
    path = tmp_path / "report.html"
    files.write_text_atomically(path, "a\r\nb\n")
    assert path.read_bytes() == b"a\r\nb\n"      # no newline translation
    assert path.stat().st_mode & 0o777 == files.NEW_FILE_MODE
    assert [p.name for p in tmp_path.iterdir()] == ["report.html"]


def test_a_replaced_file_keeps_its_mode(tmp_path):
    path = tmp_path / "printer.cfg"
    path.write_text("old")
    os.chmod(path, 0o600)
    files.write_text_atomically(path, "new")
    assert path.read_text() == "new"
    assert path.stat().st_mode & 0o777 == 0o600


def test_a_write_that_fails_leaves_the_old_file_and_no_partial_one(tmp_path):
    path = tmp_path / "part.gcode"
    path.write_text("old")

    def full_disk(out):
        out.write(b"half")
        raise OSError(28, "No space left on device")
    with pytest.raises(OSError, match="No space left"):
        files.replace_atomically(path, full_disk)
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["part.gcode"]


def test_a_folder_that_is_not_there_is_one_line(tmp_path):
    with pytest.raises(FlowloopError, match=r"nowhere/x.json: cannot write: No such"):
        files.write_text_atomically(tmp_path / "nowhere" / "x.json", "{}")
