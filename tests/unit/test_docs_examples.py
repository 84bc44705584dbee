"""The docs' worked examples, run as the docs give them, from files the
repository ships: the output and the figures in the prose are what runs."""

from __future__ import annotations

import os
import re
import shlex
from pathlib import Path

from flowloop.cli import main

ROOT = Path(__file__).resolve().parents[2]


def _example(doc: str, heading: str):
    """The `$ flowloop ...` line under a heading and the output after it."""
    text = (ROOT / "docs" / doc).read_text()
    section = text.split(heading, 1)[1]
    lines = section.splitlines()
    i = next(k for k, x in enumerate(lines) if x.startswith("    $ flowloop "))
    output = []
    for line in lines[i + 1:]:
        if not line.startswith("    "):
            break
        output.append(line[4:])
    return section, lines[i][len("    $ "):], output


def _run(command: str, tmp_path: Path, capsys) -> str:
    """Run a documented command from a copy of the repository's top: its
    inputs are read from the repository, its outputs land in tmp_path."""
    for name in ("tests", "docs"):
        (tmp_path / name).symlink_to(ROOT / name)
    old = os.getcwd()
    os.chdir(tmp_path)
    try:
        assert main(shlex.split(command)[1:]) == 0
    finally:
        os.chdir(old)
    return capsys.readouterr().out


def test_the_autotemp_bake_worked_example(tmp_path, capsys):
    section, command, output = _example("autotemp.md", "### Worked example")
    assert _run(command, tmp_path, capsys).splitlines() == output
    # the targets the prose lists, in order, are the file's M104
    listed = re.search(r"in order: \*\*([0-9,\s]+)\*\*", section)[1]
    written = re.findall(r"^M104 S(\d+)$", (tmp_path / "block_baked.gcode")
                         .read_text(), re.M)
    assert [int(x) for x in listed.split(",")] == [int(x) for x in written]
    # the print starts at the raised wait
    assert "M109 S227 ; flowloop bake: was M109 S200" in (
        tmp_path / "block_baked.gcode").read_text()
