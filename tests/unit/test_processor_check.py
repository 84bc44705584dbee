"""The upload annotator runs from any working directory, and the check
`flowloop doctor` asks for says in one line why it does not."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from flowloop.host.processor_check import (
    FILE_ARG,
    check_processor,
    isolation_flag,
    moonraker_arglist,
    processor_command,
)

pytestmark = pytest.mark.unit


@pytest.fixture
def home_with_clone(tmp_path: Path) -> Path:
    """A working directory holding a folder named flowloop/ (a home after
    `git clone ... flowloop`): `-m` would import it as a namespace package."""
    (tmp_path / "flowloop" / "docs").mkdir(parents=True)
    return tmp_path


def test_python_m_flowloop_runs_from_a_folder_holding_a_flowloop_folder(
        home_with_clone):
    proc = subprocess.run([sys.executable, "-m", "flowloop", "--version"],
                          cwd=home_with_clone, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("flowloop ")


def test_the_upload_annotator_annotates_from_a_folder_holding_a_flowloop_folder(
        home_with_clone):
    command = processor_command(sys.executable)
    assert command[1] == isolation_flag() and command[-1] == FILE_ARG
    assert check_processor(command, cwd=str(home_with_clone)) is None


def test_the_working_directory_is_kept_off_sys_path_on_every_python():
    assert isolation_flag((3, 11, 0)) == "-P"
    assert isolation_flag((3, 9, 18)) == "-I"


def test_a_processor_that_fails_is_named_in_one_line_with_its_error(
        home_with_clone):
    command = [sys.executable, "-c", "import sys; sys.stderr.write('Traceback:"
               "\\n  x\\nImportError: cannot import name __version__\\n');"
               " sys.exit(1)", FILE_ARG]
    message = check_processor(command, cwd=str(home_with_clone))
    assert "\n" not in message
    assert "exit 1" in message and str(home_with_clone) in message
    assert message.count("ImportError: cannot import name __version__") == 1
    assert "a folder named flowloop/" in message


def test_a_processor_that_leaves_the_file_as_it_was_fails_the_check():
    message = check_processor([sys.executable, "-c", "pass", FILE_ARG])
    assert message == ("the G-code processor exits 0 but leaves the file"
                       " unannotated: it is not flowloop annotate")


def test_a_processor_that_cannot_start_or_hangs_says_so(tmp_path):
    assert "cannot start" in check_processor([str(tmp_path / "nope"), FILE_ARG])
    assert "ran over 0.5 s" in check_processor(
        [sys.executable, "-c", "import time; time.sleep(5)"], timeout_s=0.5)


def test_a_command_string_is_split_as_moonraker_splits_it():
    assert moonraker_arglist("py -m 'flow loop' {gcode_file_path}", "/a b.gcode") \
        == ["py", "-m", "flow loop", "/a b.gcode"]
