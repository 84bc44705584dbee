"""The flowloop command: --help everywhere, one-line errors."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from flowloop import __version__, cli


def subcommands():
    parser = cli.build_parser()
    action = next(a for a in parser._actions
                  if isinstance(a, argparse._SubParsersAction))
    return sorted(action.choices)


@pytest.mark.parametrize("name", subcommands())
def test_every_subcommand_has_help(name, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main([name, "--help"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith("usage: flowloop " + name)


def test_the_console_script_is_installed_and_reports_its_version():
    exe = str(Path(sys.executable).parent / "flowloop")
    out = subprocess.run([exe, "--version"], capture_output=True, text=True)
    assert out.stdout.strip() == f"flowloop {__version__}"


def test_info_names_an_unreachable_moonraker_in_one_line(capsys):
    assert cli.main(["info", "--moonraker", "http://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("flowloop info: error: http://127.0.0.1:9: cannot reach")
    assert "\n" not in err
