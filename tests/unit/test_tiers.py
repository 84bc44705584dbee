"""Each tier is a marker `-m` selects (README, test tiers): the markers are
set before -m filters, whatever else reorders the collection."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

PROJECT = Path(__file__).resolve().parents[2]


def collected(*args):
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q",
         "-p", "no:cacheprovider", *args],
        cwd=PROJECT, capture_output=True, text=True, timeout=120)
    return [line for line in proc.stdout.splitlines() if "::" in line]


@pytest.mark.parametrize("tier", ["bench", "c", "klippy", "ui"])
def test_a_tier_marker_selects_that_folder_and_nothing_else(tier):
    # another tier's file beside it: -m must leave that one out
    ids = collected("-m", tier, f"tests/{tier}", "tests/unit/test_numbers.py")
    assert ids, f"-m {tier} selected nothing"
    assert all(i.startswith(f"tests/{tier}/") for i in ids), ids[:3]


def test_host_venvs_are_keyed_on_the_package_not_on_the_tools_settings(
        tmp_path, monkeypatch):
    from devtools import stack
    text = (PROJECT / "pyproject.toml").read_text()
    monkeypatch.setattr(stack, "PROJECT", tmp_path)
    (tmp_path / "pyproject.toml").write_text(text)
    before = stack._install_metadata()
    (tmp_path / "pyproject.toml").write_text(
        text.replace('markers = [', 'markers = [\n    "new: a marker",'))
    assert stack._install_metadata() == before
    (tmp_path / "pyproject.toml").write_text(
        text.replace('"numpy>=1.20"', '"numpy>=1.21"'))
    assert stack._install_metadata() != before


def test_an_unknown_host_is_refused_in_one_line():
    proc = subprocess.run(
        [sys.executable, "-c", "import devtools.stack"], cwd=PROJECT,
        capture_output=True, text=True, timeout=60,
        env={"PATH": "/usr/bin:/bin", "FLOWLOOP_HOSTS": "klipper marlin"})
    assert proc.returncode != 0
    assert proc.stderr.strip().splitlines()[-1] == (
        "FLOWLOOP_HOSTS: marlin is not one of klipper, kalico")


def test_a_build_in_use_is_spared_when_another_checkout_prunes(tmp_path,
                                                               monkeypatch):
    """A second checkout's build prunes all but the newest few builds: the
    one a running make test reuses must count as new (it was pruned once,
    and that run's klippy tests errored)."""
    import os

    from devtools import stack
    monkeypatch.setattr(stack, "cache_dir", lambda: tmp_path)
    monkeypatch.setattr(stack, "klipper_key", lambda source, host: "0" * 16)
    in_use = tmp_path / f"klipper-{'0' * 16}"
    stale = [tmp_path / f"klipper-{k}{'0' * 15}" for k in "abc"]
    for age, tree in enumerate([in_use] + stale):
        tree.mkdir()
        (tree / ".flowloop-ready").write_text("")
        os.utime(tree, (1000.0 + age, 1000.0 + age))   # in_use the oldest
    stack.build_klipper()                              # the running suite
    new = tmp_path / f"klipper-{'f' * 16}"
    new.mkdir()
    stack._prune(tmp_path.glob("klipper-[0-9a-f]*"), keep=new)
    assert in_use.is_dir()
    assert sum(tree.is_dir() for tree in stale) == 1


GROUPS_PLUGIN = '''
import json

def pytest_collection_finish(session):
    from tests import conftest
    groups = conftest._xdist_groups(session.items)
    print("GROUPS " + json.dumps({i.nodeid: g for i, g in groups.items()}))
'''


def test_every_test_of_the_simulated_mcu_runs_quiet(tmp_path):
    """make test's scheduler runs a test that starts the fil tier's
    simulated MCU with nothing beside it, wherever the test lives (a bench's
    smoke run too); a paced klippy test runs alone, beside idle-class ones."""
    (tmp_path / "groups_plugin.py").write_text(GROUPS_PLUGIN)
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q",
         "-p", "no:cacheprovider", "-p", "groups_plugin",
         "tests/bench/bench_fil.py", "tests/fil/test_fil_sensor.py",
         "tests/bench/bench_realtime_klippy.py"],
        cwd=PROJECT, capture_output=True, text=True, timeout=120,
        env={**os.environ, "PYTHONPATH": str(tmp_path)})
    line = next((x for x in proc.stdout.splitlines() if x.startswith("GROUPS ")),
                None)
    assert line, proc.stdout[-2000:] + proc.stderr[-2000:]
    groups = json.loads(line[len("GROUPS "):])
    fil = {k: g for k, g in groups.items() if "bench_fil" in k or "tests/fil/" in k}
    paced = {k: g for k, g in groups.items() if "bench_realtime_klippy" in k}
    assert any("bench_fil" in k for k in fil) and paced, groups
    assert all(g.startswith("quiet:") for g in fil.values()), fil
    assert all(g.startswith("alone:") for g in paced.values()), paced
