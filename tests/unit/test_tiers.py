"""Each tier is a marker `-m` selects (README, test tiers): the markers are
set before -m filters, whatever else reorders the collection."""

from __future__ import annotations

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


@pytest.mark.parametrize("tier", ["bench", "c", "klippy"])
def test_a_tier_marker_selects_that_folder_and_nothing_else(tier):
    ids = collected("-m", tier, f"tests/{tier}", "tests/c")
    assert ids, f"-m {tier} selected nothing"
    assert all(i.startswith(f"tests/{tier}/") for i in ids), ids[:3]
