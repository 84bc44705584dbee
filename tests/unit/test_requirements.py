"""What klippy's flowloop sections ask of klippy's Python before they import
the core (flowloop.host.requirements): the first requirement missing, in one
line naming the package and the pip that installs it."""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

import pytest

from flowloop.host import requirements

pytestmark = pytest.mark.unit

PROJECT = Path(__file__).resolve().parents[2]


def test_the_requirements_are_pyprojects_dependencies():
    text = (PROJECT / "pyproject.toml").read_text()
    block = re.search(r"^dependencies = \[(.*?)\]", text, re.S | re.M).group(1)
    names = re.findall(r'"([A-Za-z0-9_.-]+)', block)
    assert tuple(name.lower() for name in names) == requirements.REQUIREMENTS


def test_a_python_with_them_all_lacks_nothing():
    assert requirements.missing() is None


@pytest.mark.parametrize("module", requirements.REQUIREMENTS)
def test_a_missing_requirement_is_one_line_naming_it_and_its_pip(
        monkeypatch, module):
    monkeypatch.setitem(sys.modules, module, None)   # an import of it fails
    line = requirements.missing("~/klippy-env/bin/python")
    assert "\n" not in line
    assert line.startswith(f"klippy's Python (~/klippy-env/bin/python) has no"
                           f" {module}, which flowloop needs:")
    assert f"run ~/klippy-env/bin/pip install {module} " in line


def test_the_check_imports_only_the_standard_library():
    # It runs before anything flowloop needs is known to be there
    tree = ast.parse(Path(requirements.__file__).read_text())
    imported = {alias.name.split(".")[0] for node in ast.walk(tree)
                if isinstance(node, ast.Import) for alias in node.names}
    imported |= {node.module.split(".")[0] for node in ast.walk(tree)
                 if isinstance(node, ast.ImportFrom) and node.module}
    assert imported <= set(sys.stdlib_module_names) | {"__future__"}
