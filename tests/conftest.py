"""Test tiers (DESIGN.md): the folder a test lives in is its tier marker.

klippy and moonraker tiers use the real hosts through devtools.stack; without
a Klipper checkout they are skipped with one loud line saying why.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest

PROJECT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(PROJECT))

from devtools import stack  # noqa: E402
from devtools.klippy_test import KlippyTestFailure, run_file  # noqa: E402

TIERS = ("unit", "c", "klippy", "moonraker", "bench")


def pytest_collection_modifyitems(config, items):
    for item in items:
        parts = Path(str(item.fspath)).relative_to(PROJECT).parts
        if len(parts) > 2 and parts[0] == "tests" and parts[1] in TIERS:
            item.add_marker(getattr(pytest.mark, parts[1]))


def pytest_report_header(config):
    reason = stack.missing_klipper_reason()
    if reason:
        return "!" * 78 + "\n!!! " + reason + "\n" + "!" * 78
    return f"klipper: {stack.klipper_path()}"


def pytest_terminal_summary(terminalreporter):
    reason = stack.missing_klipper_reason()
    if reason:
        terminalreporter.write_line("!!! " + reason, red=True, bold=True)


def skip_without_klipper() -> None:
    # The loud explanation is printed once, in the header and the summary.
    if stack.missing_klipper_reason():
        pytest.skip(f"no Klipper checkout at {stack.klipper_path()}")


@pytest.fixture(scope="session")
def klipper_build():
    skip_without_klipper()
    return stack.build_klipper()


@pytest.fixture(scope="session")
def klippy_venv(klipper_build):
    return stack.klippy_venv()


@pytest.fixture(scope="session")
def moonraker_venv():
    return stack.moonraker_venv()


@pytest.fixture
def short_tmp():
    path = stack.short_tempdir("fl-")
    yield path
    shutil.rmtree(path, ignore_errors=True)


# --- tests/klippy/*.test: one pytest item per file ---------------------------

def pytest_collect_file(parent, file_path):
    if file_path.suffix == ".test" and file_path.parent.name == "klippy":
        return KlippyTestFile.from_parent(parent, path=file_path)
    return None


class KlippyTestFile(pytest.File):
    def collect(self):
        yield KlippyTestItem.from_parent(self, name=self.path.name)


class KlippyTestItem(pytest.Item):
    def __init__(self, **kw):
        super().__init__(**kw)
        self.add_marker(pytest.mark.klippy)

    def runtest(self):
        build, venv = _session_build()
        workdir = stack.short_tempdir("fl-test-")
        try:
            run_file(self.path, build, venv, workdir)
        finally:
            shutil.rmtree(workdir, ignore_errors=True)

    def repr_failure(self, excinfo):
        if isinstance(excinfo.value, KlippyTestFailure):
            return str(excinfo.value)
        return super().repr_failure(excinfo)

    def reportinfo(self):
        return self.path, 0, f"klippy: {self.name}"


_BUILD = None


def _session_build():
    global _BUILD
    skip_without_klipper()
    if _BUILD is None:
        _BUILD = (stack.build_klipper(), stack.klippy_venv())
    return _BUILD
