"""What runs inside klippy must run on the oldest Python flowloop supports
(3.9: Raspberry Pi OS Bullseye's klippy-env). Moonraker 0.11 itself needs
3.10, so its component is held to that."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PROJECT = Path(__file__).resolve().parents[2]
VERMIN = Path(sys.executable).parent / "vermin"
KLIPPY_SIDE = ["flowloop", "klippy_extras"]


@pytest.mark.parametrize("paths, floor", [
    (KLIPPY_SIDE, "3.9"),
    (["moonraker_components"], "3.10"),
])
def test_code_runs_on_the_oldest_supported_python(paths, floor):
    if not VERMIN.exists():
        pytest.skip("vermin is not installed (pip install -e '.[dev]')")
    proc = subprocess.run([str(VERMIN), "--no-tips", "--eval-annotations",
                           "--backport", "typing", "--violations", f"-t={floor}-",
                           *paths], cwd=PROJECT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def union_annotations(tree: ast.AST):
    """Line numbers of `X | Y` inside annotations (needs 3.10 when evaluated,
    and msgspec evaluates them even under `from __future__ import annotations`)."""
    notes = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            args = node.args
            notes += [a.annotation for a in args.posonlyargs + args.args
                      + args.kwonlyargs + [args.vararg, args.kwarg]
                      if a is not None and a.annotation is not None]
            notes.append(node.returns)
        elif isinstance(node, ast.AnnAssign):
            notes.append(node.annotation)
    return sorted(sub.lineno for note in notes if note is not None
                  for sub in ast.walk(note)
                  if isinstance(sub, ast.BinOp) and isinstance(sub.op, ast.BitOr))


def test_annotations_use_optional_not_union_operator():
    files = sorted(path for folder in KLIPPY_SIDE
                   for path in (PROJECT / folder).rglob("*.py"))
    found = [f"{path.relative_to(PROJECT)}:{line}" for path in files
             for line in union_annotations(ast.parse(path.read_text()))]
    assert not found


def test_the_union_check_sees_a_union():
    assert union_annotations(ast.parse("def f(x: int | None) -> None: pass")) == [1]
    assert union_annotations(ast.parse("y = 1 | 2\nz: int = 3")) == []
